/* The C fast path of bake/tables.py's Tables: sample, pdf, invert, eval.
 *
 * A transcription of the numpy reference (Tables.sample/_locate/pdf/invert/eval,
 * exp_cdf/exp_inverse_cdf/exp_density, to_ab/from_ab, _search, _bins): the same formulas
 * in the same order of operations, the same branches, clipping and small-rate series, so
 * results agree with numpy to a few ulps (only libm's transcendental functions may round
 * differently from numpy's). One thread, no Python API: loaded with ctypes by
 * bake/fasttables.py, which passes the Tables' float64 working arrays and preallocated
 * outputs.
 *
 * Two things make it fast without changing a single rounding:
 * - Blocks: samples go through in blocks of BLK, phase by phase (bins, row search, column
 *   search, the rest). The searches of a block run in lockstep, so the CPU overlaps the
 *   load latencies of independent samples instead of waiting on one chain per sample.
 * - One wi per call ("flat" mode): when every sample shares wi and there are many, the
 *   interpolated table of that wi (the same lerps numpy evaluates per sample) and expm1 of
 *   every cell's rates are computed once; the samples then read them. Same values, bit for
 *   bit, as computing them per sample.
 *
 * Build with -ffp-contract=off (no fused multiply-add: it would round the interpolations
 * differently from numpy) and never with -ffast-math.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>

#if defined(_WIN32)
#define FT_EXPORT __declspec(dllexport)
#else
#define FT_EXPORT __attribute__((visibility("default")))
#endif

#if defined(__GNUC__)
#define FT_INLINE static inline __attribute__((always_inline))
#elif defined(_MSC_VER)
#define FT_INLINE static __forceinline
#else
#define FT_INLINE static inline
#endif

#ifndef FT_SOURCE_SHA
#define FT_SOURCE_SHA "unknown"
#endif

/* Bumped whenever ft_tables or a signature changes (bake/fasttables.py checks it). */
#define FT_ABI 1

static const double PI = 3.141592653589793;       /* np.pi */
static const double TWO_PI = 6.283185307179586;   /* 2.0 * np.pi */
static const double SMALL = 1e-4;                 /* tables._SMALL */

#define BLK 16      /* samples per block (see the header) */

/* The Tables, as bake/fasttables.py passes them (C-contiguous arrays). */
typedef struct {
    int64_t K, R, C;
    const double *theta_bins;  /* (K) */
    const double *cos_bins;    /* (K) np.cos(theta_bins) */
    const double *a;           /* (K, R+1)    _a */
    const double *b;           /* (K, R, C+1) _b */
    const double *m;           /* (K, R, C)   _m */
    const double *alpha;       /* (K, R, C)   _alpha */
    const double *beta;        /* (K, R, C)   _beta */
    const double *row_cdf;     /* (K, R+1)    _row_cdf */
    const double *col_cum;     /* (K, R, C+1) _col_cum */
    const float *weights;      /* (K, R, C, 3) weights */
} ft_tables;

FT_EXPORT int ft_abi(void) { return FT_ABI; }
FT_EXPORT const char *ft_source_sha(void) { return FT_SOURCE_SHA; }

/* setuptools builds this file as an "extension module" only to get a shared library built
 * and installed; on Windows its linker insists on this export. Never imported. */
FT_EXPORT void *PyInit__tables_c(void) { return NULL; }

/* ------------------------------------------------------------------------ elementary */

/* np.clip(x, 0, 1): NaN stays NaN */
FT_INLINE double clip01(double x) { return x < 0.0 ? 0.0 : (x > 1.0 ? 1.0 : x); }

/* np.mod(x, 2 pi) for float64 (numpy's npy_divmod: fmod, then shifted to the divisor's
 * sign). fmod is exact; below 2 (2 pi) it is x or x -+ 2 pi, both exact (Sterbenz). */
FT_INLINE double mod_two_pi(double x) {
    const double ax = fabs(x);
    double r;
    if (ax < TWO_PI) r = x;
    else if (ax < 2.0 * TWO_PI) r = x - copysign(TWO_PI, x);
    else r = fmod(x, TWO_PI);
    if (r != 0.0) {
        if (r < 0.0) r += TWO_PI;
    } else {
        r = 0.0;
    }
    return r;
}

/* expm1(k), the one every exact branch below needs (0: unused, |k| < SMALL) */
FT_INLINE double rate_e(double k) { return fabs(k) < SMALL ? 0.0 : expm1(k); }

/* exp_cdf, exp_inverse_cdf, exp_density of tables.py; e = rate_e(k) */
FT_INLINE double exp_cdf(double x, double k, double e) {
    if (fabs(k) < SMALL) return x + 0.5 * k * (x * x - x);
    return expm1(k * x) / e;
}

FT_INLINE double exp_inverse_cdf(double u, double k, double e) {
    double r;
    if (fabs(k) < SMALL) r = u - 0.5 * k * (u * u - u);
    else r = log1p(u * e) / k;
    return clip01(r);
}

FT_INLINE double exp_density(double x, double k, double e) {
    if (fabs(k) < SMALL) return 1.0 + k * (x - 0.5);
    return k * exp(k * x) / e;
}

/* ------------------------------------------------------------------------ bins, views */

/* One sample's interpolation: (1 - t) bin k0 + t bin k1. Offsets of bin k0 in the row
 * arrays (a, row_cdf), the row x column+1 arrays (b, col_cum) and the cell arrays; d*: bin
 * k1's offset minus k0's. In flat mode all offsets are 0 and s, t unused. */
typedef struct {
    double s, t, phi_ref;
    ptrdiff_t ka, kb, kc, da, db, dc;
} ft_bin;

/* The arrays the kernels read: the Tables' (interpolated per sample) or, in flat mode,
 * one wi's interpolated table, with expm1 of the rates (ea, eb) and float64 weights. */
typedef struct {
    int64_t R, C;
    const double *a, *b, *m, *alpha, *beta, *row_cdf, *col_cum;
    const float *w32;                  /* interpolated mode */
    const double *ea, *eb, *w64;       /* flat mode (w64 only for eval) */
} ft_view;

/* Tables._bins for one wi, from theta, phi (geometry.theta_phi) and cos(theta) (unused
 * when K == 1) */
static void bin_of(const ft_tables *T, double theta, double phi, double cos_theta, ft_bin *B) {
    const int64_t K = T->K, R = T->R, C = T->C;
    int64_t k0 = 0, k1 = 0;
    double t = 0.0;
    if (K != 1) {
        /* np.clip(np.searchsorted(theta_bins, theta, side="right") - 1, 0, K - 2);
         * numpy sorts NaN last, so a NaN theta lands past every bin. */
        int64_t n = 0;
        if (isnan(theta)) n = K;
        else while (n < K && T->theta_bins[n] <= theta) n++;
        int64_t k = n - 1;
        if (k < 0) k = 0;
        if (k > K - 2) k = K - 2;
        const double ck = T->cos_bins[k], ck1 = T->cos_bins[k + 1];
        t = clip01((ck - cos_theta) / (ck - ck1));
        k0 = k;
        k1 = k + 1;
    }
    B->s = 1.0 - t;
    B->t = t;
    B->phi_ref = phi + PI;
    B->ka = k0 * (R + 1);
    B->da = (k1 - k0) * (R + 1);
    B->kb = k0 * R * (C + 1);
    B->db = (k1 - k0) * R * (C + 1);
    B->kc = k0 * R * C;
    B->dc = (k1 - k0) * R * C;
}

/* The bins of nb directions w (row stride `stride`), one libm function per loop so the
 * calls of different samples overlap. */
static void bins(const ft_tables *T, const double *w, int64_t stride, int nb, ft_bin *B) {
    double theta[BLK], phi[BLK], c[BLK];
    for (int k = 0; k < nb; k++) theta[k] = hypot(w[k * stride], w[k * stride + 1]);
    for (int k = 0; k < nb; k++) theta[k] = atan2(theta[k], w[k * stride + 2]);
    for (int k = 0; k < nb; k++) phi[k] = atan2(w[k * stride + 1], w[k * stride]);
    for (int k = 0; k < nb; k++) c[k] = T->K != 1 ? cos(theta[k]) : 0.0;
    for (int k = 0; k < nb; k++) bin_of(T, theta[k], phi[k], c[k], &B[k]);
}

/* Tables._lerp of one element: x[off] of bin k0 with x[off + d] of bin k1; in flat mode
 * the (already interpolated) x[off]. */
#define AT(x, off, d, Bk) (flat ? (x)[off] : (Bk).s * (x)[off] + (Bk).t * (x)[(off) + (d)])

/* The flat view of one wi (bin B) into buf; returns 0 when out of memory. */
static int flatten(const ft_tables *T, const ft_bin *B, int with_weights, ft_view *V, double **buf) {
    const int64_t R = T->R, C = T->C, rows = R + 1, edges = R * (C + 1), cells = R * C;
    const double s = B->s, t = B->t;
    double *p = malloc(sizeof(double) * (size_t)(2 * rows + 2 * edges + (5 + (with_weights ? 3 : 0)) * cells));
    if (!p) return 0;
    *buf = p;
    double *a = p, *row_cdf = a + rows, *b = row_cdf + rows, *col_cum = b + edges, *m = col_cum + edges;
    double *alpha = m + cells, *beta = alpha + cells, *ea = beta + cells, *eb = ea + cells, *w = eb + cells;
    for (int64_t i = 0; i < rows; i++) {
        a[i] = s * T->a[B->ka + i] + t * T->a[B->ka + B->da + i];
        row_cdf[i] = s * T->row_cdf[B->ka + i] + t * T->row_cdf[B->ka + B->da + i];
    }
    for (int64_t i = 0; i < edges; i++) {
        b[i] = s * T->b[B->kb + i] + t * T->b[B->kb + B->db + i];
        col_cum[i] = s * T->col_cum[B->kb + i] + t * T->col_cum[B->kb + B->db + i];
    }
    for (int64_t i = 0; i < cells; i++) {
        m[i] = s * T->m[B->kc + i] + t * T->m[B->kc + B->dc + i];
        alpha[i] = s * T->alpha[B->kc + i] + t * T->alpha[B->kc + B->dc + i];
        beta[i] = s * T->beta[B->kc + i] + t * T->beta[B->kc + B->dc + i];
        ea[i] = rate_e(alpha[i]);
        eb[i] = rate_e(beta[i]);
    }
    if (with_weights)
        for (int64_t i = 0; i < 3 * cells; i++)
            w[i] = s * (double)T->weights[3 * B->kc + i] + t * (double)T->weights[3 * (B->kc + B->dc) + i];
    *V = (ft_view){R, C, a, b, m, alpha, beta, row_cdf, col_cum, NULL, ea, eb, with_weights ? w : NULL};
    return 1;
}

/* ------------------------------------------------------------------------ kernels */

/* _search for nb samples in lockstep: per sample, the i in [0, n) with
 * edge(i) <= value < edge(i + 1), i.e. the largest i in [0, n) with edge(i) <= value, or 0.
 * Sample k's edges are x[off[k] + i] (interpolated with x[off[k] + d[k] + i]).
 * Interpolated edges and cumulative masses never decrease (a sum of two non-decreasing
 * roundings), so those i form a prefix and any bisection finds numpy's i. Branch-free: a
 * conditional move per halving (a mispredicted branch would cost more than the rest). */
FT_INLINE void search_block(int nb, const double *value, int64_t n, const double *x, const ptrdiff_t *off,
                            const ptrdiff_t *d, const ft_bin *B, int64_t *lo, const int flat) {
    for (int k = 0; k < nb; k++) lo[k] = 0;
    int64_t len = n;
    while (len > 1) {
        const int64_t half = len / 2;
        for (int k = 0; k < nb; k++) {
            const int64_t mid = lo[k] + half;
            const double e = AT(x, off[k] + mid, d[k], B[k]);
            lo[k] = (e <= value[k]) ? mid : lo[k];
        }
        len -= half;
    }
}

typedef struct {
    double a0, a1, b0, b1, m, ka, kb, ea, eb;
} ft_cell;

/* Tables._cell, with the rates' expm1 */
FT_INLINE void cell(const ft_view *V, const ft_bin *B, int64_t i, int64_t j, ft_cell *c, const int flat) {
    const ptrdiff_t ia = B->ka + i, ib = B->kb + i * (V->C + 1) + j, ic = B->kc + i * V->C + j;
    c->a0 = AT(V->a, ia, B->da, *B);
    c->a1 = AT(V->a, ia + 1, B->da, *B);
    c->b0 = AT(V->b, ib, B->db, *B);
    c->b1 = AT(V->b, ib + 1, B->db, *B);
    c->m = AT(V->m, ic, B->dc, *B);
    c->ka = AT(V->alpha, ic, B->dc, *B);
    c->kb = AT(V->beta, ic, B->dc, *B);
    c->ea = flat ? V->ea[ic] : rate_e(c->ka);
    c->eb = flat ? V->eb[ic] : rate_e(c->kb);
}

/* Tables.sample for samples [0, nb) of a block: u (nb, 2) -> wo (nb, 3), pdf (nb) */
FT_INLINE void sample_block(const ft_view *V, const ft_bin *B, int nb, const double *u, double *wo,
                            double *pdf, const int flat) {
    const int64_t R = V->R, C = V->C;
    int64_t I[BLK], J[BLK];
    double val[BLK], c0[BLK], c1[BLK];
    ptrdiff_t off[BLK], d[BLK];
    for (int k = 0; k < nb; k++) {
        val[k] = u[2 * k];
        off[k] = B[k].ka;
        d[k] = B[k].da;
    }
    search_block(nb, val, R, V->row_cdf, off, d, B, I, flat);
    for (int k = 0; k < nb; k++) {
        c0[k] = AT(V->row_cdf, B[k].ka + I[k], B[k].da, B[k]);
        c1[k] = AT(V->row_cdf, B[k].ka + I[k] + 1, B[k].da, B[k]);
        val[k] = u[2 * k + 1] * (c1[k] - c0[k]);          /* v */
        off[k] = B[k].kb + I[k] * (C + 1);
        d[k] = B[k].db;
    }
    search_block(nb, val, C, V->col_cum, off, d, B, J, flat);
    /* The rest in short loops over the block, one libm function each: the calls of
     * different samples are independent, so they overlap in the CPU. */
    ft_cell cells[BLK];
    double X[BLK], Y[BLK];
    for (int k = 0; k < nb; k++) {
        const double d0 = AT(V->col_cum, off[k] + J[k], B[k].db, B[k]);
        cell(V, &B[k], I[k], J[k], &cells[k], flat);
        X[k] = clip01((u[2 * k] - c0[k]) / (c1[k] - c0[k]));
        Y[k] = clip01((val[k] - d0) / cells[k].m);
    }
    for (int k = 0; k < nb; k++) X[k] = exp_inverse_cdf(X[k], cells[k].ka, cells[k].ea);
    for (int k = 0; k < nb; k++) Y[k] = exp_inverse_cdf(Y[k], cells[k].kb, cells[k].eb);
    for (int k = 0; k < nb; k++) {
        /* from_ab */
        const ft_cell *c = &cells[k];
        const double a = c->a0 + X[k] * (c->a1 - c->a0), b = c->b0 + Y[k] * (c->b1 - c->b0);
        double r2 = a * (2.0 - a);
        r2 = r2 < 0.0 ? 0.0 : r2;   /* np.maximum(., 0): NaN stays NaN */
        const double sn = sqrt(r2);
        const double phi = b - PI + B[k].phi_ref;
        wo[3 * k] = sn * cos(phi);
        wo[3 * k + 1] = sn * sin(phi);
        wo[3 * k + 2] = 1.0 - a;
    }
    for (int k = 0; k < nb; k++) {
        const ft_cell *c = &cells[k];
        pdf[k] = c->m * exp_density(X[k], c->ka, c->ea) * exp_density(Y[k], c->kb, c->eb)
                 / ((c->a1 - c->a0) * (c->b1 - c->b0));
    }
}

/* Tables._locate for wo[0, nb) of a block: cell (I, J), in-cell X, Y, the cell, and when
 * want_p the unmasked pdf P. */
FT_INLINE void locate_block(const ft_view *V, const ft_bin *B, int nb, const double *wo, int64_t *I, int64_t *J,
                            double *X, double *Y, ft_cell *cells, double *P, const int want_p, const int flat) {
    const int64_t R = V->R, C = V->C;
    double A[BLK], Bv[BLK];
    ptrdiff_t off[BLK], d[BLK];
    for (int k = 0; k < nb; k++) Bv[k] = atan2(wo[3 * k + 1], wo[3 * k]);
    for (int k = 0; k < nb; k++) {
        /* to_ab */
        const double *w = wo + 3 * k;
        const double z = w[2];
        const double a = (w[0] * w[0] + w[1] * w[1]) / (1.0 + (z < 0.0 ? 0.0 : z));
        A[k] = z > 0.0 ? (a > 1.0 ? 1.0 : a) : 1.0;
        Bv[k] = mod_two_pi(Bv[k] - B[k].phi_ref + PI);
        off[k] = B[k].ka;
        d[k] = B[k].da;
    }
    search_block(nb, A, R, V->a, off, d, B, I, flat);
    for (int k = 0; k < nb; k++) {
        off[k] = B[k].kb + I[k] * (C + 1);
        d[k] = B[k].db;
    }
    search_block(nb, Bv, C, V->b, off, d, B, J, flat);
    for (int k = 0; k < nb; k++) {
        ft_cell *c = &cells[k];
        cell(V, &B[k], I[k], J[k], c, flat);
        X[k] = clip01((A[k] - c->a0) / (c->a1 - c->a0));
        Y[k] = clip01((Bv[k] - c->b0) / (c->b1 - c->b0));
    }
    if (want_p)
        for (int k = 0; k < nb; k++) {
            const ft_cell *c = &cells[k];
            P[k] = c->m * exp_density(X[k], c->ka, c->ea) * exp_density(Y[k], c->kb, c->eb)
                   / ((c->a1 - c->a0) * (c->b1 - c->b0));
        }
}

/* Tables.pdf: 0 below the horizon */
FT_INLINE void pdf_block(const ft_view *V, const ft_bin *B, int nb, const double *wo, double *pdf, const int flat) {
    int64_t I[BLK], J[BLK];
    double X[BLK], Y[BLK], P[BLK];
    ft_cell cells[BLK];
    locate_block(V, B, nb, wo, I, J, X, Y, cells, P, 1, flat);
    for (int k = 0; k < nb; k++) pdf[k] = wo[3 * k + 2] > 0.0 ? P[k] : 0.0;
}

/* Tables.invert: wo -> u (nb, 2) */
FT_INLINE void invert_block(const ft_view *V, const ft_bin *B, int nb, const double *wo, double *u, const int flat) {
    const int64_t C = V->C;
    int64_t I[BLK], J[BLK];
    double X[BLK], Y[BLK];
    ft_cell cells[BLK];
    locate_block(V, B, nb, wo, I, J, X, Y, cells, NULL, 0, flat);
    for (int k = 0; k < nb; k++) {
        const ptrdiff_t row = B[k].kb + I[k] * (C + 1);
        const double c0 = AT(V->row_cdf, B[k].ka + I[k], B[k].da, B[k]);
        const double c1 = AT(V->row_cdf, B[k].ka + I[k] + 1, B[k].da, B[k]);
        const double d0 = AT(V->col_cum, row + J[k], B[k].db, B[k]);
        const double d1 = AT(V->col_cum, row + J[k] + 1, B[k].db, B[k]);
        const ft_cell *c = &cells[k];
        u[2 * k] = c0 + exp_cdf(X[k], c->ka, c->ea) * (c1 - c0);
        u[2 * k + 1] = (d0 + exp_cdf(Y[k], c->kb, c->eb) * (d1 - d0)) / (c1 - c0);
    }
}

/* Tables.eval: the cell's RGB weight x pdf / cos(theta_o); 0 unless wi and wo are both
 * above the horizon (wi_z: each sample's wi z) */
FT_INLINE void eval_block(const ft_view *V, const ft_bin *B, int nb, const double *wo, const double *wi_z,
                          int64_t wi_stride, double *f, const int flat) {
    const int64_t C = V->C;
    int64_t I[BLK], J[BLK];
    double X[BLK], Y[BLK], P[BLK];
    ft_cell cells[BLK];
    locate_block(V, B, nb, wo, I, J, X, Y, cells, P, 1, flat);
    for (int k = 0; k < nb; k++) {
        const double z = wo[3 * k + 2];
        const int above = z > 0.0 && wi_z[k * wi_stride] > 0.0;
        const double scale = P[k] / z;
        const ptrdiff_t ic = B[k].kc + I[k] * C + J[k];
        for (int ch = 0; ch < 3; ch++) {
            const double wc = flat ? V->w64[3 * ic + ch]
                                   : B[k].s * (double)V->w32[3 * ic + ch] + B[k].t * (double)V->w32[3 * (ic + B[k].dc) + ch];
            f[3 * k + ch] = above ? wc * scale : 0.0;
        }
    }
}

/* ------------------------------------------------------------------------ entry points */

enum { SAMPLE, PDF, INVERT, EVAL };

/* Flat mode pays for itself from about one sample per cell. */
#define FLAT_MIN_SAMPLES(R, C) ((R) * (C))

FT_INLINE void run_block(int kind, const ft_view *V, const ft_bin *B, int nb, int64_t q0, const double *wi,
                         int64_t wi_stride, const double *in, double *out, double *out2, const int flat) {
    switch (kind) {
    case SAMPLE: sample_block(V, B, nb, in + 2 * q0, out + 3 * q0, out2 + q0, flat); break;
    case PDF: pdf_block(V, B, nb, in + 3 * q0, out + q0, flat); break;
    case INVERT: invert_block(V, B, nb, in + 3 * q0, out + 2 * q0, flat); break;
    default: eval_block(V, B, nb, in + 3 * q0, wi + q0 * wi_stride + 2, wi_stride, out + 3 * q0, flat); break;
    }
}

/* The n samples: wi (n, 3) with row stride wi_stride (3, or 0: one wi for all), in (n, 2)
 * u or (n, 3) wo, out (and out2: sample's pdf). */
static void run(int kind, const ft_tables *T, int64_t n, const double *wi, int64_t wi_stride, const double *in,
                double *out, double *out2) {
    ft_bin B[BLK];
    ft_view V = {T->R, T->C, T->a, T->b, T->m, T->alpha, T->beta, T->row_cdf, T->col_cum, T->weights,
                 NULL, NULL, NULL};
    double *buf = NULL;
    if (n <= 0) return;
    if (wi_stride == 0) {
        bins(T, wi, 0, 1, B);
        if (n >= FLAT_MIN_SAMPLES(T->R, T->C) && flatten(T, &B[0], kind == EVAL, &V, &buf)) {
            B[0].ka = B[0].kb = B[0].kc = B[0].da = B[0].db = B[0].dc = 0;
        }
        for (int k = 1; k < BLK; k++) B[k] = B[0];
    }
    for (int64_t q0 = 0; q0 < n; q0 += BLK) {
        const int nb = n - q0 < BLK ? (int)(n - q0) : BLK;
        if (wi_stride != 0)
            bins(T, wi + q0 * wi_stride, wi_stride, nb, B);
        if (buf) run_block(kind, &V, B, nb, q0, wi, wi_stride, in, out, out2, 1);
        else run_block(kind, &V, B, nb, q0, wi, wi_stride, in, out, out2, 0);
    }
    free(buf);
}

/* Tables.sample: u (n, 2) -> wo (n, 3), pdf (n) */
FT_EXPORT void ft_sample(const ft_tables *T, int64_t n, const double *wi, int64_t wi_stride, const double *u,
                         double *wo, double *pdf) {
    run(SAMPLE, T, n, wi, wi_stride, u, wo, pdf);
}

/* Tables.pdf: wo (n, 3) -> pdf (n) */
FT_EXPORT void ft_pdf(const ft_tables *T, int64_t n, const double *wi, int64_t wi_stride, const double *wo,
                      double *pdf) {
    run(PDF, T, n, wi, wi_stride, wo, pdf, NULL);
}

/* Tables.invert: wo (n, 3) -> u (n, 2) */
FT_EXPORT void ft_invert(const ft_tables *T, int64_t n, const double *wi, int64_t wi_stride, const double *wo,
                         double *u) {
    run(INVERT, T, n, wi, wi_stride, wo, u, NULL);
}

/* Tables.eval: wo (n, 3) -> f (n, 3) */
FT_EXPORT void ft_eval(const ft_tables *T, int64_t n, const double *wi, int64_t wi_stride, const double *wo,
                       double *f) {
    run(EVAL, T, n, wi, wi_stride, wo, f, NULL);
}
