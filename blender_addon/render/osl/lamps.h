// FlowBSDF OSL: Blender's lamps, with Cycles' radiometry (kernel/light/*.h, scene/light.cpp):
// strength S = colour x energy x 2^exposure (the node passes colour and energy x 2^exposure);
// point and spot: radius 0 -> intensity S / 4 pi; radius r -> a disk of radius r facing the
// shading point (soft falloff, Blender's default) or a sphere (soft falloff off), radiance
// S / (4 pi^2 r^2) (S / pi without Normalize); spot: times smoothstep((cos a - cos(size / 2)) /
// ((1 - cos(size / 2)) blend)), a measured in the lamp's scaled frame; sun: angle 0 ->
// irradiance S cos, else a cone of half-angle angle / 2, radiance S / (pi sin^2(angle / 2));
// area: one-sided toward local -Z, radiance S / (pi A) (A with the object's scale; pi / 4 of
// the box for disk and ellipse), times the spread factor below 180 degrees.
//
// Per lamp: lamp_sample (next-event estimation: a direction toward the lamp and its solid-angle
// pdf, 0 for delta lamps; rectangles uniformly in solid angle, disks and ellipses by area) and lamp_hit (does a direction from P reach the lamp, its radiance
// and the pdf lamp_sample would have given it), consistent with each other.

#define LAMP_POINT 1
#define LAMP_SPOT 2
#define LAMP_SUN 3
#define LAMP_RECT 4
#define LAMP_ELLIPSE 5

#define LAMP_SHADOW 1       // casts shadows (NEE traces a shadow ray)
#define LAMP_MIS 2          // Cycles' "Multiple Importance": its own rays may hit the lamp
#define LAMP_CAMERA 4       // ray visibility: camera, diffuse, glossy
#define LAMP_DIFFUSE 8
#define LAMP_GLOSSY 16
#define LAMP_SPHERE 32      // point / spot without soft falloff: a sphere, not a facing disk
#define LAMP_NORMALIZE 64

#define FAR 1e30

struct Lamp {
    int kind;
    int flags;
    point co;           // location
    vector X, Y, Z;     // the object's axes, scale included
    color S;            // strength
    vector size;        // point/spot (radius, spot size, blend); sun (angle, 0, 0); area (size x, size y, spread)
};

int has_flag(Lamp L, int f) { return (L.flags & f) != 0; }

// A lamp that Cycles' rays (and the shader's own hit test) can hit: it has a size.
int is_shaped(Lamp L)
{
    if (L.kind == LAMP_POINT || L.kind == LAMP_SPOT || L.kind == LAMP_SUN)
        return L.size[0] > 0.0;
    return L.kind == LAMP_RECT || L.kind == LAMP_ELLIPSE;
}

float one_minus_cos_from_sin2(float s2)
{
    return (s2 < 1e-4) ? s2 * (0.5 + 0.125 * s2) : 1.0 - sqrt(max(1.0 - s2, 0.0));
}

// v in the lamp's frame: [X Y Z]^-1 v.
vector lamp_local(Lamp L, vector v)
{
    vector yz = cross(L.Y, L.Z), zx = cross(L.Z, L.X), xy = cross(L.X, L.Y);
    return vector(dot(v, yz), dot(v, zx), dot(v, xy)) / dot(L.X, yz);
}

float smoothstep01(float x)
{
    if (x <= 0.0) return 0.0;
    if (x >= 1.0) return 1.0;
    return x * x * (3.0 - 2.0 * x);
}

// The spot's falloff for light leaving the lamp along `away`.
float spot_attenuation(Lamp L, vector away)
{
    vector d = normalize(lamp_local(L, away));
    float z = -d[2];
    float ch = cos(0.5 * L.size[1]);
    float blend = L.size[2];
    if (blend <= 0.0)
        return (z > ch) ? 1.0 : 0.0;
    return smoothstep01((z - ch) / ((1.0 - ch) * blend));
}

color point_radiance(Lamp L)
{
    float r = L.size[0];
    if (r == 0.0)
        return L.S / (4.0 * M_PI);        // an intensity
    return has_flag(L, LAMP_NORMALIZE) ? L.S / (4.0 * M_PI * M_PI * r * r) : L.S / M_PI;
}

float sun_half_angle(Lamp L) { return 0.5 * L.size[0]; }

color sun_radiance(Lamp L)
{
    float s = sin_small(sun_half_angle(L));
    return (has_flag(L, LAMP_NORMALIZE) && s > 0.0) ? L.S / (M_PI * s * s) : L.S;
}

// Area lamps: unit axes, side lengths, normal (the emitting side) and area.
void area_frame(Lamp L, output vector au, output vector av, output float lu, output float lv,
                output vector ng, output float area)
{
    lu = length(L.X) * L.size[0];
    lv = length(L.Y) * L.size[1];
    au = normalize(L.X);
    av = normalize(L.Y);
    ng = normalize(-L.Z);
    area = lu * lv * ((L.kind == LAMP_ELLIPSE) ? M_PI / 4.0 : 1.0);
}

// Cycles' area spread: the share of a soft box's grid a direction passes, normalised.
float spread_attenuation(Lamp L, vector dir, vector ng)
{
    float spread = L.size[2];
    if (spread >= M_PI)
        return 1.0;
    float half = 0.5 * max(spread, 0.0);
    float c = -dot(dir, ng);
    float tan_a = sqrt(max(1.0 - c * c, 0.0)) / max(c, 1e-12);
    float tan_h = tan(half);
    float norm = (half > 0.05) ? 1.0 / (tan_h - half) : 3.0 / (half * half * half);
    return max((tan_h - tan_a) * norm, 0.0);
}

color area_radiance(Lamp L, vector dir, vector ng, float area)
{
    color Le = has_flag(L, LAMP_NORMALIZE) ? L.S / (M_PI * area) : L.S / M_PI;
    return Le * spread_attenuation(L, dir, ng);
}

// A rectangle as seen from Pp, for sampling it uniformly in solid angle (the spherical
// rectangle of Urena, Fajardo and King 2013, as Cycles samples its rectangular lamps): the
// corner's coordinates in the rectangle's frame (x0, y0 to x1, y1, depth z0 < 0), the frame
// (ex, ey, ez toward Pp's far side), and what the warp needs (b0, b1, k); returns the solid angle.
float rect_solid_angle(point Pp, point corner, vector ex, vector ey, float lx, float ly,
                       output float x0, output float y0, output float x1, output float y1,
                       output float z0, output vector ez, output float b0, output float b1, output float k)
{
    ez = cross(ex, ey);
    vector d = corner - Pp;
    z0 = dot(d, ez);
    if (z0 > 0.0) {
        ez = -ez;
        z0 = -z0;
    }
    x0 = dot(d, ex);
    y0 = dot(d, ey);
    x1 = x0 + lx;
    y1 = y0 + ly;
    vector v00 = vector(x0, y0, z0), v01 = vector(x0, y1, z0), v10 = vector(x1, y0, z0), v11 = vector(x1, y1, z0);
    vector n0 = normalize(cross(v00, v10)), n1 = normalize(cross(v10, v11));
    vector n2 = normalize(cross(v11, v01)), n3 = normalize(cross(v01, v00));
    float g0 = acos(clamp(-dot(n0, n1), -1.0, 1.0)), g1 = acos(clamp(-dot(n1, n2), -1.0, 1.0));
    float g2 = acos(clamp(-dot(n2, n3), -1.0, 1.0)), g3 = acos(clamp(-dot(n3, n0), -1.0, 1.0));
    b0 = n0[2];
    b1 = n2[2];
    k = 2.0 * M_PI - g2 - g3;
    return g0 + g1 - k;
}

// The point of the spherical rectangle (rect_solid_angle's outputs) for (u0, u1), uniform in
// its solid angle S, relative to Pp in the frame (ex, ey, ez).
vector rect_solid_angle_offset(float S, float x0, float y0, float x1, float y1, float z0,
                               float b0, float b1, float k, float u0, float u1)
{
    float au = u0 * S + k;
    float fu = (cos(au) * b0 - b1) / sin(au);
    float cu = clamp(((fu > 0.0) ? 1.0 : -1.0) / sqrt(fu * fu + b0 * b0), -1.0, 1.0);
    float xu = clamp(-(cu * z0) / max(sqrt(1.0 - cu * cu), 1e-7), x0, x1);
    float d = sqrt(xu * xu + z0 * z0);
    float h0 = y0 / sqrt(d * d + y0 * y0), h1 = y1 / sqrt(d * d + y1 * y1);
    float hv = h0 + u1 * (h1 - h0);
    float yv = (hv * hv < 1.0 - 1e-6) ? hv * d / sqrt(1.0 - hv * hv) : y1;
    return vector(xu, clamp(yv, y0, y1), z0);
}

// Whether the ray P + t dir (t > 0) reaches lamp L: distance, radiance arriving along it, the
// solid-angle pdf lamp_sample gives that direction, and where the ray leaves the lamp again
// (a sphere's far side: a ray started between the two would still hit it).
int lamp_hit(Lamp L, point Pp, vector dir, output float t, output color Le, output float pdf,
             output float t_exit)
{
    t = FAR;
    t_exit = FAR;
    Le = 0;
    pdf = 0;
    if (!is_shaped(L))
        return 0;
    if (L.kind == LAMP_SUN) {
        float h = sun_half_angle(L);
        if (!in_cone_angle(dir, normalize(L.Z), h))
            return 0;
        Le = sun_radiance(L);
        pdf = 1.0 / (2.0 * M_PI * one_minus_cos(h));
        return 1;
    }
    if (L.kind == LAMP_POINT || L.kind == LAMP_SPOT) {
        float r = L.size[0];
        vector oc = L.co - Pp;
        float d2 = dot(oc, oc);
        if (d2 <= r * r)
            return 0;
        if (has_flag(L, LAMP_SPHERE)) {
            float b = dot(oc, dir);
            float disc = b * b - (d2 - r * r);
            if (disc < 0.0 || b <= 0.0)
                return 0;
            t = b - sqrt(disc);
            t_exit = b + sqrt(disc);
            pdf = 1.0 / (2.0 * M_PI * one_minus_cos_from_sin2(r * r / d2));
        } else {
            vector n = -oc / sqrt(d2);          // the disk faces the shading point
            float cos_l = -dot(dir, n);
            if (cos_l <= 0.0)
                return 0;
            t = dot(oc, -n) / cos_l;
            vector q = Pp + t * dir - L.co;
            if (dot(q, q) > r * r)
                return 0;
            pdf = t * t / (cos_l * M_PI * r * r);
            t_exit = t;
        }
        Le = point_radiance(L);
        if (L.kind == LAMP_SPOT)
            Le *= spot_attenuation(L, -dir);
        return 1;
    }
    vector au, av, ng;
    float lu, lv, area;
    area_frame(L, au, av, lu, lv, ng, area);
    float cos_l = -dot(dir, ng);
    if (cos_l <= 0.0 || area <= 0.0)
        return 0;
    t = dot(L.co - Pp, ng) / dot(dir, ng);
    if (t <= 0.0)
        return 0;
    vector q = Pp + t * dir - L.co;
    float x = dot(q, au) / lu, y = dot(q, av) / lv;
    if (L.kind == LAMP_ELLIPSE ? x * x + y * y > 0.25 : (abs(x) > 0.5 || abs(y) > 0.5))
        return 0;
    Le = area_radiance(L, dir, ng, area);
    if (L.kind == LAMP_RECT) {
        float x0, y0, x1, y1, z0, b0, b1, k;
        vector ez;
        point corner = L.co - 0.5 * lu * au - 0.5 * lv * av;
        float S = rect_solid_angle(Pp, corner, au, av, lu, lv, x0, y0, x1, y1, z0, ez, b0, b1, k);
        pdf = (S > 1e-12) ? 1.0 / S : t * t / (cos_l * area);    // a vanishing sliver: by area
    } else {
        pdf = t * t / (cos_l * area);
    }
    t_exit = t;
    return 1;
}

// A uniform point of the unit disk.
void disk_point(float u0, float u1, output float x, output float y)
{
    float r = sqrt(u0);
    x = r * cos(2.0 * M_PI * u1);
    y = r * sin(2.0 * M_PI * u1);
}

// A direction of the cone around axis whose 1 - cos(half angle) is omc, uniform in solid angle.
vector cone_direction(vector axis, float omc, float u0, float u1)
{
    float t = u0 * omc;
    float z = 1.0 - t;
    float s = sqrt(max(t * (2.0 - t), 0.0));     // not from z: 1 - z * z cancels in a sun's tiny cone
    vector tx = (abs(axis[0]) < 0.9) ? cross(axis, vector(1, 0, 0)) : cross(axis, vector(0, 1, 0));
    tx = normalize(tx);
    vector ty = cross(axis, tx);
    float phi = 2.0 * M_PI * u1;
    return normalize(s * cos(phi) * tx + s * sin(phi) * ty + z * axis);
}

// Next-event estimation toward lamp L from Pp: a direction, the distance to the lamp, the
// radiance arriving (delta lamps: the irradiance at normal incidence) and its solid-angle pdf
// (0 for delta lamps). Returns 0 when the lamp cannot light Pp this way.
int lamp_sample(Lamp L, point Pp, float u0, float u1, output vector dir, output float dist,
                output color Le, output float pdf)
{
    dir = 0;
    dist = FAR;
    Le = 0;
    pdf = 0;
    if (L.kind == LAMP_SUN) {
        vector s = normalize(L.Z);
        if (!is_shaped(L)) {
            dir = s;
            Le = L.S;
            return 1;
        }
        dir = cone_direction(s, one_minus_cos(sun_half_angle(L)), u0, u1);
        float t, t_exit;
        return lamp_hit(L, Pp, dir, t, Le, pdf, t_exit);
    }
    if (L.kind == LAMP_POINT || L.kind == LAMP_SPOT) {
        vector oc = L.co - Pp;
        float d2 = dot(oc, oc);
        float r = L.size[0];
        if (r == 0.0) {
            dist = sqrt(d2);
            dir = oc / dist;
            Le = point_radiance(L) / d2;
            if (L.kind == LAMP_SPOT)
                Le *= spot_attenuation(L, -dir);
            return 1;
        }
        if (d2 <= r * r)
            return 0;
        if (has_flag(L, LAMP_SPHERE)) {
            dir = cone_direction(oc / sqrt(d2), one_minus_cos_from_sin2(r * r / d2), u0, u1);
        } else {
            vector n = -oc / sqrt(d2);
            vector tx = normalize((abs(n[0]) < 0.9) ? cross(n, vector(1, 0, 0)) : cross(n, vector(0, 1, 0)));
            vector ty = cross(n, tx);
            float x, y;
            disk_point(u0, u1, x, y);
            dir = normalize(oc + r * (x * tx + y * ty));
        }
        float t_exit;
        return lamp_hit(L, Pp, dir, dist, Le, pdf, t_exit);
    }
    vector au, av, ng;
    float lu, lv, area;
    area_frame(L, au, av, lu, lv, ng, area);
    vector to;
    if (L.kind == LAMP_RECT) {
        float x0, y0, x1, y1, z0, b0, b1, k;
        vector ez;
        point corner = L.co - 0.5 * lu * au - 0.5 * lv * av;
        float S = rect_solid_angle(Pp, corner, au, av, lu, lv, x0, y0, x1, y1, z0, ez, b0, b1, k);
        if (S > 1e-12) {
            vector o = rect_solid_angle_offset(S, x0, y0, x1, y1, z0, b0, b1, k, u0, u1);
            to = o[0] * au + o[1] * av + o[2] * ez;
        } else {
            to = L.co + (u0 - 0.5) * lu * au + (u1 - 0.5) * lv * av - Pp;
        }
    } else {
        float x, y;
        disk_point(u0, u1, x, y);
        to = L.co + 0.5 * x * lu * au + 0.5 * y * lv * av - Pp;
    }
    dir = normalize(to);
    float t_exit;
    return lamp_hit(L, Pp, dir, dist, Le, pdf, t_exit);
}

// The largest cosine to the normal n that a direction toward lamp L can have from Pp (0 when
// the whole lamp is below Pp's tangent plane: it cannot light a reflecting surface there).
float lamp_facing(Lamp L, point Pp, vector n)
{
    if (L.kind == LAMP_SUN) {
        float h = is_shaped(L) ? sun_half_angle(L) : 0.0;
        float a = acos(clamp(dot(normalize(L.Z), n), -1.0, 1.0));
        return max(cos(max(a - h, 0.0)), 0.0);
    }
    vector oc = L.co - Pp;
    float d = max(length(oc), 1e-8);
    if (L.kind == LAMP_POINT || L.kind == LAMP_SPOT) {
        float r = L.size[0];
        if (r >= d)
            return 1.0;
        float a = acos(clamp(dot(oc / d, n), -1.0, 1.0));
        return max(cos(max(a - asin(r / d), 0.0)), 0.0);
    }
    // area: the rectangle's corners (an ellipse's bounding box): convex, so below the plane
    // when all of them are
    vector au, av, ng;
    float lu, lv, area;
    area_frame(L, au, av, lu, lv, ng, area);
    float best = dot(normalize(oc), n);
    for (int i = 0; i < 4; i++) {
        vector corner = oc + ((i & 1) ? 0.5 : -0.5) * lu * au + ((i & 2) ? 0.5 : -0.5) * lv * av;
        best = max(best, dot(normalize(corner), n));
    }
    return max(best, 0.0);
}

// A rough share of the light lamp L sends to Pp, whose normal is n (for choosing one lamp per
// shading point): its irradiance at Pp times the best cosine it can have there; 0 where it
// cannot light Pp at all (behind an area lamp's emitting side, below the tangent plane).
float lamp_importance(Lamp L, point Pp, vector n)
{
    float lum = luminance(L.S);
    if (lum <= 0.0 || !(has_flag(L, LAMP_DIFFUSE) || has_flag(L, LAMP_GLOSSY)))
        return 0.0;
    float facing = lamp_facing(L, Pp, n);
    if (facing <= 0.0)
        return 0.0;
    if (L.kind == LAMP_SUN)
        return lum * facing;
    vector oc = L.co - Pp;
    float d2 = max(dot(oc, oc), 1e-8);
    if (L.kind == LAMP_POINT || L.kind == LAMP_SPOT) {
        float r = L.size[0];
        float e = lum / (4.0 * M_PI * max(d2, r * r));
        if (L.kind == LAMP_SPOT)
            e *= max(spot_attenuation(L, -oc), 0.02);
        return e * facing;
    }
    vector au, av, ng;
    float lu, lv, area;
    area_frame(L, au, av, lu, lv, ng, area);
    float toward = dot(-oc, ng);
    if (toward <= 0.0)          // behind the emitting side: no point of the lamp reaches Pp
        return 0.0;
    float c = max(toward / sqrt(d2), 0.05);
    return lum * c * area / (M_PI * max(d2, area)) * facing;
}
