// FlowBSDF OSL: the world's importance map (bake/export/world_map.py's texture layout): an
// equirectangular map in Blender's convention (column u = 0.5 - atan2(y, x) / 2 pi, row =
// theta / pi * H, row 0 the zenith), a pixel chosen by its share of the baked radiance times
// its solid angle, the direction uniform in the pixel's solid angle. pdf() reads the pixel's
// density back, so sampling and density are exactly consistent (bake/export/world_map.WorldMap is
// the numpy reference).

#define WORLD_LAYOUT 1

struct WorldMap {
    string file;
    float Wt, Ht;       // the texture's size
    int W, H, G;        // the map's pixels, guide entries
    int rcdf, rpdf, rguide;     // first rows of the CDF, pdf and guide blocks
};

// 1 and the map's header when `file` is a current world map (3 fetches: read it once).
int world_header(string file, output WorldMap m)
{
    int res[2];
    m.file = file;
    if (file == "" || !gettextureinfo(file, "resolution", res) || res[0] < 3)
        return 0;
    m.Wt = res[0];
    m.Ht = res[1];
    color h0 = fetch(file, m.Wt, m.Ht, 0, 0);   // (WORLD_LAYOUT, W, H)
    color h1 = fetch(file, m.Wt, m.Ht, 1, 0);   // (G, rcdf, rpdf)
    color h2 = fetch(file, m.Wt, m.Ht, 2, 0);   // (rguide, 0, 0)
    m.W = int(h0[1]);
    m.H = int(h0[2]);
    m.G = int(h1[0]);
    m.rcdf = int(h1[1]);
    m.rpdf = int(h1[2]);
    m.rguide = int(h2[0]);
    return int(h0[0]) == WORLD_LAYOUT && m.W >= 1 && m.H >= 1 && m.G >= 1;
}

float world_cdf(WorldMap m, int k)
{
    int iw = int(m.Wt);
    return fetch1(m.file, m.Wt, m.Ht, k % iw, m.rcdf + k / iw);
}

// The world-space direction for u (uniform in [0, 1)^2) and its pdf per steradian.
void sample_world(WorldMap m, float u0, float u1, output vector dir, output float pdf)
{
    int iw = int(m.Wt);
    int g = min(int(u0 * m.G), m.G - 1);
    color guide = fetch(m.file, m.Wt, m.Ht, g % iw, m.rguide + g / iw);
    int lo = int(guide[0]), hi = int(guide[1]);
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        if (world_cdf(m, mid) <= u0) lo = mid; else hi = mid;
    }
    int k = lo;
    int row = k / m.W, col = k % m.W;
    float c0 = world_cdf(m, k), c1 = world_cdf(m, k + 1);
    float z0 = cos(M_PI * row / m.H), z1 = cos(M_PI * (row + 1) / m.H);
    float z = z0 + u1 * (z1 - z0);
    float t = clamp((u0 - c0) / (c1 - c0), 0.0, 1.0);
    float phi = (0.5 - (col + t) / m.W) * 2.0 * M_PI;
    float s = sqrt(max(1.0 - z * z, 0.0));
    dir = vector(s * cos(phi), s * sin(phi), z);
    pdf = fetch1(m.file, m.Wt, m.Ht, col, m.rpdf + row);
}

// The pdf per steradian of sample_world at a world-space direction.
float pdf_world(WorldMap m, vector dir)
{
    float theta = acos(clamp(dir[2], -1.0, 1.0));
    float u = 0.5 - atan2(dir[1], dir[0]) / (2.0 * M_PI);
    u -= floor(u);
    int row = clamp(int(theta / M_PI * m.H), 0, m.H - 1);
    int col = clamp(int(u * m.W), 0, m.W - 1);
    return fetch1(m.file, m.Wt, m.Ht, col, m.rpdf + row);
}

// A Sky Texture's sun disc's radiance toward dir (within the disc of half angle `half` around
// sun), as the node fitted it to Cycles' render (blender_addon/world.sun_fit): the sky plus a
// colour linear in the height across the disc, limb-darkened. The angle by its sine (float
// keeps it for a tiny disc).
color sun_radiance(vector sun, float half, color sky, color base, color rise, vector dir)
{
    float r = asin(min(length(cross(dir, sun)), 1.0)) / half;
    float h = (asin(clamp(dir[2], -1.0, 1.0)) - asin(clamp(sun[2], -1.0, 1.0))) / (2.0 * half) + 0.5;
    float limb = 1.0 - 0.6 * (1.0 - sqrt(max(1.0 - r * r, 0.0)));
    return sky + (base + rise * h) * limb;
}
