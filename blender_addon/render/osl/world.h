// FlowBSDF OSL: the world's importance map (bake/export/world_map.py's texture layout): an
// equirectangular map in Blender's convention (column u = 0.5 - atan2(y, x) / 2 pi, row =
// theta / pi * H, row 0 the zenith), a pixel chosen by its share of the baked radiance times
// its solid angle — its row by the marginal CDF, its column by the row's conditional CDF — the
// direction uniform in the pixel's solid angle. pdf() reads the pixel's density back, so
// sampling and density are exactly consistent (bake/export/world_map.WorldMap is the numpy reference).

#define WORLD_LAYOUT 3

struct WorldMap {
    string file;
    float Wt, Ht;       // the texture's size
    int W, H;           // the map's pixels
};

// 1 and the map's header when `file` is a current world map.
int world_header(string file, output WorldMap m)
{
    int res[2];
    m.file = file;
    if (file == "" || !gettextureinfo(file, "resolution", res) || res[0] < 2 || res[1] < 3)
        return 0;
    m.Wt = res[0];
    m.Ht = res[1];
    color h0 = fetch(file, m.Wt, m.Ht, 0, 0);   // (WORLD_LAYOUT, W, H)
    m.W = int(h0[1]);
    m.H = int(h0[2]);
    return int(h0[0]) == WORLD_LAYOUT && m.W >= 1 && m.H >= 1;
}

// The density per steradian of the map's pixel (row, col).
float pdf_pixel(WorldMap m, int row, int col)
{
    color c = fetch(m.file, m.Wt, m.Ht, col, 2 + row);
    return c[1];
}

// The last entry k < n of a CDF (texture row y, entries at x = 0 .. n, the last 1) with
// cdf_k <= u, its value and the next one: tables.h's edge_search of the red channel, from the
// bracket of u's guide (channels `gc` and gc + 1 of texel floor(u Wt) of the row).
int cdf_search(WorldMap m, int y, int n, int gc, float u, output float c0, output float c1)
{
    float alpha = 0;
    color guide = texture(m.file, (clamp(int(u * m.Wt), 0, int(m.Wt) - 1) + 0.5) / m.Wt, (y + 0.5) / m.Ht,
                          0, 0, 0, 0, "interp", "closest", "wrap", "clamp", "alpha", alpha);
    float red[4] = {1.0, 0.0, 0.0, 0.0};
    return edge_search(m.file, m.Wt, m.Ht, y, n, int(guide[gc]), (gc == 1) ? int(guide[2]) : int(alpha), red, u,
                       c0, c1);
}

// The world-space direction for u (uniform in [0, 1)^2), its pdf per steradian and its pixel.
void sample_world(WorldMap m, float u0, float u1, output vector dir, output float pdf, output int row,
                  output int col)
{
    float r0, r1, c0, c1;
    row = cdf_search(m, 1, m.H, 1, u0, r0, r1);
    col = cdf_search(m, 2 + row, m.W, 2, u1, c0, c1);
    float t_row = clamp((u0 - r0) / (r1 - r0), 0.0, 1.0);
    float t_col = clamp((u1 - c0) / (c1 - c0), 0.0, 1.0);
    float z0 = cos(M_PI * row / m.H), z1 = cos(M_PI * (row + 1) / m.H);
    float z = z0 + t_row * (z1 - z0);
    float phi = (0.5 - (col + t_col) / m.W) * 2.0 * M_PI;
    float s = sqrt(max(1.0 - z * z, 0.0));
    dir = vector(s * cos(phi), s * sin(phi), z);
    pdf = pdf_pixel(m, row, col);
}

// The map pixel holding a world-space direction (where pdf_world reads its density).
void world_pixel(WorldMap m, vector dir, output int row, output int col)
{
    float theta = acos(clamp(dir[2], -1.0, 1.0));
    float u = 0.5 - atan2(dir[1], dir[0]) / (2.0 * M_PI);
    u -= floor(u);
    row = clamp(int(theta / M_PI * m.H), 0, m.H - 1);
    col = clamp(int(u * m.W), 0, m.W - 1);
}

// The pdf per steradian of sample_world at a world-space direction.
float pdf_world(WorldMap m, vector dir)
{
    int row, col;
    world_pixel(m, dir, row, col);
    return pdf_pixel(m, row, col);
}

// asin and sin of the small angles of a sun's disc by their series: Cycles' OSL evaluates
// asin/sin with approximations good to ~4e-6 rad, 1e-3 of a 0.27 degree sun's radius (measured:
// r 0.95260 against 0.95378, the disc's radiance 0.4 % high there: its control variate left
// Cycles' sun short by ~300 per sample, a pixel of -2.9). Series to s^5: 1e-10 below 0.05.
float asin_small(float s)
{
    float s2 = s * s;
    return (abs(s) < 0.05) ? s * (1.0 + s2 * (1.0 / 6.0 + s2 * (3.0 / 40.0))) : asin(s);
}

float sin_small(float x)
{
    float x2 = x * x;
    return (abs(x) < 0.05) ? x * (1.0 - x2 * (1.0 / 6.0 - x2 / 120.0)) : sin(x);
}

// Whether dir is within the cone of half angle asin(sin_half) < pi / 2 around axis: by the sine,
// which float keeps for a sun's tiny angle (dot(dir, axis) >= cos(half) is off by ~1 % of the
// radius there: the portal then disagrees with Cycles about the disc's edge).
int in_cone(vector dir, vector axis, float sin_half)
{
    return dot(dir, axis) > 0.0 && length(cross(dir, axis)) < sin_half;
}

// 1 - cos(half), exact in float for a small angle too.
float one_minus_cos(float half)
{
    float s = sin_small(0.5 * half);
    return 2.0 * s * s;
}

// Whether dir is within the cone of half angle `half` around axis (by the sine below pi / 4).
int in_cone_angle(vector dir, vector axis, float half)
{
    return (half < 0.25 * M_PI) ? in_cone(dir, axis, sin_small(half)) : dot(dir, axis) > cos(half);
}

// A Sky Texture's sun disc's radiance toward dir (within the disc of half angle `half` around
// sun), as the node fitted it to Cycles' render (blender_addon/world.sun_fit): the sky plus a
// colour linear in the height across the disc, limb-darkened. The angle by its sine, the height
// by the sine of the elevations' difference (a float cosine or asin keeps neither for a tiny disc).
color sun_radiance(vector sun, float half, color sky, color base, color rise, vector dir)
{
    float r = asin_small(min(length(cross(dir, sun)), 1.0)) / half;
    float a = clamp(dir[2], -1.0, 1.0), b = clamp(sun[2], -1.0, 1.0);
    float h = asin_small(a * sqrt(max(1.0 - b * b, 0.0)) - b * sqrt(max(1.0 - a * a, 0.0))) / (2.0 * half) + 0.5;
    float limb = 1.0 - 0.6 * (1.0 - sqrt(max(1.0 - r * r, 0.0)));
    return sky + (base + rise * h) * limb;
}
