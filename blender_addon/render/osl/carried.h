// FlowBSDF OSL: the carried blend (bake/core/carried.py, the numpy reference; the texture:
// bake/export/carry_export.py). Between two bins whose interval carries, a direction of bin j's
// table is carried to theta_i at fixed s, the measured file's own coordinates (its warp's inverse
// at the half vector, s_x over its horizon value: rgl.WarpedCoords(horizon=True)):
//     sample: bin j of the two with its weight (u0 split by the weights), wo_j from bin j's table,
//             wo = W_i^-1(W_j(wo_j)); its pdf and f cos as eval's sum, bin j's term from the
//             chain's own values (the numpy reference re-derives it from wo: the same to float32)
//     eval:   sum_j w_j {pdf, f cos}_j(W_j^-1(W_i(wo))) J_j / J_i,  J = d omega / d s
// Elsewhere (at a bin, on an interval that does not carry, without a carry texture) the tables'
// own fixed-cell blend (tables.h). Isotropic tables only: the local frame has phi_i = 0.

#define CARRY_LAYOUT 1
#define CARRY_SLICES 16     // the most theta_i slices a file may have here (RGL files: 8)

struct Carry {
    string file;
    float W, H;
    int S, ny, nx, K;
    int on;                         // the shader carries with it (set beside carry_header: isotropic tables)
    float theta_i[CARRY_SLICES];    // the slices' incident angles, read once with the header
};

// 1 and the header when `file` is a carry texture of tables with K bins.
int carry_header(string file, int K, output Carry c)
{
    int res[2];
    c.file = file;
    if (file == "" || !gettextureinfo(file, "resolution", res) || res[0] < 4 || res[1] < 2)
        return 0;
    c.W = res[0];
    c.H = res[1];
    float nx = 0;
    color h0 = fetch4(file, c.W, c.H, 0, 0, nx);      // (CARRY_LAYOUT, S, ny, nx)
    color h1 = fetch(file, c.W, c.H, 1, 0);           // (W, H, K)
    c.S = int(h0[1]);
    c.ny = int(h0[2]);
    c.nx = int(nx);
    c.K = int(h1[2]);
    if (c.S < 1 || c.S > CARRY_SLICES)
        return 0;
    for (int s = 0; s < c.S; s++)
        c.theta_i[s] = fetch1(file, c.W, c.H, 2 + s, 0);
    return int(h0[0]) == CARRY_LAYOUT && c.K == K && c.ny >= 2 && c.nx >= 2
        && int(h1[0]) == res[0] && int(h1[1]) == res[1];
}

// The file's two slices at theta (rgl._param_weights: Mitsuba's find_interval, linear in the angle).
void carry_slices(Carry c, float theta, output int s0, output float t)
{
    s0 = 0;
    t = 0.0;
    if (c.S == 1)
        return;
    for (int s = 1; s < c.S - 1; s++)
        if (c.theta_i[s] < theta)
            s0 += 1;
    t = clamp((theta - c.theta_i[s0]) / (c.theta_i[s0 + 1] - c.theta_i[s0]), 0.0, 1.0);
}

// Texel x of patch row y, blended over the two slices (alpha in a).
color carry_texel(Carry c, int s0, float t, int x, int y, output float a)
{
    float a0 = 0, a1 = 0;
    color v = fetch4(c.file, c.W, c.H, x, 1 + s0 * (c.ny - 1) + y, a0);
    if (t > 0.0) {
        color v1 = fetch4(c.file, c.W, c.H, x, 1 + (s0 + 1) * (c.ny - 1) + y, a1);
        v = (1.0 - t) * v + t * v1;
        a0 = (1.0 - t) * a0 + t * a1;
    }
    a = a0;
    return v;
}

// The nine numbers of patch (py, px): corner densities v00 v10 v01 v11, the conditional CDF at
// its left edge on its two rows, the two rows' totals, the marginal CDF at its lower row.
void carry_patch(Carry c, int s0, float t, int py, int px, output float v[9])
{
    float a0, a1, ar, am;
    color e0 = carry_texel(c, s0, t, px, py, a0);
    color e1 = carry_texel(c, s0, t, px + 1, py, a1);
    color er = carry_texel(c, s0, t, c.nx - 1, py, ar);
    color em = carry_texel(c, s0, t, c.nx, py, am);
    v[0] = e0[0]; v[1] = e1[0]; v[2] = e0[2]; v[3] = e1[2];
    v[4] = e0[1]; v[5] = a0; v[6] = er[1]; v[7] = ar; v[8] = em[0];
}

// rgl._patch: the cell of u among n - 1 and the position in it.
void carry_cell(float u, int n, output int i, output float f)
{
    float x = clamp(u, 0.0, 1.0) * (n - 1);
    i = min(int(x), n - 2);
    f = x - i;
}

// rgl._warp_to_s within a patch at (fx, fy): s_x (over the row total), s_y, zero row, density.
void carry_within(float v[9], float fx, float fy, output float sx, output float sy, output int zero,
                  output float density)
{
    float gy = 1.0 - fy;
    float row_total = gy * v[6] + fy * v[7];
    zero = row_total == 0.0;
    if (zero)
        row_total = 1.0;
    float c0 = gy * v[0] + fy * v[2], c1 = gy * v[1] + fy * v[3];
    sx = (fx * (c0 + 0.5 * fx * (c1 - c0)) + gy * v[4] + fy * v[5]) / row_total;
    sy = fy * (v[6] + 0.5 * fy * (v[7] - v[6])) + v[8];
    density = (1.0 - fx) * c0 + fx * c1;
}

// s_x at the horizon in row (py, fy) (WarpedCoords._rim).
float carry_rim(Carry c, int s0, float t, float cos_i, int py, float fy)
{
    float sin_i = sqrt(max(1.0 - cos_i * cos_i, 0.0));
    float delta = ((py + fy) / (c.ny - 1)) * (2.0 * M_PI) - M_PI;
    float theta_h = 0.5 * atan2(cos_i, -sin_i * cos(delta));
    int px;
    float fx, sx, sy, density, v[9];
    int zero;
    carry_cell(sqrt(theta_h * (2.0 / M_PI)), c.nx, px, fx);
    carry_patch(c, s0, t, py, px, v);
    carry_within(v, fx, fy, sx, sy, zero, density);
    return clamp(sx, 1e-30, 1.0);
}

// d omega_o / d s at the half vector h (u_m x = u_x) without the rim; 0 where the warp has no density.
float carry_jac(Carry c, vector wi, float u_x, vector h, float density)
{
    float theta_h = u_x * u_x * (0.5 * M_PI);
    float d = 4.0 * abs(dot(h, wi)) * sin(theta_h) * (M_PI * u_x) * (2.0 * M_PI);
    return (density > 0.0) ? d / (density * (c.nx - 1) * (c.ny - 1)) : 0.0;
}

// x in [0, 1] with start x + slope_half x^2 = d (WarpedCoords._root).
float carry_root(float slope_half, float start, float d)
{
    float root = sqrt(max(start * start + 4.0 * slope_half * d, 0.0));
    float den = start + root;
    if (den > 0.0)
        return clamp(2.0 * d / den, 0.0, 1.0);
    return (d > 0.0) ? 1.0 : 0.0;
}

vector carry_wi(float cos_i)
{
    return vector(sqrt(max(1.0 - cos_i * cos_i, 0.0)), 0.0, cos_i);
}

// WarpedCoords(horizon=True).to_s at wi = (sin theta, 0, cos theta): s and d omega / d s
// (jac 0 where the warp has no density).
void carry_to_s(Carry c, float cos_i, float theta, vector wo, output float s_x, output float s_y,
                output float jac)
{
    int s0;
    float t;
    carry_slices(c, theta, s0, t);
    vector wi = carry_wi(cos_i);
    vector h = normalize(wi + wo);
    float dist = sqrt(h[0] * h[0] + h[1] * h[1] + (h[2] - 1.0) * (h[2] - 1.0));
    float u_x = sqrt(2.0 * asin(min(0.5 * dist, 1.0)) * (2.0 / M_PI));
    float u_y = (atan2(h[1], h[0]) + M_PI) * (0.5 / M_PI);
    u_y -= floor(u_y);
    int px, py, zero;
    float fx, fy, sx, density, v[9];
    carry_cell(u_x, c.nx, px, fx);
    carry_cell(u_y, c.ny, py, fy);
    carry_patch(c, s0, t, py, px, v);
    carry_within(v, fx, fy, sx, s_y, zero, density);
    float rim = carry_rim(c, s0, t, cos_i, py, fy);
    s_x = min(sx / rim, 1.0);
    jac = carry_jac(c, wi, u_x, h, zero ? 0.0 : density) * rim;
}

// WarpedCoords(horizon=True).from_s: the direction at s and d omega / d s (jac 0: s reaches no
// direction above the horizon).
void carry_from_s(Carry c, float cos_i, float theta, float s_x, float s_y, output vector wo, output float jac)
{
    int s0;
    float t, a;
    carry_slices(c, theta, s0, t);
    // row: the last py in [0, ny - 2] whose marginal CDF is <= s_y
    int lo = 0, hi = c.ny - 1;
    color m = carry_texel(c, s0, t, c.nx, 0, a);
    if (!(m[0] <= s_y))
        hi = 0;
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        m = carry_texel(c, s0, t, c.nx, mid, a);
        if (m[0] <= s_y) lo = mid; else hi = mid;
    }
    int py = lo;
    float r1;
    color r = carry_texel(c, s0, t, c.nx - 1, py, r1);
    float r0 = r[1];
    m = carry_texel(c, s0, t, c.nx, py, a);
    float m0 = m[0];
    float fy = carry_root(0.5 * (r1 - r0), r0, s_y - m0), gy = 1.0 - fy;
    float rim = carry_rim(c, s0, t, cos_i, py, fy);
    float target = s_x * rim * (gy * r0 + fy * r1);
    // column: the last px in [0, nx - 2] whose start (the conditional CDF at its left edge) is <= target
    lo = 0;
    hi = c.nx - 1;
    color e = carry_texel(c, s0, t, 0, py, a);
    if (!(gy * e[1] + fy * a <= target))
        hi = 0;
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        e = carry_texel(c, s0, t, mid, py, a);
        if (gy * e[1] + fy * a <= target) lo = mid; else hi = mid;
    }
    int px = lo;
    float v[9];
    carry_patch(c, s0, t, py, px, v);
    float c0 = gy * v[0] + fy * v[2], c1 = gy * v[1] + fy * v[3];
    float fx = carry_root(0.5 * (c1 - c0), c0, target - (gy * v[4] + fy * v[5]));
    float u_x = (px + fx) / (c.nx - 1), u_y = (py + fy) / (c.ny - 1);
    float theta_h = u_x * u_x * (0.5 * M_PI), phi_h = u_y * (2.0 * M_PI) - M_PI;
    vector h = vector(sin(theta_h) * cos(phi_h), sin(theta_h) * sin(phi_h), cos(theta_h));
    vector wi = carry_wi(cos_i);
    float cos_ih = dot(h, wi);
    wo = 2.0 * cos_ih * h - wi;
    jac = (cos_ih > 0.0 && wo[2] > 0.0) ? carry_jac(c, wi, u_x, h, (1.0 - fx) * c0 + fx * c1) * rim : 0.0;
}

// Whether theta_i carries (c.on, with a carry texture: its interval's flag, above its first bin, past
// the last bin too: its directions carried on, as CarriedTables does), and the angles of its
// two bins (bl: the shading point's Blend, tables.h).
int carry_interval(Carry c, Blend bl, output float theta[2])
{
    if (!c.on)
        return 0;
    theta[0] = fetch1(c.file, c.W, c.H, 2 + c.S + bl.bins[0], 0);
    theta[1] = fetch1(c.file, c.W, c.H, 2 + c.S + bl.bins[1], 0);
    color flag = fetch(c.file, c.W, c.H, 2 + c.S + bl.bins[0], 0);
    return flag[1] > 0.5 && bl.w[1] > 0.0 && bl.bins[1] == bl.bins[0] + 1;
}

// Adds bin q's term of the carried sum at s: w_q {pdf, f cos}_q(W_q^-1(s)) J_q / J (J: d omega / d s
// at theta_i).
void carry_term(TablesTexture tab, Carry c, int bin, float theta_q, float w_q, float s_x, float s_y, float jac,
                output color fcos, output float pdf)
{
    vector wo_q;
    float jac_q, pdf_q;
    color fcos_q;
    carry_from_s(c, cos(theta_q), theta_q, s_x, s_y, wo_q, jac_q);
    if (jac_q > 0.0) {
        eval_tables(tab, fetch1(tab.file, tab.W, tab.H, bin, 1), 0.0, wo_q, fcos_q, pdf_q);
        pdf += w_q * pdf_q * (jac_q / jac);
        fcos += w_q * fcos_q * (jac_q / jac);
    }
}

// eval_tables, carried where the interval carries: pdf per steradian and baked f cos at wo.
void eval_bsdf(TablesTexture tab, Carry c, Blend bl, float cos_i, float phi_i, vector wo, output color fcos,
               output float pdf)
{
    float theta_j[2];
    if (!carry_interval(c, bl, theta_j)) {
        eval_blend(tab, bl, cos_i, phi_i, wo, fcos, pdf);
        return;
    }
    fcos = 0;
    pdf = 0;
    if (wo[2] <= 0.0)
        return;
    float s_x, s_y, jac;
    carry_to_s(c, cos_i, acos(cos_i), wo, s_x, s_y, jac);
    if (jac <= 0.0)
        return;
    for (int q = 0; q < 2; q++)
        if (bl.w[q] > 0.0)
            carry_term(tab, c, bl.bins[q], theta_j[q], bl.w[q], s_x, s_y, jac, fcos, pdf);
}

// sample_tables, carried where the interval carries: wo, its weight (baked f cos / pdf) and pdf.
void sample_bsdf(TablesTexture tab, Carry c, Blend bl, float cos_i, float phi_i, float u0, float u1,
                 output vector wo, output color weight, output float pdf)
{
    float theta_j[2];
    if (!carry_interval(c, bl, theta_j)) {
        sample_blend(tab, bl, cos_i, phi_i, u0, u1, wo, weight, pdf);
        return;
    }
    int j = (u0 < bl.w[0]) ? 0 : 1, o = 1 - j;
    float u = (j == 0) ? u0 / bl.w[0] : (u0 - bl.w[0]) / bl.w[1];
    vector wo_j;
    color weight_j;
    float pdf_j, s_x, s_y, jac_j, jac;
    sample_tables(tab, fetch1(tab.file, tab.W, tab.H, bl.bins[j], 1), 0.0, clamp(u, 0.0, 0.99999994), u1,
                  wo_j, weight_j, pdf_j);
    carry_to_s(c, cos(theta_j[j]), theta_j[j], wo_j, s_x, s_y, jac_j);
    carry_from_s(c, cos_i, acos(cos_i), s_x, s_y, wo, jac);
    if (jac_j <= 0.0) {     // no warp density at wo_j (rare): the pdf as eval_bsdf reads it at wo
        color fcos;
        eval_bsdf(tab, c, bl, cos_i, phi_i, wo, fcos, pdf);
        weight = (pdf > 0.0) ? fcos / pdf : color(0);
        return;
    }
    // eval_bsdf at wo, from the sampling chain's own values for bin j (its table's pdf and weight
    // at wo_j, d omega / d s both ways): one carry and one table lookup less
    pdf = 0;
    weight = 0;
    if (jac <= 0.0)
        return;         // s reaches no direction above the horizon at theta_i: lost
    color fcos = bl.w[j] * weight_j * pdf_j * (jac_j / jac);
    pdf = bl.w[j] * pdf_j * (jac_j / jac);
    if (bl.w[o] > 0.0)
        carry_term(tab, c, bl.bins[o], theta_j[o], bl.w[o], s_x, s_y, jac, fcos, pdf);
    weight = (pdf > 0.0) ? fcos / pdf : color(0);
}
