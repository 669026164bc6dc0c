// FlowBSDF OSL: the world's importance map (bake/world_map.py's texture layout): an
// equirectangular map in Blender's convention (column u = 0.5 - atan2(y, x) / 2 pi, row =
// theta / pi * H, row 0 the zenith), a pixel chosen by its share of the baked radiance times
// its solid angle, the direction uniform in the pixel's solid angle. pdf() reads the pixel's
// density back, so sampling and density are exactly consistent (bake/world_map.WorldMap is
// the numpy reference).

#define WORLD_LAYOUT 1

// (1, header) when the file is a current world map: W x H pixels, the texture's width Wt, N + 1
// CDF entries, G guides and the first rows of the CDF, pdf and guide blocks.
int world_header(string file, output float Wt, output float Ht, output int W, output int H,
                 output int G, output int rcdf, output int rpdf, output int rguide)
{
    int res[2];
    if (file == "" || !gettextureinfo(file, "resolution", res) || res[0] < 3)
        return 0;
    Wt = res[0];
    Ht = res[1];
    color h0 = fetch(file, Wt, Ht, 0, 0);   // (WORLD_LAYOUT, W, H)
    color h1 = fetch(file, Wt, Ht, 1, 0);   // (G, rcdf, rpdf)
    color h2 = fetch(file, Wt, Ht, 2, 0);   // (rguide, 0, 0)
    W = int(h0[1]);
    H = int(h0[2]);
    G = int(h1[0]);
    rcdf = int(h1[1]);
    rpdf = int(h1[2]);
    rguide = int(h2[0]);
    return int(h0[0]) == WORLD_LAYOUT && W >= 1 && H >= 1 && G >= 1;
}

float world_cdf(string file, float Wt, float Ht, int rcdf, int k)
{
    int iw = int(Wt);
    return fetch1(file, Wt, Ht, k % iw, rcdf + k / iw);
}

// The world-space direction for u (uniform in [0, 1)^2) and its pdf per steradian.
void sample_world(string file, float u0, float u1, output vector dir, output float pdf)
{
    float Wt, Ht;
    int W, H, G, rcdf, rpdf, rguide;
    world_header(file, Wt, Ht, W, H, G, rcdf, rpdf, rguide);
    int iw = int(Wt);
    int g = min(int(u0 * G), G - 1);
    color guide = fetch(file, Wt, Ht, g % iw, rguide + g / iw);
    int lo = int(guide[0]), hi = int(guide[1]);
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        if (world_cdf(file, Wt, Ht, rcdf, mid) <= u0) lo = mid; else hi = mid;
    }
    int k = lo;
    int row = k / W, col = k % W;
    float c0 = world_cdf(file, Wt, Ht, rcdf, k), c1 = world_cdf(file, Wt, Ht, rcdf, k + 1);
    float z0 = cos(M_PI * row / H), z1 = cos(M_PI * (row + 1) / H);
    float z = z0 + u1 * (z1 - z0);
    float t = clamp((u0 - c0) / (c1 - c0), 0.0, 1.0);
    float phi = (0.5 - (col + t) / W) * 2.0 * M_PI;
    float s = sqrt(max(1.0 - z * z, 0.0));
    dir = vector(s * cos(phi), s * sin(phi), z);
    pdf = fetch1(file, Wt, Ht, col, rpdf + row);
}

// The pdf per steradian of sample_world at a world-space direction.
float pdf_world(string file, vector dir)
{
    float Wt, Ht;
    int W, H, G, rcdf, rpdf, rguide;
    world_header(file, Wt, Ht, W, H, G, rcdf, rpdf, rguide);
    float theta = acos(clamp(dir[2], -1.0, 1.0));
    float u = 0.5 - atan2(dir[1], dir[0]) / (2.0 * M_PI);
    u -= floor(u);
    int row = clamp(int(theta / M_PI * H), 0, H - 1);
    int col = clamp(int(u * W), 0, W - 1);
    return fetch1(file, Wt, Ht, col, rpdf + row);
}
