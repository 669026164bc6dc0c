// FlowBSDF OSL: the baked tables (bake/export/osl_export.py's texture layout): header, sampling and
// evaluation. A port of bake/core/tables.py's Tables.sample and Tables._locate (the numpy reference).
// Every texel is fetched with "interp", "closest" and zero derivatives, so values come back exact.

#define LAYOUT 12
#define NSEG 3
#define LOG_MEAN_SERIES 1e-3
#define K_SMALL 1e-4

float fetch1(string file, float W, float H, int x, int y)
{
    color c = texture(file, (x + 0.5) / W, (y + 0.5) / H, 0, 0, 0, 0,
                      "interp", "closest", "wrap", "clamp");
    return c[0];
}

color fetch(string file, float W, float H, int x, int y)
{
    return texture(file, (x + 0.5) / W, (y + 0.5) / H, 0, 0, 0, 0,
                   "interp", "closest", "wrap", "clamp");
}

// phi_bin p (row 1, green).
float fetch_phi(string file, float W, float H, int p)
{
    color c = fetch(file, W, H, p, 1);
    return c[1];
}

// One fetch of a corner-block texel, blended over its four bins (red, green, blue, alpha).
color fetch4(string file, float W, float H, int x, int y, output float alpha)
{
    return texture(file, (x + 0.5) / W, (y + 0.5) / H, 0, 0, 0, 0,
                   "interp", "closest", "wrap", "clamp", "alpha", alpha);
}

float fetch_blend(string file, float W, float H, int x, int y, float w[4])
{
    float alpha = 0;
    color c = fetch4(file, W, H, x, y, alpha);
    return w[0] * c[0] + w[1] * c[1] + w[2] * c[2] + w[3] * alpha;
}

// fetch_blend of an isotropic corner's texel (red, green: bins k, k + 1) and, blended alike, the
// other quantity its blue and alpha hold (the row CDF's texels hold the a edges, the column sums'
// the b edges: bake/export/osl_export.py).
float fetch_pair(string file, float W, float H, int x, int y, float w[4], output float second)
{
    float alpha = 0;
    color c = fetch4(file, W, H, x, y, alpha);
    second = w[0] * c[2] + w[1] * alpha;
    return w[0] * c[0] + w[1] * c[1];
}

float log1p_(float x)
{
    float y = 1.0 + x;
    float d = y - 1.0;
    return (d == 0.0) ? x : log(y) * (x / d);
}

float expm1_(float x)
{
    return (abs(x) < 1e-5) ? x + 0.5 * x * x : exp(x) - 1.0;
}

// Inverse CDF of the in-cell density k e^(k x) / (e^k - 1) on [0, 1] (bake/core/profiles.py).
float exp_inverse_cdf(float u, float k)
{
    float x;
    if (abs(k) < K_SMALL)
        x = u - 0.5 * k * (u * u - u);
    else
        x = log1p_(u * expm1_(k)) / k;
    return clamp(x, 0.0, 1.0);
}

// bake/core/profiles.py _log_mean: (v1 - v0) / log(v1 / v0), its series where they are close.
float log_mean(float v0, float v1)
{
    float r = v1 / v0;
    float lr = log(r);
    return (abs(lr) < LOG_MEAN_SERIES) ? v0 * (1.0 + lr * (0.5 + lr / 6.0)) : v0 * ((r - 1.0) / lr);
}

// bake/core/profiles.py profile_parts: the pieces' masses of a profile's node values, and their total.
float profile_parts(float V[4], output float M[3])
{
    for (int k = 0; k < NSEG; k++)
        M[k] = log_mean(V[k], V[k + 1]) / NSEG;
    return M[0] + M[1] + M[2];
}

// bake/core/profiles.py profile_sample: the piece whose CDF brackets u, then its exponential; and
// the profile's density there, from that piece.
float profile_sample(float u, float V[4], output float density)
{
    float M[3];
    float total = profile_parts(V, M);
    float target = clamp(u, 0.0, 1.0) * total;
    int k = 0;
    float prev = 0.0, c = M[0];
    for (int n = 1; n < NSEG; n++) {
        if (c <= target) {
            k = n;
            prev = c;
        }
        c += M[n];
    }
    float rate = log(V[k + 1] / V[k]);
    float t = exp_inverse_cdf(clamp((target - prev) / M[k], 0.0, 1.0), rate);
    density = V[k] * exp(t * rate) / total;
    return (k + t) / NSEG;
}

// bake/core/profiles.py profile_density.
float profile_density(float x, float V[4])
{
    float M[3];
    float total = profile_parts(V, M);
    int k = clamp(int(floor(x * NSEG)), 0, NSEG - 1);
    float t = clamp(x * NSEG - k, 0.0, 1.0);
    return V[k] * exp(t * log(V[k + 1] / V[k])) / total;
}

// The tables' texture as the shader reads it, its header read once (read_header): the file and
// its size (W, H texels), K incident bins of NP azimuths over the period, R x C cells, the
// coordinates (half: 0 "wo", 1 "halfvector", 2 "halfpolar") and their frame's angle.
struct TablesTexture {
    string file;
    float W, H;
    int K, R, C, NP;
    float period;
    int half;
    float frame;
};

// 1 and the header when `file` is a current export (of the size the export makes of it:
// bake/export/osl_export.texture_image). The header is read from the file's attributes (osl_export.HEADER):
// gettextureinfo() of a constant file name is answered once, when OSL compiles the shader, where the
// header's texels cost two texture() calls at every shading point.
int read_header(string file, output TablesTexture tab)
{
    int res[2];
    int layout = 0, K = 0, R = 0, C = 0, NP = 0, half = 0;
    float period = 0, frame = 0;
    int found = gettextureinfo(file, "resolution", res) && res[0] >= 3 && res[1] >= 3
        && gettextureinfo(file, "flowbsdf_layout", layout) && layout == LAYOUT
        && gettextureinfo(file, "flowbsdf_K", K) && gettextureinfo(file, "flowbsdf_R", R)
        && gettextureinfo(file, "flowbsdf_C", C) && gettextureinfo(file, "flowbsdf_P", NP)
        && gettextureinfo(file, "flowbsdf_period", period) && gettextureinfo(file, "flowbsdf_coords", half)
        && gettextureinfo(file, "flowbsdf_frame", frame);
    tab.file = file;
    tab.W = res[0];
    tab.H = res[1];
    tab.K = K;
    tab.R = R;
    tab.C = C;
    tab.NP = NP;
    tab.period = period;
    tab.half = half;
    tab.frame = frame;
    int B = K * NP;
    return found && K >= 1 && R >= 1 && C >= 1 && NP >= 1 && period > 0.0
        && res[0] == max(max(C + 1, R + 1), max(max(K, NP), 3))
        && res[1] == 3 + 3 * B * R + max(K - 1, 1) * NP * (3 + 3 * R);
}

// The bins a direction blends at (cos theta_i, phi_i) (phi_i in the tangent frame; 0 when
// NP = 1): their indices, weights and the first row of their corner block; and for halfvector
// tables the whole periods phi_i was turned back by (turn).
void blend_bins(TablesTexture tab, float cos_i, float phi_i, output int bins[4], output float w[4], output int base,
                output float turn)
{
    turn = 0.0;
    // theta_i: the last k with theta_bin k <= theta_i (cos_k >= cos_i), weight t toward k + 1.
    int k = 0;
    float t = 0.0;
    if (tab.K > 1) {
        float c1 = 0;
        color guide = fetch4(tab.file, tab.W, tab.H, min(int(cos_i * tab.W), int(tab.W) - 1), 2, c1);
        int lo = int(guide[0]), hi = int(guide[1]);
        float c0 = guide[2];        // cos of bins min(lo, K - 2) and the next (c1)
        if (hi - lo > 1) {
            // (lo <= K - 2 here.) The search keeps what it reads: where lo stays, the guide's
            // c0 and c1 are the bins' own; else cos at lo, and at hi once it moved.
            int lo0 = lo;
            float clo = 0.0, chi = -2.0;
            while (hi - lo > 1) {
                int mid = (lo + hi) / 2;
                float c = fetch1(tab.file, tab.W, tab.H, mid, 1);
                if (c >= cos_i) { lo = mid; clo = c; } else { hi = mid; chi = c; }
            }
            if (lo == tab.K - 1) {
                c0 = fetch1(tab.file, tab.W, tab.H, lo - 1, 1);
                c1 = clo;
            } else if (lo != lo0) {
                c0 = clo;
                c1 = (chi > -2.0) ? chi : fetch1(tab.file, tab.W, tab.H, lo + 1, 1);
            }
        }
        k = min(lo, tab.K - 2);
        t = clamp((c0 - cos_i) / (c0 - c1), 0.0, 1.0);
    }
    // phi_i: within the period from the first bin; the last bin's gap wraps to the first
    // (halfvector: the bins close the period, the last one at the first + period).
    int p = 0;
    float sp = 0.0;
    if (tab.NP > 1) {
        float phi0 = fetch_phi(tab.file, tab.W, tab.H, 0);
        float x = mod(phi_i - phi0, tab.period);
        if (tab.half)
            turn = phi_i - phi0 - x;
        int lo = 0, hi = tab.half ? tab.NP - 1 : tab.NP;
        while (hi - lo > 1) {
            int mid = (lo + hi) / 2;
            if (fetch_phi(tab.file, tab.W, tab.H, mid) - phi0 <= x) lo = mid; else hi = mid;
        }
        p = lo;
        float start = fetch_phi(tab.file, tab.W, tab.H, p) - phi0;
        float end = (p + 1 < tab.NP) ? fetch_phi(tab.file, tab.W, tab.H, p + 1) - phi0 : tab.period;
        sp = clamp((x - start) / (end - start), 0.0, 1.0);
    }
    int k1 = min(k + 1, tab.K - 1);
    int p1 = (p + 1) % tab.NP;
    w[0] = (1.0 - t) * (1.0 - sp);
    w[1] = t * (1.0 - sp);
    w[2] = (1.0 - t) * sp;
    w[3] = t * sp;
    bins[0] = k * tab.NP + p;
    bins[1] = k1 * tab.NP + p;
    bins[2] = k * tab.NP + p1;
    bins[3] = k1 * tab.NP + p1;
    base = 3 + 3 * tab.K * tab.NP * tab.R + (k * tab.NP + p) * (3 + 3 * tab.R);
}

// The bins a shading point blends: blend_bins at its (cos theta_i, phi_i), the same for each of
// its samples and pdfs, so read once there and handed to sample_blend / eval_blend.
struct Blend {
    int bins[4];
    float w[4];
    int base;
    float turn;
};

void blend_at(TablesTexture tab, float cos_i, float phi_i, output Blend b)
{
    blend_bins(tab, cos_i, phi_i, b.bins, b.w, b.base, b.turn);
}

// Cell (i, j) of the blended table: its weight W (baked f cos / pdf), mass and profiles along a
// and b (node values): three RGBA texels a cell, (mass, a0, a1, a2), (a3, b0, b1, b2), (b3, W), one
// above the other, the bins of a table row in consecutive rows (the blend's reads share a tile).
void blend_cell(TablesTexture tab, int bins[4], float w[4], int i, int j, output color weight, output float mass,
                output float pa[4], output float pb[4])
{
    int B = tab.K * tab.NP;
    color q0 = 0, q1 = 0, q2 = 0;
    float s0 = 0, s1 = 0, s2 = 0;
    for (int c = 0; c < 4; c++) {
        if (w[c] > 0.0) {
            int y = 3 + 3 * (i * B + bins[c]);
            float a0 = 0, a1 = 0, a2 = 0;
            q0 += w[c] * fetch4(tab.file, tab.W, tab.H, j, y, a0);
            q1 += w[c] * fetch4(tab.file, tab.W, tab.H, j, y + 1, a1);
            q2 += w[c] * fetch4(tab.file, tab.W, tab.H, j, y + 2, a2);
            s0 += w[c] * a0;
            s1 += w[c] * a1;
            s2 += w[c] * a2;
        }
    }
    mass = q0[0];
    pa[0] = q0[1]; pa[1] = q0[2]; pa[2] = s0; pa[3] = q1[0];
    pb[0] = q1[1]; pb[1] = q1[2]; pb[2] = s1; pb[3] = q2[0];
    weight = color(q2[1], q2[2], s2);
}

// bake/core/halfvector.py: 1 - cos theta_max(phi_h), the valid cap of h along phi_h at wi.
float half_cap(vector wi, float phi_h)
{
    float s = sin(0.25 * atan2(wi[2], -(wi[0] * cos(phi_h) + wi[1] * sin(phi_h))));
    return max(2.0 * s * s, 1e-30);
}

// bake/core/halfvector.py polar_from_ab: wo of polar coordinates (a, b) at wi (the map's frame),
// and jac (isotropic halfpolar tables; the concentric map ends in it).
vector polar_from_ab(vector wi, float a, float b, output float jac)
{
    float cap = half_cap(wi, b);
    float one_minus_cos = a * cap;
    float sin_h = sqrt(max(one_minus_cos * (2.0 - one_minus_cos), 0.0));
    vector h = vector(sin_h * cos(b), sin_h * sin(b), 1.0 - one_minus_cos);
    float cos_ih = dot(wi, h);
    vector wo = 2.0 * cos_ih * h - wi;
    wo[2] = max(wo[2], 0.0);
    jac = 4.0 * cos_ih * cap;
    return wo;
}

// bake/core/halfvector.py from_ab: wo of table coordinates (a, b) at wi (the map's frame), and
// jac = d omega_o / (da db).
vector half_from_ab(vector wi, float a, float b, output float jac)
{
    float x = 2.0 * a - 1.0, y = b / M_PI - 1.0;
    float r = y, angle = M_PI_2 - M_PI_4 * ((y != 0.0) ? x / y : 0.0);
    if (abs(x) >= abs(y)) {
        r = x;
        angle = M_PI_4 * ((x != 0.0) ? y / x : 0.0);
    }
    float u = r * cos(angle), v = r * sin(angle);
    return polar_from_ab(wi, u * u + v * v, atan2(v, u), jac);      // the disk point's radius^2 and angle
}

// bake/core/halfvector.py to_ab: (a, b) and jac of wo at wi (both in the map's frame).
void half_to_ab(vector wi, vector wo, output float a, output float b, output float jac)
{
    vector h = normalize(wi + wo);
    float phi_h = atan2(h[1], h[0]);
    float cap = half_cap(wi, phi_h);
    float radius = sqrt(clamp((h[0] * h[0] + h[1] * h[1]) / (1.0 + h[2]) / cap, 0.0, 1.0));
    float u = radius * cos(phi_h), v = radius * sin(phi_h);
    float x = sign(v) * radius * ((v != 0.0) ? atan(u / v) : 0.0) / M_PI_4, y = sign(v) * radius;
    if (abs(u) >= abs(v)) {
        x = sign(u) * radius;
        y = sign(u) * radius * ((u != 0.0) ? atan(v / u) : 0.0) / M_PI_4;
    }
    a = clamp(0.5 * (x + 1.0), 0.0, 1.0);
    b = clamp(M_PI * (y + 1.0), 0.0, 2.0 * M_PI);
    jac = 4.0 * dot(wi, h) * cap;
}

// bake/core/halfvector.py polar_to_ab: (a, b) and jac of wo at wi (both in the map's frame).
void polar_to_ab(vector wi, vector wo, output float a, output float b, output float jac)
{
    vector h = normalize(wi + wo);
    b = mod(atan2(h[1], h[0]), 2.0 * M_PI);
    float cap = half_cap(wi, b);
    a = clamp((h[0] * h[0] + h[1] * h[1]) / (1.0 + h[2]) / cap, 0.0, 1.0);
    jac = 4.0 * dot(wi, h) * cap;
}

vector turn_z(vector w, float angle)
{
    float c = cos(angle), s = sin(angle);
    return vector(c * w[0] - s * w[1], s * w[0] + c * w[1], w[2]);
}

// Samples the tables at (cos theta_i, phi_i): wo in the local frame (x toward phi = 0), its
// weight (baked f cos / pdf) and pdf per steradian.
// (sample_blend: with the shading point's Blend read.)
void sample_blend(TablesTexture tab, Blend bl, float cos_i, float phi_i, float u0, float u1, output vector wo,
                  output color weight, output float pdf)
{
    int base = bl.base;

    // Isotropic corners: every texel the searches read brings its a (b) edge along (fetch_pair).
    int iso = tab.NP == 1;
    float e = 0.0;
    // Row: the last i with CDF_i <= u0 (the guide brackets it).
    color guide = fetch(tab.file, tab.W, tab.H, min(int(u0 * tab.R), tab.R - 1), base + 2);
    int lo = int(guide[0]), hi = int(guide[1]);
    float c0 = -1.0, c1 = -1.0;         // the CDF at lo and hi, once the search has read them
    float a0 = 0.0, a1 = 0.0;           // (isotropic: the a edges there)
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        float c = iso ? fetch_pair(tab.file, tab.W, tab.H, mid, base, bl.w, e)
                      : fetch_blend(tab.file, tab.W, tab.H, mid, base, bl.w);
        if (c <= u0) { lo = mid; c0 = c; a0 = e; } else { hi = mid; c1 = c; a1 = e; }
    }
    int i = lo;
    if (c0 < 0.0)
        c0 = iso ? fetch_pair(tab.file, tab.W, tab.H, i, base, bl.w, a0)
                 : fetch_blend(tab.file, tab.W, tab.H, i, base, bl.w);
    if (c1 < 0.0 || hi != i + 1)
        c1 = iso ? fetch_pair(tab.file, tab.W, tab.H, i + 1, base, bl.w, a1)
                 : fetch_blend(tab.file, tab.W, tab.H, i + 1, base, bl.w);
    if (!iso) {
        a0 = fetch_blend(tab.file, tab.W, tab.H, i, base + 1, bl.w);
        a1 = fetch_blend(tab.file, tab.W, tab.H, i + 1, base + 1, bl.w);
    }
    float v = u1 * (c1 - c0);
    // Column: the last j with cumsum_ij <= v.
    int yrow = base + 3 + 3 * i;
    guide = fetch(tab.file, tab.W, tab.H, min(int(u1 * tab.C), tab.C - 1), yrow + 2);
    lo = int(guide[0]);
    hi = int(guide[1]);
    float d0 = -1.0;
    float b0 = 0.0, b1 = -1.0;          // (isotropic: the b edges at lo and hi, once read)
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        float d = iso ? fetch_pair(tab.file, tab.W, tab.H, mid, yrow, bl.w, e)
                      : fetch_blend(tab.file, tab.W, tab.H, mid, yrow, bl.w);
        if (d <= v) { lo = mid; d0 = d; b0 = e; } else { hi = mid; b1 = e; }
    }
    int j = lo;
    if (d0 < 0.0)
        d0 = iso ? fetch_pair(tab.file, tab.W, tab.H, j, yrow, bl.w, b0)
                 : fetch_blend(tab.file, tab.W, tab.H, j, yrow, bl.w);
    if (!iso) {
        b0 = fetch_blend(tab.file, tab.W, tab.H, j, yrow + 1, bl.w);
        b1 = fetch_blend(tab.file, tab.W, tab.H, j + 1, yrow + 1, bl.w);
    } else if (b1 < 0.0 || hi != j + 1) {
        fetch_pair(tab.file, tab.W, tab.H, j + 1, yrow, bl.w, b1);
    }
    float mass, pa[4], pb[4];
    blend_cell(tab, bl.bins, bl.w, i, j, weight, mass, pa, pb);
    float dx, dy;
    float x = profile_sample(clamp((u0 - c0) / (c1 - c0), 0.0, 1.0), pa, dx);
    float y = profile_sample(clamp((v - d0) / mass, 0.0, 1.0), pb, dy);
    float a = a0 + x * (a1 - a0);
    float b = b0 + y * (b1 - b0);
    pdf = mass * dx * dy / ((a1 - a0) * (b1 - b0));
    if (tab.half) {     // h in the frame turned by whole periods and the lobe's axes (halfpolar: wi's + pi)
        float ref = (tab.half == 2) ? phi_i + M_PI : bl.turn + tab.frame, sin_i = sqrt(max(1.0 - cos_i * cos_i, 0.0));
        float jac;
        vector wi = vector(sin_i * cos(phi_i - ref), sin_i * sin(phi_i - ref), cos_i);
        wo = turn_z((tab.half == 2) ? polar_from_ab(wi, a, b, jac) : half_from_ab(wi, a, b, jac), ref);
        pdf /= jac;
        return;
    }
    float s = sqrt(max(a * (2.0 - a), 0.0));
    // b is the azimuth from the mirror plane of wi, + pi: phi_o = b - pi + (phi_i + pi).
    wo = vector(s * cos(b + phi_i), s * sin(b + phi_i), 1.0 - a);
}

void sample_tables(TablesTexture tab, float cos_i, float phi_i, float u0, float u1, output vector wo,
                   output color weight, output float pdf)
{
    Blend bl;
    blend_at(tab, cos_i, phi_i, bl);
    sample_blend(tab, bl, cos_i, phi_i, u0, u1, wo, weight, pdf);
}

// The last k in [lo, hi) with blended edge_k <= x among the edges of texture row y (binary
// search), its edge and the next one. (Its last reads at lo and hi = lo + 1 are kept, not re-read.)
int bracket_search(string file, float W, float H, int y, int lo_guide, int hi_guide, float w[4], float x,
                   output float e0, output float e1)
{
    int lo = lo_guide, hi = hi_guide;
    e0 = -1.0;
    e1 = -1.0;
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        float e = fetch_blend(file, W, H, mid, y, w);
        if (e <= x) { lo = mid; e0 = e; } else { hi = mid; e1 = e; }
    }
    if (e0 < 0.0)
        e0 = fetch_blend(file, W, H, lo, y, w);
    if (e1 < 0.0 || hi != lo + 1)
        e1 = fetch_blend(file, W, H, lo + 1, y, w);
    return lo;
}

// The last k < n with blended edge_k <= x among the edges of texture row y (x = 0 .. n), its
// edge and the next one: searched within the guide's bracket [lo, hi), the whole row should
// float rounding put x outside it.
int edge_search(string file, float W, float H, int y, int n, int lo_guide, int hi_guide, float w[4], float x,
                output float e0, output float e1)
{
    int k = bracket_search(file, W, H, y, lo_guide, hi_guide, w, x, e0, e1);
    if ((e0 <= x || k == 0) && (x < e1 || k == n - 1))
        return k;
    return bracket_search(file, W, H, y, 0, n, w, x, e0, e1);
}

// edge_search among a corner's own edges (x = 0 .. n, n its rows (axis 0) or columns (axis 1)
// from its count texel, x = R of the row guide's row): the count is read only when the guide's
// bracket is not enough (x outside it, or x on the last edge).
int own_edge_search(TablesTexture tab, int y, int base, int axis, int lo_guide, int hi_guide, float w[4], float x,
                    output float e0, output float e1)
{
    int k = bracket_search(tab.file, tab.W, tab.H, y, lo_guide, hi_guide, w, x, e0, e1);
    if ((e0 <= x || k == 0) && x < e1)
        return k;
    color count = fetch(tab.file, tab.W, tab.H, tab.R, base + 2);
    return edge_search(tab.file, tab.W, tab.H, y, int(count[axis]), k, k + 1, w, x, e0, e1);
}

// The tables' pdf (per steradian) and baked f cos (= the cell's weight x pdf) at a direction
// wo of the local frame (Tables.pdf and Tables.eval x cos): 0 below the horizon.
// (eval_blend: with the shading point's Blend read.)
void eval_blend(TablesTexture tab, Blend bl, float cos_i, float phi_i, vector wo, output color fcos,
                output float pdf)
{
    fcos = 0;
    pdf = 0;
    if (wo[2] <= 0.0)
        return;
    int base = bl.base;
    float a = min((wo[0] * wo[0] + wo[1] * wo[1]) / (1.0 + wo[2]), 1.0);
    float b = mod(atan2(wo[1], wo[0]) - phi_i, 2.0 * M_PI);     // as in sample_tables: phi_o = b + phi_i
    float jac = 1.0;
    if (tab.half) {
        float ref = (tab.half == 2) ? phi_i + M_PI : bl.turn + tab.frame, sin_i = sqrt(max(1.0 - cos_i * cos_i, 0.0));
        vector wi = vector(sin_i * cos(phi_i - ref), sin_i * sin(phi_i - ref), cos_i);
        if (tab.half == 2)
            polar_to_ab(wi, turn_z(wo, -ref), a, b, jac);
        else
            half_to_ab(wi, turn_z(wo, -ref), a, b, jac);
    }
    // Row: the last i with a_i <= a; column: the last j with b_ij <= b. Each search starts from
    // its guide's bracket (blue, alpha of the row / column guide texels).
    float a0, a1, b0, b1;
    float alpha = 0;
    color guide = fetch4(tab.file, tab.W, tab.H, clamp(int(a * tab.R), 0, tab.R - 1), base + 2, alpha);
    int i = own_edge_search(tab, base + 1, base, 0, int(guide[2]), int(alpha), bl.w, a, a0, a1);
    int brow = base + 4 + 3 * i;
    guide = fetch4(tab.file, tab.W, tab.H, clamp(int(b * (tab.C / (2.0 * M_PI))), 0, tab.C - 1), brow + 1, alpha);
    int j = own_edge_search(tab, brow, base, 1, int(guide[2]), int(alpha), bl.w, b, b0, b1);
    color weight;
    float mass, pa[4], pb[4];
    blend_cell(tab, bl.bins, bl.w, i, j, weight, mass, pa, pb);
    float x = clamp((a - a0) / (a1 - a0), 0.0, 1.0);
    float y = clamp((b - b0) / (b1 - b0), 0.0, 1.0);
    pdf = mass * profile_density(x, pa) * profile_density(y, pb) / ((a1 - a0) * (b1 - b0)) / jac;
    fcos = weight * pdf;
}

void eval_tables(TablesTexture tab, float cos_i, float phi_i, vector wo, output color fcos, output float pdf)
{
    fcos = 0;
    pdf = 0;
    if (wo[2] <= 0.0)
        return;
    Blend bl;
    blend_at(tab, cos_i, phi_i, bl);
    eval_blend(tab, bl, cos_i, phi_i, wo, fcos, pdf);
}
