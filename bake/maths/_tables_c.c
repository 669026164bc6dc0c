/* The C fast path of bake/core/tables.py's Tables: sample, pdf, invert, eval.
 *
 * A transcription of the numpy reference (Tables.sample/_locate/pdf/invert/eval,
 * the profiles' and exponentials' CDFs, to_ab/from_ab, _search, _bins): the same formulas
 * in the same order of operations, the same branches, clipping and small-rate series, so
 * results agree with numpy to a few ulps (only libm's transcendental functions may round
 * differently from numpy's). One thread, no Python API: loaded with ctypes by
 * bake/maths/fasttables.py, which passes the Tables' float64 working arrays and preallocated
 * outputs.
 *
 * One translation unit (~1300 lines) on purpose: ctypes loads one library, and the sampler,
 * pdf, inverse and eval share their static helpers (the compiler inlines them across calls).
 *
 * Four things make it fast without changing a single rounding:
 * - Blocks: samples go through in blocks of BLK, phase by phase (bins, row search, column
 *   search, the rest). The searches of a block run in lockstep, so the CPU overlaps the
 *   load latencies of independent samples instead of waiting on one chain per sample.
 * - No branch on a sample's data where the data decide it at random (the theta bin of a
 *   new wi, the sign in mod 2 pi): with a new wi per sample, those mispredicted branches
 *   alone made sample and pdf 1.3x slower (measured).
 * - A new wi per sample, many samples: the samples run grouped by their incident bins (see
 *   "Grouping" below), whose values then come from cache.
 * - One wi per call ("flat" mode): when every sample shares wi and there are many, the
 *   interpolated table of that wi (the same lerps numpy evaluates per sample) is computed
 *   once; the samples then read it. Same values, bit for bit, as computing them per sample.
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

/* Vector math (GCC on x86-64 Linux): the per-block loops of libm calls run through glibc's
 * libmvec (4 or 8 lanes, <= 4 ulp like libm), and `run` is compiled for AVX-512, AVX2 and
 * the baseline, picked at load time by the CPU. Every sample goes through full blocks (run
 * pads the last one), so a sample's result never depends on its place in a call. Build
 * with -fopenmp-simd and link -lmvec; FT_NO_MVEC (or another compiler) builds plain C. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__) && !defined(FT_NO_MVEC)
#define FT_VEC __attribute__((simd("notinbranch")))
double exp(double) FT_VEC;
double expm1(double) FT_VEC;
double log(double) FT_VEC;
double log1p(double) FT_VEC;
double atan2(double, double) FT_VEC;
double asin(double) FT_VEC;
double hypot(double, double) FT_VEC;
double cos(double) FT_VEC;
double sin(double) FT_VEC;
#define FT_SIMD _Pragma("omp simd")
#define FT_CLONES __attribute__((target_clones("avx512f", "avx2", "default"), noinline))
#else
#define FT_SIMD
#define FT_CLONES
#endif

#ifndef FT_SOURCE_SHA
#define FT_SOURCE_SHA "unknown"
#endif

/* Bumped whenever ft_tables or a signature changes (bake/maths/fasttables.py checks it). */
#define FT_ABI 8

static const double PI = 3.141592653589793;       /* np.pi */
static const double TWO_PI = 6.283185307179586;   /* 2.0 * np.pi */
static const double SMALL = 1e-4;                 /* profiles._SMALL */
static const double QUARTER = 0.7853981633974483; /* halfvector.QUARTER, 0.25 * np.pi */
static const double TINY = 1e-300;                /* halfvector._TINY */

#define BLK 16      /* samples per block (see the header) */
#define NSEG 3      /* profiles.NSEG: a profile's pieces */
#define NN 4        /* and its node values */
static const double LOG_MEAN_SERIES = 1e-3;       /* profiles.LOG_MEAN_SERIES */

/* The Tables, as bake/maths/fasttables.py passes them (C-contiguous arrays). Anisotropic
 * tables (P > 1, halfvector coordinates only): bins k P + p, the phi axis closed (the last
 * bin one period after the first), starts = phi_bins - phi_bins[0]. */
typedef struct {
    int64_t K, R, C, P, coords;    /* coords: 0 "wo", 1 "halfvector", 2 "halfpolar" (isotropic) */
    double period, frame, phi0;    /* anisotropic: phi_period, frame_angle, phi_bins[0] */
    const double *starts;      /* (P) */
    const double *theta_bins;  /* (K) */
    const double *cos_bins;    /* (K) np.cos(theta_bins) */
    const double *a;           /* (K, R+1)    _a */
    const double *b;           /* (K, R, C+1) _b */
    const double *m;           /* (K, R, C)   _m */
    const double *alpha;       /* (K, R, C, NN) _alpha (the a profiles' node values, normalized) */
    const double *beta;        /* (K, R, C, NN) _beta (the b profiles') */
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
    double r = x;
    if (ax >= TWO_PI) r = ax < 2.0 * TWO_PI ? x - copysign(TWO_PI, x) : fmod(x, TWO_PI);   /* rare */
    /* arithmetic, not a branch: the sign of r is a coin toss. r + 0.0 turns -0.0 into 0.0. */
    return r + TWO_PI * (double)(r < 0.0);
}

/* The exponential of a profile's piece, for a block: rate_e (expm1(k), the one every exact
 * branch needs; 0 when unused, |k| < SMALL) and exp_cdf, exp_inverse_cdf of profiles.py
 * (e = rate_e(k)). Each computes its libm function for every lane in a loop of
 * its own (vector lanes; a call under a branch would not vectorize), then selects. */
FT_INLINE void rate_e(const double *k, double *e) {
    double t[BLK];
    FT_SIMD for (int q = 0; q < BLK; q++) t[q] = expm1(k[q]);
    for (int q = 0; q < BLK; q++) e[q] = fabs(k[q]) < SMALL ? 0.0 : t[q];
}

FT_INLINE void exp_cdf(const double *x, const double *k, const double *e, double *out) {
    double t[BLK];
    FT_SIMD for (int q = 0; q < BLK; q++) t[q] = expm1(k[q] * x[q]);
    for (int q = 0; q < BLK; q++)
        out[q] = fabs(k[q]) < SMALL ? x[q] + 0.5 * k[q] * (x[q] * x[q] - x[q]) : t[q] / e[q];
}

FT_INLINE void exp_inverse_cdf(const double *u, const double *k, const double *e, double *out) {
    double t[BLK];
    FT_SIMD for (int q = 0; q < BLK; q++) t[q] = log1p(u[q] * e[q]);
    for (int q = 0; q < BLK; q++)
        out[q] = clip01(fabs(k[q]) < SMALL ? u[q] - 0.5 * k[q] * (u[q] * u[q] - u[q]) : t[q] / k[q]);
}

/* The profiles of a block's cells (profiles.profile_parts, profile_sample, profile_density,
 * profile_cdf): node values V[n][lane]. Each libm call in a loop of its own, as above. */
FT_INLINE void profile_parts(const double V[NN][BLK], double M[NSEG][BLK], double *tot, double LR[NSEG][BLK]) {
    for (int n = 0; n < NSEG; n++) {
        double r[BLK];
        for (int q = 0; q < BLK; q++) r[q] = V[n + 1][q] / V[n][q];
        FT_SIMD for (int q = 0; q < BLK; q++) LR[n][q] = log(r[q]);
        for (int q = 0; q < BLK; q++) {
            const double lr = LR[n][q];
            const double lm = fabs(lr) < LOG_MEAN_SERIES ? 1.0 + lr * (0.5 + lr / 6.0) : (r[q] - 1.0) / lr;
            M[n][q] = V[n][q] * lm / NSEG;
        }
    }
    for (int q = 0; q < BLK; q++) tot[q] = (M[0][q] + M[1][q]) + M[2][q];
}

/* A piece's start value and log rate, per lane (piece k[q]): the log profile_parts took */
FT_INLINE void piece_rate(const double V[NN][BLK], const double LR[NSEG][BLK], const int64_t *k, double *v0,
                          double *rate) {
    for (int q = 0; q < BLK; q++) {
        v0[q] = V[k[q]][q];
        rate[q] = LR[k[q]][q];
    }
}

/* profiles.profile_sample: the place x and the density there (from the piece found) */
FT_INLINE void profile_sample(const double *u, const double V[NN][BLK], double *out, double *dens) {
    double M[NSEG][BLK], LR[NSEG][BLK], tot[BLK], target[BLK], prev[BLK], rem[BLK], v0[BLK], rate[BLK], e[BLK],
        t[BLK], g[BLK];
    int64_t k[BLK];
    profile_parts(V, M, tot, LR);
    for (int q = 0; q < BLK; q++) {
        target[q] = clip01(u[q]) * tot[q];
        const double c0 = M[0][q], c1 = c0 + M[1][q];
        k[q] = (int64_t)(c0 <= target[q]) + (int64_t)(c1 <= target[q]);
        prev[q] = k[q] == 0 ? 0.0 : (k[q] == 1 ? c0 : c1);
    }
    piece_rate(V, LR, k, v0, rate);
    for (int q = 0; q < BLK; q++) rem[q] = clip01((target[q] - prev[q]) / M[k[q]][q]);
    rate_e(rate, e);
    exp_inverse_cdf(rem, rate, e, t);
    FT_SIMD for (int q = 0; q < BLK; q++) g[q] = exp(t[q] * rate[q]);
    for (int q = 0; q < BLK; q++) {
        out[q] = ((double)k[q] + t[q]) / NSEG;
        dens[q] = v0[q] * g[q] / tot[q];
    }
}

/* profiles._piece: piece k and place t of x */
FT_INLINE void piece_of(const double *x, int64_t *k, double *t) {
    for (int q = 0; q < BLK; q++) {
        const double f = floor(x[q] * NSEG);
        k[q] = f < 0.0 ? 0 : (f > NSEG - 1 ? NSEG - 1 : (int64_t)f);
        t[q] = clip01(x[q] * NSEG - (double)k[q]);
    }
}

FT_INLINE void profile_density(const double *x, const double V[NN][BLK], double *out) {
    double M[NSEG][BLK], LR[NSEG][BLK], tot[BLK], t[BLK], v0[BLK], rate[BLK], g[BLK];
    int64_t k[BLK];
    profile_parts(V, M, tot, LR);
    piece_of(x, k, t);
    piece_rate(V, LR, k, v0, rate);
    FT_SIMD for (int q = 0; q < BLK; q++) g[q] = exp(t[q] * rate[q]);
    for (int q = 0; q < BLK; q++) out[q] = v0[q] * g[q] / tot[q];
}

FT_INLINE void profile_cdf(const double *x, const double V[NN][BLK], double *out) {
    double M[NSEG][BLK], LR[NSEG][BLK], tot[BLK], t[BLK], v0[BLK], rate[BLK], e[BLK], c[BLK];
    int64_t k[BLK];
    profile_parts(V, M, tot, LR);
    piece_of(x, k, t);
    piece_rate(V, LR, k, v0, rate);
    rate_e(rate, e);
    exp_cdf(t, rate, e, c);
    for (int q = 0; q < BLK; q++) {
        const double start = k[q] == 0 ? 0.0 : (k[q] == 1 ? M[0][q] : M[0][q] + M[1][q]);
        out[q] = (start + M[k[q]][q] * c[q]) / tot[q];
    }
}

/* ------------------------------------------------------------------------ bins, views */

/* One sample's interpolation: w[0] bin b0 + w[1] bin b1 (+ w[2] b2 + w[3] b3 when n == 4,
 * anisotropic), Tables._lerp's order. Offsets of bin b0 in the row arrays (a, row_cdf), the
 * row x column+1 arrays (b, col_cum) and the cell arrays; d*[c]: bin c+1's offset minus b0's.
 * In flat mode all offsets are 0 and the weights unused. phi_ref: the "wo" coordinates'
 * reference; halfvector: the map's frame angle, with wi in that frame (wr) and the cosine
 * and sine that turn a direction back (cr, sr). */
typedef struct {
    double w[4], phi_ref, wr[3], cr, sr;
    int64_t n;
    ptrdiff_t ka, kb, kc, da[3], db[3], dc[3];
} ft_bin;

/* The arrays the kernels read: the Tables' (interpolated per sample) or, in flat mode,
 * one wi's interpolated table, with float64 weights. */
typedef struct {
    int64_t R, C, half;                /* half: ft_tables.coords (1, 2: over h) */
    const double *a, *b, *m, *alpha, *beta, *row_cdf, *col_cum;
    const float *w32;                  /* interpolated mode */
    const double *w64;                 /* flat mode (only for eval) */
} ft_view;

/* Tables._bins for one wi, from theta, phi (geometry.theta_phi), cos(theta) (unused when
 * K == 1) and n = np.searchsorted(theta_bins, theta, side="right") */
FT_INLINE void bin_of(const ft_tables *T, double theta, double phi, double cos_theta, int64_t n, ft_bin *B) {
    const int64_t K = T->K, R = T->R, C = T->C, P = T->P;
    int64_t k0 = 0, k1 = 0;
    double t = 0.0;
    if (K != 1) {
        int64_t k = n - 1;      /* np.clip(n - 1, 0, K - 2) */
        if (k < 0) k = 0;
        if (k > K - 2) k = K - 2;
        const double ck = T->cos_bins[k], ck1 = T->cos_bins[k + 1];
        t = clip01((ck - cos_theta) / (ck - ck1));
        k0 = k;
        k1 = k + 1;
    }
    int64_t bin[4] = {k0, k1, 0, 0};
    if (P > 1) {    /* halfvector: phi_i turned back by whole periods into the closed axis */
        const double turns = floor((phi - T->phi0) / T->period);
        const double x = phi - T->phi0 - turns * T->period;
        int64_t p = 0;
        for (int64_t q = 0; q < P; q++) p += T->starts[q] <= x;     /* searchsorted right */
        p -= 1;
        if (p < 0) p = 0;
        if (p > P - 2) p = P - 2;
        const double sp = clip01((x - T->starts[p]) / (T->starts[p + 1] - T->starts[p]));
        B->w[0] = (1.0 - t) * (1.0 - sp);
        B->w[1] = (1.0 - t) * sp;
        B->w[2] = t * (1.0 - sp);
        B->w[3] = t * sp;
        bin[0] = k0 * P + p;
        bin[1] = k0 * P + p + 1;
        bin[2] = k1 * P + p;
        bin[3] = k1 * P + p + 1;
        B->n = 4;
        B->phi_ref = turns * T->period + T->frame;
    } else {
        B->w[0] = 1.0 - t;
        B->w[1] = t;
        B->w[2] = B->w[3] = 0.0;
        B->n = 2;
        B->phi_ref = phi + PI;
    }
    B->ka = bin[0] * (R + 1);
    B->kb = bin[0] * R * (C + 1);
    B->kc = bin[0] * R * C;
    for (int c = 0; c < 3; c++) {
        B->da[c] = (bin[c + 1] - bin[0]) * (R + 1);
        B->db[c] = (bin[c + 1] - bin[0]) * R * (C + 1);
        B->dc[c] = (bin[c + 1] - bin[0]) * R * C;
    }
}

/* The bins of a block of directions w (row stride `stride`), one libm function per loop:
 * the calls of different samples run in vector lanes. */
FT_INLINE void bins(const ft_tables *T, const double *w, int64_t stride, ft_bin *B) {
    double x[BLK], y[BLK], z[BLK], theta[BLK], phi[BLK], c[BLK];
    for (int k = 0; k < BLK; k++) {
        x[k] = w[k * stride];
        y[k] = w[k * stride + 1];
        z[k] = w[k * stride + 2];
    }
    FT_SIMD for (int k = 0; k < BLK; k++) theta[k] = hypot(x[k], y[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) theta[k] = atan2(theta[k], z[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) phi[k] = atan2(y[k], x[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) c[k] = cos(theta[k]);
    /* searchsorted(side="right") as a count of the (increasing) bins at or below theta: in
     * vector lanes, where a scan per sample would mispredict its exit on every new wi. numpy
     * sorts NaN last, so a NaN theta lands past every bin. */
    double n[BLK] = {0};      /* whole numbers: double lanes vectorize on every x86 */
    for (int64_t q = 0; q < T->K; q++)
        for (int k = 0; k < BLK; k++) n[k] += T->theta_bins[q] <= theta[k] ? 1.0 : 0.0;
    for (int k = 0; k < BLK; k++) bin_of(T, theta[k], phi[k], c[k], isnan(theta[k]) ? T->K : (int64_t)n[k], &B[k]);
    if (T->coords) {     /* h's coordinates: wi in the map's frame (warps.rotate_z by -phi_ref) */
        double cr[BLK], sr[BLK];
        FT_SIMD for (int k = 0; k < BLK; k++) cr[k] = cos(B[k].phi_ref);
        FT_SIMD for (int k = 0; k < BLK; k++) sr[k] = sin(B[k].phi_ref);
        for (int k = 0; k < BLK; k++) {
            B[k].cr = cr[k];
            B[k].sr = sr[k];
            B[k].wr[0] = cr[k] * x[k] - (-sr[k]) * y[k];
            B[k].wr[1] = (-sr[k]) * x[k] + cr[k] * y[k];
            B[k].wr[2] = z[k];
        }
    }
}

/* Tables._lerp of one element: x[off] of bin b0 blended with x[off + d[c]] of the others. */
FT_INLINE double lerp(const double *x, ptrdiff_t off, const ptrdiff_t *d, const ft_bin *B) {
    double v = B->w[0] * x[off] + B->w[1] * x[off + d[0]];
    if (B->n == 4) v = (v + B->w[2] * x[off + d[1]]) + B->w[3] * x[off + d[2]];
    return v;
}

FT_INLINE double lerp32(const float *x, ptrdiff_t off, const ptrdiff_t *d, const ft_bin *B) {
    double v = B->w[0] * (double)x[off] + B->w[1] * (double)x[off + d[0]];
    if (B->n == 4) v = (v + B->w[2] * (double)x[off + d[1]]) + B->w[3] * (double)x[off + d[2]];
    return v;
}

/* Tables._lerp of one element (lerp); in flat mode the (already interpolated) x[off]. */
#define AT(x, off, d, Bk) (flat ? (x)[off] : lerp((x), (off), (d), &(Bk)))

/* The flat view of one wi (bin B) into buf; returns 0 when out of memory. */
FT_INLINE int flatten(const ft_tables *T, const ft_bin *B, int with_weights, ft_view *V, double **buf) {
    const int64_t R = T->R, C = T->C, rows = R + 1, edges = R * (C + 1), cells = R * C;
    double *p = malloc(sizeof(double) * (size_t)(2 * rows + 2 * edges + (1 + 2 * NN + (with_weights ? 3 : 0)) * cells));
    if (!p) return 0;
    *buf = p;
    double *a = p, *row_cdf = a + rows, *b = row_cdf + rows, *col_cum = b + edges, *m = col_cum + edges;
    double *alpha = m + cells, *beta = alpha + NN * cells, *w = beta + NN * cells;
    for (int64_t i = 0; i < rows; i++) {
        a[i] = lerp(T->a, B->ka + i, B->da, B);
        row_cdf[i] = lerp(T->row_cdf, B->ka + i, B->da, B);
    }
    for (int64_t i = 0; i < edges; i++) {
        b[i] = lerp(T->b, B->kb + i, B->db, B);
        col_cum[i] = lerp(T->col_cum, B->kb + i, B->db, B);
    }
    const ptrdiff_t dn[3] = {NN * B->dc[0], NN * B->dc[1], NN * B->dc[2]};
    for (int64_t i = 0; i < cells; i++) m[i] = lerp(T->m, B->kc + i, B->dc, B);
    for (int64_t i = 0; i < NN * cells; i++) {
        alpha[i] = lerp(T->alpha, NN * B->kc + i, dn, B);
        beta[i] = lerp(T->beta, NN * B->kc + i, dn, B);
    }
    if (with_weights) {
        const ptrdiff_t d3[3] = {3 * B->dc[0], 3 * B->dc[1], 3 * B->dc[2]};
        for (int64_t i = 0; i < 3 * cells; i++)
            w[i] = lerp32(T->weights, 3 * B->kc + i, d3, B);
    }
    *V = (ft_view){R, C, T->coords, a, b, m, alpha, beta, row_cdf, col_cum, NULL, with_weights ? w : NULL};
    return 1;
}

/* ------------------------------------------------------------------------ kernels */

/* _search for nb samples in lockstep: per sample, the i in [0, n) with
 * edge(i) <= value < edge(i + 1), i.e. the largest i in [0, n) with edge(i) <= value, or 0.
 * Sample k's edges are x[off[k] + i] (interpolated with x[off[k] + d[k] + i]).
 * Interpolated edges and cumulative masses never decrease (a sum of two non-decreasing
 * roundings), so those i form a prefix and any bisection finds numpy's i. Branch-free: a
 * conditional move per halving (a mispredicted branch would cost more than the rest). */
FT_INLINE void search_block(const double *value, int64_t n, const double *x, const ptrdiff_t *off,
                            const ptrdiff_t *const *d, const ft_bin *B, int64_t *lo, const int flat) {
    for (int k = 0; k < BLK; k++) lo[k] = 0;
    int64_t len = n;
    while (len > 1) {
        const int64_t half = len / 2;
        for (int k = 0; k < BLK; k++) {
            const int64_t mid = lo[k] + half;
            const double e = AT(x, off[k] + mid, d[k], B[k]);
            lo[k] = (e <= value[k]) ? mid : lo[k];
        }
        len -= half;
    }
}

typedef struct {
    double a0, a1, b0, b1, m, pa[NN], pb[NN];
} ft_cell;

/* Tables._cell: edges, mass and the blended profiles' node values */
FT_INLINE void cell(const ft_view *V, const ft_bin *B, int64_t i, int64_t j, ft_cell *c, const int flat) {
    const ptrdiff_t ia = B->ka + i, ib = B->kb + i * (V->C + 1) + j, ic = B->kc + i * V->C + j;
    const ptrdiff_t dn[3] = {NN * B->dc[0], NN * B->dc[1], NN * B->dc[2]};
    c->a0 = AT(V->a, ia, B->da, *B);
    c->a1 = AT(V->a, ia + 1, B->da, *B);
    c->b0 = AT(V->b, ib, B->db, *B);
    c->b1 = AT(V->b, ib + 1, B->db, *B);
    c->m = AT(V->m, ic, B->dc, *B);
    for (int n = 0; n < NN; n++) {
        c->pa[n] = AT(V->alpha, NN * ic + n, dn, *B);
        c->pb[n] = AT(V->beta, NN * ic + n, dn, *B);
    }
}

/* Per-lane cell data in arrays (SoA): what the vector loops read */
typedef struct {
    double a0[BLK], a1[BLK], b0[BLK], b1[BLK], m[BLK], pa[NN][BLK], pb[NN][BLK];
} ft_cells;

FT_INLINE void cells_of(const ft_view *V, const ft_bin *B, const int64_t *I, const int64_t *J, ft_cells *S,
                        const int flat) {
    ft_cell c[BLK];
    for (int k = 0; k < BLK; k++) cell(V, &B[k], I[k], J[k], &c[k], flat);
    for (int k = 0; k < BLK; k++) {
        S->a0[k] = c[k].a0; S->a1[k] = c[k].a1; S->b0[k] = c[k].b0; S->b1[k] = c[k].b1; S->m[k] = c[k].m;
        for (int n = 0; n < NN; n++) {
            S->pa[n][k] = c[k].pa[n];
            S->pb[n][k] = c[k].pb[n];
        }
    }
}

/* the cell's density from its profiles' densities at the sampled place */
FT_INLINE void sampled_density(const ft_cells *S, const double *DX, const double *DY, double *P) {
    for (int k = 0; k < BLK; k++)
        P[k] = S->m[k] * DX[k] * DY[k] / ((S->a1[k] - S->a0[k]) * (S->b1[k] - S->b0[k]));
}

/* the cell's density at in-cell (X, Y) */
FT_INLINE void density_block(const ft_cells *S, const double *X, const double *Y, double *P) {
    double dx[BLK], dy[BLK];
    profile_density(X, S->pa, dx);
    profile_density(Y, S->pb, dy);
    for (int k = 0; k < BLK; k++)
        P[k] = S->m[k] * dx[k] * dy[k] / ((S->a1[k] - S->a0[k]) * (S->b1[k] - S->b0[k]));
}

/* halfvector.py _cap for a block: 1 - cos theta_max at azimuths phi_h of h, wi per lane */
FT_INLINE void half_cap(const ft_bin *B, const double *phi_h, double *cap) {
    double c[BLK], s[BLK], t[BLK];
    FT_SIMD for (int k = 0; k < BLK; k++) c[k] = cos(phi_h[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) s[k] = sin(phi_h[k]);
    for (int k = 0; k < BLK; k++) t[k] = -(B[k].wr[0] * c[k] + B[k].wr[1] * s[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) t[k] = atan2(B[k].wr[2], t[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) t[k] = sin(0.25 * t[k]);
    for (int k = 0; k < BLK; k++) {
        const double v = 2.0 * (t[k] * t[k]);
        cap[k] = v < TINY ? TINY : v;
    }
}

/* halfvector.polar_from_ab for a block (wi: B[k].wr), then turned back by phi_ref: wo, jac
 * (the isotropic halfpolar tables' map; the concentric one ends in it) */
FT_INLINE void polar_from_ab(const ft_bin *B, const double *a, const double *b, double *wo, double *jac) {
    double cap[BLK], c[BLK], sn[BLK], sh[BLK];
    half_cap(B, b, cap);
    FT_SIMD for (int k = 0; k < BLK; k++) c[k] = cos(b[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) sn[k] = sin(b[k]);
    for (int k = 0; k < BLK; k++) {
        const double omc = a[k] * cap[k];
        const double q = omc * (2.0 - omc);
        sh[k] = q < 0.0 ? 0.0 : q;
    }
    FT_SIMD for (int k = 0; k < BLK; k++) sh[k] = sqrt(sh[k]);
    for (int k = 0; k < BLK; k++) {
        const double h0 = sh[k] * c[k], h1 = sh[k] * sn[k], h2 = 1.0 - a[k] * cap[k];
        const double *w = B[k].wr;
        const double d = (w[0] * h0 + w[1] * h1) + w[2] * h2;
        const double x = 2.0 * d * h0 - w[0], y = 2.0 * d * h1 - w[1], z = 2.0 * d * h2 - w[2];
        wo[3 * k] = B[k].cr * x - B[k].sr * y;
        wo[3 * k + 1] = B[k].sr * x + B[k].cr * y;
        wo[3 * k + 2] = z < 0.0 ? 0.0 : z;
        jac[k] = 4.0 * d * cap[k];
    }
}

/* halfvector.from_ab for a block (wi: B[k].wr), then warps.rotate_z back by phi_ref: wo (BLK, 3)
 * and jac = d omega_o / (da db) */
FT_INLINE void half_from_ab(const ft_bin *B, const double *a, const double *b, double *wo, double *jac) {
    double r[BLK], ang[BLK], u[BLK], v[BLK], phi[BLK];
    for (int k = 0; k < BLK; k++) {
        const double x = 2.0 * a[k] - 1.0, y = b[k] / PI - 1.0;
        const int wide = fabs(x) >= fabs(y);
        r[k] = wide ? x : y;
        const double safe = r[k] == 0.0 ? 1.0 : r[k];
        ang[k] = wide ? QUARTER * (y / safe) : 2.0 * QUARTER - QUARTER * (x / safe);
    }
    FT_SIMD for (int k = 0; k < BLK; k++) u[k] = cos(ang[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) v[k] = sin(ang[k]);
    for (int k = 0; k < BLK; k++) {
        u[k] = r[k] * u[k];
        v[k] = r[k] * v[k];
    }
    FT_SIMD for (int k = 0; k < BLK; k++) phi[k] = atan2(v[k], u[k]);
    for (int k = 0; k < BLK; k++) r[k] = u[k] * u[k] + v[k] * v[k];     /* the disk point's radius^2 */
    polar_from_ab(B, r, phi, wo, jac);
}

/* h = normalize(wi + wo) for a block of wo, turned by -phi_ref into the map's frame (wi: B[k].wr) */
FT_INLINE void half_of(const ft_bin *B, const double *wo, double h[3][BLK]) {
    double n[BLK];
    for (int k = 0; k < BLK; k++) {
        const double *o = wo + 3 * k, *w = B[k].wr;
        const double ox = B[k].cr * o[0] - (-B[k].sr) * o[1], oy = (-B[k].sr) * o[0] + B[k].cr * o[1];
        h[0][k] = w[0] + ox;
        h[1][k] = w[1] + oy;
        h[2][k] = w[2] + o[2];
        n[k] = (h[0][k] * h[0][k] + h[1][k] * h[1][k]) + h[2][k] * h[2][k];
    }
    FT_SIMD for (int k = 0; k < BLK; k++) n[k] = sqrt(n[k]);
    for (int k = 0; k < BLK; k++)
        for (int i = 0; i < 3; i++) h[i][k] = h[i][k] / n[k];
}

/* halfvector.polar_to_ab for a block of wo (turned by -phi_ref into the map's frame first) */
FT_INLINE void polar_to_ab(const ft_bin *B, const double *wo, double *a, double *b, double *jac) {
    double h[3][BLK], cap[BLK];
    half_of(B, wo, h);
    FT_SIMD for (int k = 0; k < BLK; k++) b[k] = atan2(h[1][k], h[0][k]);
    for (int k = 0; k < BLK; k++) {
        b[k] = isnan(b[k]) ? 0.0 : mod_two_pi(b[k]);      /* np.nan_to_num(np.mod(., 2 pi)) */
    }
    half_cap(B, b, cap);
    for (int k = 0; k < BLK; k++) {
        const double av = clip01((h[0][k] * h[0][k] + h[1][k] * h[1][k]) / (1.0 + h[2][k]) / cap[k]);
        a[k] = isnan(av) ? 0.0 : av;
        const double *w = B[k].wr;
        jac[k] = 4.0 * ((w[0] * h[0][k] + w[1] * h[1][k]) + w[2] * h[2][k]) * cap[k];
    }
}

/* halfvector.to_ab for a block of wo (turned by -phi_ref into the map's frame first): a, b, jac */
FT_INLINE void half_to_ab(const ft_bin *B, const double *wo, double *a, double *b, double *jac) {
    double h[3][BLK], phi[BLK], cap[BLK], rad[BLK], c[BLK], sn[BLK], t[BLK];
    half_of(B, wo, h);
    FT_SIMD for (int k = 0; k < BLK; k++) phi[k] = atan2(h[1][k], h[0][k]);
    half_cap(B, phi, cap);
    for (int k = 0; k < BLK; k++)
        rad[k] = clip01((h[0][k] * h[0][k] + h[1][k] * h[1][k]) / (1.0 + h[2][k]) / cap[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) rad[k] = sqrt(rad[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) c[k] = cos(phi[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) sn[k] = sin(phi[k]);
    for (int k = 0; k < BLK; k++) {
        c[k] = rad[k] * c[k];     /* u */
        sn[k] = rad[k] * sn[k];   /* v */
        const int wide = fabs(c[k]) >= fabs(sn[k]);
        t[k] = wide ? sn[k] / c[k] : c[k] / sn[k];      /* NaN at the centre: numpy's too */
    }
    FT_SIMD for (int k = 0; k < BLK; k++) t[k] = atan(t[k]);
    for (int k = 0; k < BLK; k++) {
        const double u = c[k], v = sn[k];
        const int wide = fabs(u) >= fabs(v);
        const double su = (double)((u > 0.0) - (u < 0.0)), sv = (double)((v > 0.0) - (v < 0.0));
        double x = wide ? su * rad[k] : sv * rad[k] * t[k] / QUARTER;
        double y = wide ? su * rad[k] * t[k] / QUARTER : sv * rad[k];
        x = isnan(x) ? 0.0 : x;     /* np.nan_to_num */
        y = isnan(y) ? 0.0 : y;
        const double av = 0.5 * (x + 1.0), bv = PI * (y + 1.0);
        a[k] = clip01(av);
        b[k] = bv < 0.0 ? 0.0 : (bv > TWO_PI ? TWO_PI : bv);
        const double *w = B[k].wr;
        jac[k] = 4.0 * ((w[0] * h[0][k] + w[1] * h[1][k]) + w[2] * h[2][k]) * cap[k];
    }
}

/* Tables.sample for one block: u (BLK, 2) -> wo (BLK, 3), pdf (BLK) */
FT_INLINE void sample_block(const ft_view *V, const ft_bin *B, const double *u, double *wo, double *pdf,
                            const int flat) {
    const int64_t R = V->R, C = V->C;
    int64_t I[BLK], J[BLK];
    double val[BLK], c0[BLK], c1[BLK];
    ptrdiff_t off[BLK];
    const ptrdiff_t *d[BLK];
    for (int k = 0; k < BLK; k++) {
        val[k] = u[2 * k];
        off[k] = B[k].ka;
        d[k] = B[k].da;
    }
    search_block(val, R, V->row_cdf, off, d, B, I, flat);
    for (int k = 0; k < BLK; k++) {
        c0[k] = AT(V->row_cdf, B[k].ka + I[k], B[k].da, B[k]);
        c1[k] = AT(V->row_cdf, B[k].ka + I[k] + 1, B[k].da, B[k]);
        val[k] = u[2 * k + 1] * (c1[k] - c0[k]);          /* v */
        off[k] = B[k].kb + I[k] * (C + 1);
        d[k] = B[k].db;
    }
    search_block(val, C, V->col_cum, off, d, B, J, flat);
    ft_cells S;
    double X[BLK], Y[BLK], A[BLK], Bv[BLK], sn[BLK], cs[BLK], ss[BLK];
    for (int k = 0; k < BLK; k++) {
        const double d0 = AT(V->col_cum, off[k] + J[k], B[k].db, B[k]);
        X[k] = (u[2 * k] - c0[k]) / (c1[k] - c0[k]);
        Y[k] = val[k] - d0;
    }
    cells_of(V, B, I, J, &S, flat);
    for (int k = 0; k < BLK; k++) {
        X[k] = clip01(X[k]);
        Y[k] = clip01(Y[k] / S.m[k]);
    }
    double DX[BLK], DY[BLK];
    profile_sample(X, S.pa, X, DX);
    profile_sample(Y, S.pb, Y, DY);
    if (V->half) {
        double jac[BLK];
        for (int k = 0; k < BLK; k++) {
            A[k] = S.a0[k] + X[k] * (S.a1[k] - S.a0[k]);
            Bv[k] = S.b0[k] + Y[k] * (S.b1[k] - S.b0[k]);
        }
        if (V->half == 2) polar_from_ab(B, A, Bv, wo, jac);
        else half_from_ab(B, A, Bv, wo, jac);
        sampled_density(&S, DX, DY, pdf);
        for (int k = 0; k < BLK; k++) pdf[k] = pdf[k] / jac[k];
        return;
    }
    for (int k = 0; k < BLK; k++) {
        /* from_ab */
        A[k] = S.a0[k] + X[k] * (S.a1[k] - S.a0[k]);
        Bv[k] = S.b0[k] + Y[k] * (S.b1[k] - S.b0[k]);
        double r2 = A[k] * (2.0 - A[k]);
        sn[k] = r2 < 0.0 ? 0.0 : r2;   /* np.maximum(., 0): NaN stays NaN */
        Bv[k] = Bv[k] - PI + B[k].phi_ref;
    }
    FT_SIMD for (int k = 0; k < BLK; k++) sn[k] = sqrt(sn[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) cs[k] = cos(Bv[k]);
    FT_SIMD for (int k = 0; k < BLK; k++) ss[k] = sin(Bv[k]);
    for (int k = 0; k < BLK; k++) {
        wo[3 * k] = sn[k] * cs[k];
        wo[3 * k + 1] = sn[k] * ss[k];
        wo[3 * k + 2] = 1.0 - A[k];
    }
    sampled_density(&S, DX, DY, pdf);
}

/* Tables._locate for one block of wo: cell (I, J), in-cell X, Y, and the cells */
FT_INLINE void locate_block(const ft_view *V, const ft_bin *B, const double *wo, int64_t *I, int64_t *J,
                            double *X, double *Y, ft_cells *S, double *jac, const int flat) {
    const int64_t R = V->R, C = V->C;
    double A[BLK], Bv[BLK], wx[BLK], wy[BLK];
    ptrdiff_t off[BLK];
    const ptrdiff_t *d[BLK];
    for (int k = 0; k < BLK; k++) {
        wx[k] = wo[3 * k];
        wy[k] = wo[3 * k + 1];
    }
    if (V->half == 2) {
        polar_to_ab(B, wo, A, Bv, jac);
    } else if (V->half) {
        half_to_ab(B, wo, A, Bv, jac);
    } else {
        FT_SIMD for (int k = 0; k < BLK; k++) Bv[k] = atan2(wy[k], wx[k]);
        for (int k = 0; k < BLK; k++) {
            jac[k] = 1.0;
            /* to_ab */
            const double *w = wo + 3 * k;
            const double z = w[2];
            const double a = (w[0] * w[0] + w[1] * w[1]) / (1.0 + (z < 0.0 ? 0.0 : z));
            A[k] = z > 0.0 ? (a > 1.0 ? 1.0 : a) : 1.0;
            Bv[k] = mod_two_pi(Bv[k] - B[k].phi_ref + PI);
        }
    }
    for (int k = 0; k < BLK; k++) {
        off[k] = B[k].ka;
        d[k] = B[k].da;
    }
    search_block(A, R, V->a, off, d, B, I, flat);
    for (int k = 0; k < BLK; k++) {
        off[k] = B[k].kb + I[k] * (C + 1);
        d[k] = B[k].db;
    }
    search_block(Bv, C, V->b, off, d, B, J, flat);
    cells_of(V, B, I, J, S, flat);
    for (int k = 0; k < BLK; k++) {
        X[k] = clip01((A[k] - S->a0[k]) / (S->a1[k] - S->a0[k]));
        Y[k] = clip01((Bv[k] - S->b0[k]) / (S->b1[k] - S->b0[k]));
    }
}

/* Tables.pdf: 0 below the horizon */
FT_INLINE void pdf_block(const ft_view *V, const ft_bin *B, const double *wo, double *pdf, const int flat) {
    int64_t I[BLK], J[BLK];
    double X[BLK], Y[BLK], P[BLK];
    ft_cells S;
    double jac[BLK];
    locate_block(V, B, wo, I, J, X, Y, &S, jac, flat);
    density_block(&S, X, Y, P);
    for (int k = 0; k < BLK; k++) pdf[k] = wo[3 * k + 2] > 0.0 ? P[k] / jac[k] : 0.0;
}

/* Tables.invert: wo -> u (BLK, 2) */
FT_INLINE void invert_block(const ft_view *V, const ft_bin *B, const double *wo, double *u, const int flat) {
    const int64_t C = V->C;
    int64_t I[BLK], J[BLK];
    double X[BLK], Y[BLK], jac[BLK];
    ft_cells S;
    locate_block(V, B, wo, I, J, X, Y, &S, jac, flat);
    profile_cdf(X, S.pa, X);
    profile_cdf(Y, S.pb, Y);
    for (int k = 0; k < BLK; k++) {
        const ptrdiff_t row = B[k].kb + I[k] * (C + 1);
        const double c0 = AT(V->row_cdf, B[k].ka + I[k], B[k].da, B[k]);
        const double c1 = AT(V->row_cdf, B[k].ka + I[k] + 1, B[k].da, B[k]);
        const double d0 = AT(V->col_cum, row + J[k], B[k].db, B[k]);
        const double d1 = AT(V->col_cum, row + J[k] + 1, B[k].db, B[k]);
        u[2 * k] = c0 + X[k] * (c1 - c0);
        u[2 * k + 1] = (d0 + Y[k] * (d1 - d0)) / (c1 - c0);
    }
}

/* Tables.eval: the cell's RGB weight x pdf / cos(theta_o); 0 unless wi and wo are both
 * above the horizon (wi_z: each sample's wi z) */
FT_INLINE void eval_block(const ft_view *V, const ft_bin *B, const double *wo, const double *wi_z,
                          int64_t wi_stride, double *f, const int flat) {
    const int64_t C = V->C;
    int64_t I[BLK], J[BLK];
    double X[BLK], Y[BLK], P[BLK];
    ft_cells S;
    double jac[BLK];
    locate_block(V, B, wo, I, J, X, Y, &S, jac, flat);
    density_block(&S, X, Y, P);
    for (int k = 0; k < BLK; k++) P[k] = P[k] / jac[k];
    for (int k = 0; k < BLK; k++) {
        const double z = wo[3 * k + 2];
        const int above = z > 0.0 && wi_z[k * wi_stride] > 0.0;
        const double scale = P[k] / z;
        const ptrdiff_t ic = B[k].kc + I[k] * C + J[k];
        for (int ch = 0; ch < 3; ch++) {
            const ptrdiff_t d3[3] = {3 * B[k].dc[0], 3 * B[k].dc[1], 3 * B[k].dc[2]};
            const double wc = flat ? V->w64[3 * ic + ch] : lerp32(V->w32, 3 * ic + ch, d3, &B[k]);
            f[3 * k + ch] = above ? wc * scale : 0.0;
        }
    }
}

/* ------------------------------------------------------------------------ entry points */

enum { SAMPLE, PDF, INVERT, EVAL };

/* Flat mode pays for itself from about one sample per cell. */
#define FLAT_MIN_SAMPLES(R, C) ((R) * (C))

FT_INLINE void run_block(int kind, const ft_view *V, const ft_bin *B, const double *wi, int64_t wi_stride,
                         const double *in, double *out, double *out2, const int flat) {
    switch (kind) {
    case SAMPLE: sample_block(V, B, in, out, out2, flat); break;
    case PDF: pdf_block(V, B, in, out, flat); break;
    case INVERT: invert_block(V, B, in, out, flat); break;
    default: eval_block(V, B, in, wi + 2, wi_stride, out, flat); break;
    }
}

/* The n samples of one part (plain tables: the whole): wi (n, 3) with row stride wi_stride (3,
 * or 0: one wi for all), in (n, 2) u or (n, 3) wo, out (and out2: sample's pdf). The last,
 * partial block runs padded with copies of its first sample. */
FT_CLONES static void run_part(int kind, const ft_tables *T, int64_t n, const double *wi, int64_t wi_stride,
                               const double *in, double *out, double *out2) {
    enum { IN = 3, OUT = 3 };
    const int in_w = kind == SAMPLE ? 2 : 3, out_w = kind == SAMPLE ? 3 : (kind == PDF ? 1 : (kind == INVERT ? 2 : 3));
    ft_bin B[BLK];
    ft_view V = {T->R, T->C, T->coords, T->a, T->b, T->m, T->alpha, T->beta, T->row_cdf, T->col_cum, T->weights,
                 NULL};
    double *buf = NULL;
    double pad_wi[3 * BLK], pad_in[IN * BLK], pad_out[OUT * BLK], pad_out2[BLK];
    if (n <= 0) return;
    if (wi_stride == 0) {
        for (int k = 0; k < BLK; k++)
            for (int c = 0; c < 3; c++) pad_wi[3 * k + c] = wi[c];
        bins(T, pad_wi, 3, B);
        if (n >= FLAT_MIN_SAMPLES(T->R, T->C) && flatten(T, &B[0], kind == EVAL, &V, &buf)) {
            B[0].ka = B[0].kb = B[0].kc = 0;
            for (int c = 0; c < 3; c++) B[0].da[c] = B[0].db[c] = B[0].dc[c] = 0;
        }
        for (int k = 1; k < BLK; k++) B[k] = B[0];
    }
    for (int64_t q0 = 0; q0 < n; q0 += BLK) {
        const int nb = n - q0 < BLK ? (int)(n - q0) : BLK;
        const double *w = wi_stride ? wi + q0 * wi_stride : pad_wi, *x = in + in_w * q0;
        int64_t stride = wi_stride ? wi_stride : 3;
        double *o = out + out_w * q0, *o2 = out2 ? out2 + q0 : NULL;
        if (nb < BLK) {
            for (int k = 0; k < BLK; k++) {
                const int src = k < nb ? k : 0;
                for (int c = 0; c < in_w; c++) pad_in[in_w * k + c] = x[in_w * src + c];
                if (wi_stride)
                    for (int c = 0; c < 3; c++) pad_wi[3 * k + c] = w[src * wi_stride + c];
            }
            x = pad_in;
            if (wi_stride) { w = pad_wi; stride = 3; }
            o = pad_out;
            o2 = out2 ? pad_out2 : NULL;
        }
        if (wi_stride != 0)
            bins(T, w, stride, B);
        if (buf) run_block(kind, &V, B, w, wi_stride ? stride : 0, x, o, o2, 1);
        else run_block(kind, &V, B, w, wi_stride ? stride : 0, x, o, o2, 0);
        if (nb < BLK) {
            for (int k = 0; k < nb * out_w; k++) out[out_w * q0 + k] = pad_out[k];
            if (out2)
                for (int k = 0; k < nb; k++) out2[q0 + k] = pad_out2[k];
        }
    }
    free(buf);
}

/* Grouping (a new wi per sample): the samples run in the order of their part (mixed tables) and
 * of their wi's z = cos theta_i in GROUP_KEYS steps (a counting sort: copies of the inputs in that
 * order, the outputs copied back), so the blocks that follow each other read the same incident
 * bins, from cache, where in the callers' order each sample read its bins' rows and cells at
 * random among all the bins' (most of the time with a new wi per sample went into those reads).
 * A sample's arithmetic is the same in any order, so are its bits. The copies cost about what
 * the order saves until there are about GROUP_PER_BIN samples per bin (measured on the shared
 * files, n = 2048 .. 262144: 10 % slower at 30 per bin, even at 250, 10-25 % faster from 1000);
 * with fewer, plain tables run in the callers' order (mixed tables are always grouped by part). */
#define GROUP_KEYS 256
#define GROUP_PER_BIN 1000
#define GROUP_MAX ((int64_t)1 << 18)    /* samples grouped at a time (their copies: 23 MB at most) */

/* Per sample of a block of directions w (row stride `stride`): the part of mixed tables
 * (mixed_tables.MixedTables.part_at: the count of bounds <= theta_i, theta_i as bins() computes it)
 * and the sort key: the part, then z's step. NaN goes to part 0, step 0. */
FT_INLINE void group_keys(const double *w, int64_t stride, int64_t nparts, const double *bounds, int64_t *part,
                          int64_t *key) {
    double x[BLK], y[BLK], z[BLK], theta[BLK];
    for (int k = 0; k < BLK; k++) {
        x[k] = w[k * stride];
        y[k] = w[k * stride + 1];
        z[k] = w[k * stride + 2];
        part[k] = 0;
    }
    if (nparts > 1) {
        FT_SIMD for (int k = 0; k < BLK; k++) theta[k] = hypot(x[k], y[k]);
        FT_SIMD for (int k = 0; k < BLK; k++) theta[k] = atan2(theta[k], z[k]);
        for (int64_t p = 0; p < nparts - 1; p++)
            for (int k = 0; k < BLK; k++) part[k] += bounds[p] <= theta[k];
    }
    for (int k = 0; k < BLK; k++) {
        const double f = z[k] * GROUP_KEYS;
        const int64_t step = f >= 1.0 ? (f < GROUP_KEYS - 1 ? (int64_t)f : GROUP_KEYS - 1) : 0;
        key[k] = part[k] * GROUP_KEYS + step;
    }
}

/* Tables (nparts 1) or MixedTables (nparts parts, bounds[nparts - 1] the parts' first angles
 * after the first part's): the samples, as run_part describes them, grouped (see above).
 * Cloned per instruction set as run_part is: mixed tables' keys need theta_i (hypot, atan2),
 * which ran in 2-lane SSE2 calls before (paper_white, a new wi per sample: 6 % of the time). */
FT_CLONES static void run_grouped(int kind, const ft_tables *parts, int64_t nparts, const double *bounds, int64_t n,
                const double *wi, int64_t wi_stride, const double *in, double *out, double *out2) {
    const int in_w = kind == SAMPLE ? 2 : 3, out_w = kind == SAMPLE ? 3 : (kind == PDF ? 1 : (kind == INVERT ? 2 : 3));
    const int64_t keys = nparts * GROUP_KEYS;
    int64_t part[BLK], key[BLK];
    double block[3 * BLK];
    if (n <= 0) return;
    /* each sample's key (n), each key's first place (keys + 1) and next one (keys), then the
     * samples in key order: wi, in, out, out2 */
    int64_t *of = wi_stride != 0 && (nparts > 1 || n >= GROUP_PER_BIN * parts[0].K * parts[0].P)
                      ? malloc(sizeof(int64_t) * (size_t)(n + 2 * keys + 1 + n * (3 + in_w + out_w + 1)))
                      : NULL;
    if (!of) {
        if (wi_stride == 0 || nparts == 1) {    /* one wi, or few samples of plain tables: one part */
            for (int k = 0; k < 3 * BLK; k++) block[k] = wi[k % 3];
            group_keys(block, 3, nparts, bounds, part, key);
            run_part(kind, &parts[part[0]], n, wi, wi_stride, in, out, out2);    /* nparts 1: part 0 */
            return;
        }
        for (int64_t q = 0; q < n; q++) {        /* mixed tables, out of memory: a sample at a time */
            for (int k = 0; k < 3 * BLK; k++) block[k] = wi[q * wi_stride + k % 3];
            group_keys(block, 3, nparts, bounds, part, key);
            run_part(kind, &parts[part[0]], 1, wi + q * wi_stride, 0, in + in_w * q, out + out_w * q,
                     out2 ? out2 + q : NULL);
        }
        return;
    }
    int64_t *start = of + n, *next = start + keys + 1;
    double *s_wi = (double *)(next + keys), *s_in = s_wi + 3 * n, *s_out = s_in + in_w * n, *s_out2 = s_out + out_w * n;
    for (int64_t k = 0; k <= keys; k++) start[k] = 0;
    for (int64_t q0 = 0; q0 < n; q0 += BLK) {      /* the keys, a block at a time (padded as run_part's) */
        const int nb = n - q0 < BLK ? (int)(n - q0) : BLK;
        for (int k = 0; k < BLK; k++)
            for (int c = 0; c < 3; c++) block[3 * k + c] = wi[(q0 + (k < nb ? k : 0)) * wi_stride + c];
        group_keys(block, 3, nparts, bounds, part, key);
        for (int k = 0; k < nb; k++) {
            of[q0 + k] = key[k];
            start[key[k] + 1]++;
        }
    }
    for (int64_t k = 0; k < keys; k++) start[k + 1] += start[k];
    /* in key order: the inputs read in the callers' order, each key's copies written one after
     * the other (no random reads or writes: streams the caches and prefetchers follow) */
    for (int64_t k = 0; k < keys; k++) next[k] = start[k];
    for (int64_t q = 0; q < n; q++) {
        const int64_t r = next[of[q]]++;
        for (int c = 0; c < 3; c++) s_wi[3 * r + c] = wi[q * wi_stride + c];
        for (int c = 0; c < in_w; c++) s_in[in_w * r + c] = in[in_w * q + c];
    }
    for (int64_t p = 0; p < nparts; p++) {
        const int64_t lo = start[p * GROUP_KEYS], hi = start[(p + 1) * GROUP_KEYS];
        run_part(kind, &parts[p], hi - lo, s_wi + 3 * lo, 3, s_in + in_w * lo, s_out + out_w * lo,
                 out2 ? s_out2 + lo : NULL);
    }
    for (int64_t k = 0; k < keys; k++) next[k] = start[k];      /* and back, alike */
    for (int64_t q = 0; q < n; q++) {
        const int64_t r = next[of[q]]++;
        for (int c = 0; c < out_w; c++) out[out_w * q + c] = s_out[out_w * r + c];
        if (out2) out2[q] = s_out2[r];
    }
    free(of);
}

/* run_grouped over slices of at most GROUP_MAX samples (one wi for all: in one go) */
static void run(int kind, const ft_tables *parts, int64_t nparts, const double *bounds, int64_t n,
                const double *wi, int64_t wi_stride, const double *in, double *out, double *out2) {
    const int in_w = kind == SAMPLE ? 2 : 3, out_w = kind == SAMPLE ? 3 : (kind == PDF ? 1 : (kind == INVERT ? 2 : 3));
    const int64_t slice = wi_stride ? GROUP_MAX : n;
    for (int64_t q = 0; q < n; q += slice)
        run_grouped(kind, parts, nparts, bounds, n - q < slice ? n - q : slice, wi + q * wi_stride, wi_stride,
                    in + in_w * q, out + out_w * q, out2 ? out2 + q : NULL);
}

/* Tables.sample: u (n, 2) -> wo (n, 3), pdf (n) */
FT_EXPORT void ft_sample(const ft_tables *T, int64_t nparts, const double *bounds, int64_t n, const double *wi,
                         int64_t wi_stride, const double *u, double *wo, double *pdf) {
    run(SAMPLE, T, nparts, bounds, n, wi, wi_stride, u, wo, pdf);
}

/* Tables.pdf: wo (n, 3) -> pdf (n) */
FT_EXPORT void ft_pdf(const ft_tables *T, int64_t nparts, const double *bounds, int64_t n, const double *wi,
                      int64_t wi_stride, const double *wo, double *pdf) {
    run(PDF, T, nparts, bounds, n, wi, wi_stride, wo, pdf, NULL);
}

/* Tables.invert: wo (n, 3) -> u (n, 2) */
FT_EXPORT void ft_invert(const ft_tables *T, int64_t nparts, const double *bounds, int64_t n, const double *wi,
                         int64_t wi_stride, const double *wo, double *u) {
    run(INVERT, T, nparts, bounds, n, wi, wi_stride, wo, u, NULL);
}

/* Tables.eval: wo (n, 3) -> f (n, 3) */
FT_EXPORT void ft_eval(const ft_tables *T, int64_t nparts, const double *bounds, int64_t n, const double *wi,
                       int64_t wi_stride, const double *wo, double *f) {
    run(EVAL, T, nparts, bounds, n, wi, wi_stride, wo, f, NULL);
}

/* ---------------------------------------------------------------- RGL measured material
 * bake/materials/rgl.py RGLMaterial._eval_chunk for one wi (the `incident` path: the wi's
 * tables already interpolated across theta_i and phi_i), transcribed formula by formula in
 * numpy's order of operations. The baker evaluates f·cos at tens of millions of nodes per
 * material with one wi per call: this is its hot loop. Results agree with numpy to a few
 * ulps (libm's asin, atan2 and sqrt may round differently from numpy's).
 *
 * par: wix, wiy, wiz (mirrored), sign_x, sign_y, theta_i, phi_i, relative_phi, jacobian, sigma
 * vndf: (vny-1)*(vnx-1) patches x 9; rgb: (ry-1)*(rx-1) patches x 12; ndf: nny x nnx. */
FT_INLINE void rgl_patch(double u, int64_t n, int64_t *i, double *f) {
    double x = fmin(fmax(u, 0.0), 1.0) * (double)(n - 1);
    int64_t k = (int64_t)x;
    if (k > n - 2) k = n - 2;
    *i = k;
    *f = x - (double)k;
}

/* The half vector's RGL coordinates of a block of directions (the libm calls, in vector
 * lanes): um_x = sqrt(theta_m 2 / pi) and phi_m. Lanes past m hold a dummy direction, so every
 * direction goes through a full block (see "Vector math" above). */
FT_INLINE void rgl_angles(const double *wo, int64_t m, const double *par, double *um_x, double *phi_m) {
    const double wix = par[0], wiy = par[1], wiz = par[2], sgx = par[3], sgy = par[4];
    double mx[BLK], my[BLK], t[BLK];
    for (int q = 0; q < BLK; q++) {
        const int in = q < m;
        mx[q] = wix + (in ? wo[3 * q] : 0.0) * sgx;
        my[q] = wiy + (in ? wo[3 * q + 1] : 0.0) * sgy;
        t[q] = wiz + (in ? wo[3 * q + 2] : 1.0);
    }
    FT_SIMD for (int q = 0; q < BLK; q++) {
        const double inv = 1.0 / sqrt(mx[q] * mx[q] + my[q] * my[q] + t[q] * t[q]);
        const double x = mx[q] * inv, y = my[q] * inv, z = t[q] * inv;
        mx[q] = x, my[q] = y;
        t[q] = fmin(0.5 * sqrt(x * x + y * y + (z - 1.0) * (z - 1.0)), 1.0);
    }
    FT_SIMD for (int q = 0; q < BLK; q++) t[q] = asin(t[q]);
    FT_SIMD for (int q = 0; q < BLK; q++) um_x[q] = sqrt(2.0 * t[q] * (2.0 / 3.141592653589793));
    FT_SIMD for (int q = 0; q < BLK; q++) phi_m[q] = atan2(my[q], mx[q]);
}

FT_CLONES static void rgl_run(int64_t n, const double *wo, const double *par, const double *vndf, int64_t vny,
                              int64_t vnx, const double *rgb, int64_t ry, int64_t rx, const double *ndf, int64_t nny,
                              int64_t nnx, double *out) {
    const double phi_i = par[6], sigma = par[9];
    const int relative = par[7] != 0.0, jacobian = par[8] != 0.0;
    const double pi = 3.141592653589793;
    double block_um_x[BLK], block_phi_m[BLK];
    for (int64_t b = 0; b < n; b += BLK) {
        const int64_t m = n - b < BLK ? n - b : BLK;
        rgl_angles(wo + 3 * b, m, par, block_um_x, block_phi_m);
        for (int64_t q = 0; q < m; q++) {
            const int64_t s = b + q;
            double *o = out + 3 * s;
            const double woz = wo[3 * s + 2];
            if (!(woz > 0.0)) {
                o[0] = o[1] = o[2] = 0.0;
                continue;
            }
            const double um_x = block_um_x[q], phi_m = block_phi_m[q];
            double um_y = ((relative ? phi_m - phi_i : phi_m) + pi) * (0.5 / pi);
            um_y -= floor(um_y);

            int64_t px, py;
            double fx, fy;
            rgl_patch(um_x, vnx, &px, &fx);
            rgl_patch(um_y, vny, &py, &fy);
            const double *t = vndf + 9 * (py * (vnx - 1) + px);
            const double gy = 1.0 - fy;
            double row_total = gy * t[6] + fy * t[7];
            const int zero = row_total == 0.0;
            if (zero) row_total = 1.0;
            const double c0 = gy * t[0] + fy * t[2], c1 = gy * t[1] + fy * t[3];
            const double sx = (fx * (c0 + 0.5 * fx * (c1 - c0)) + gy * t[4] + fy * t[5]) / row_total;
            const double sy = fy * (t[6] + 0.5 * fy * (t[7] - t[6])) + t[8];

            int64_t qx, qy;
            double hx, hy;
            rgl_patch(sx, rx, &qx, &hx);
            rgl_patch(sy, ry, &qy, &hy);
            const double *g = rgb + 12 * (qy * (rx - 1) + qx);
            const double ex = 1.0 - hx, ey = 1.0 - hy;
            const double w[4] = {ex * ey, hx * ey, ex * hy, hx * hy};

            double scale = 1.0 / woz;
            if (jacobian) {
                int64_t nx_, ny_;
                double ax, ay;
                rgl_patch(um_x, nnx, &nx_, &ax);
                rgl_patch(um_y, nny, &ny_, &ay);
                const int64_t i = ny_ * nnx + nx_;
                const double bx = 1.0 - ax;
                const double d = (1.0 - ay) * (bx * ndf[i] + ax * ndf[i + 1]) + ay * (bx * ndf[i + nnx] + ax * ndf[i + nnx + 1]);
                scale *= d / (4.0 * sigma);
            }
            if (zero) scale = 0.0;
            for (int c = 0; c < 3; c++)
                o[c] = (w[0] * g[c] + w[1] * g[3 + c] + w[2] * g[6 + c] + w[3] * g[9 + c]) * scale;
        }
    }
}

FT_EXPORT void ft_rgl_eval(int64_t n, const double *wo, const double *par, const double *vndf, int64_t vny,
                           int64_t vnx, const double *rgb, int64_t ry, int64_t rx, const double *ndf, int64_t nny,
                           int64_t nnx, double *out) {
    rgl_run(n, wo, par, vndf, vny, vnx, rgb, ry, rx, ndf, nny, nnx, out);
}

/* ------------------------------------------------------------------- an RGL file's coordinates
 *
 * rgl.WarpedCoords.to_s / from_s, transcribed (same formulas and order of operations, to a few
 * ulps): the file's continuous Marginal2D warp over the half vector's u_m at each sample's wi (its
 * two theta_i slices' patches blended as they are read), with s_x over its horizon value when
 * `horizon`. The searches in from_s are bisections over monotone values, which find the same
 * index as numpy's. carried.CarriedTables calls them through WarpedCoords (the bins' tables
 * through ft_sample and ft_pdf). */
typedef struct {
    int64_t ny, nx, S, horizon;
    const double *theta_i;     /* (S) the slices' incident angles */
    const double *tables;      /* (S, ny-1, nx-1, 9): _continuous_warp_table per slice */
} ft_warp;

typedef struct {               /* one sample's incident direction and its two slices */
    double wx, wy, wz, phi_i, w0, w1;
    const double *t0, *t1;
} ft_wi;

FT_INLINE double theta2u(double theta) { return sqrt(theta * (2.0 / PI)); }

FT_INLINE void warp_incident(const ft_warp *W, const double *wi, ft_wi *I) {
    I->wx = wi[0], I->wy = wi[1], I->wz = wi[2];
    const double dist = sqrt(wi[0] * wi[0] + wi[1] * wi[1] + (wi[2] - 1.0) * (wi[2] - 1.0));
    const double theta = 2.0 * asin(fmin(0.5 * dist, 1.0));
    I->phi_i = atan2(wi[1], wi[0]);
    int64_t i = 0;
    double w1 = 0.0;
    if (W->S > 1) {            /* rgl._param_weights: Mitsuba's find_interval, linear in the angle */
        for (int64_t k = 1; k < W->S - 1; k++) i += theta > W->theta_i[k];
        const double p0 = W->theta_i[i], p1 = W->theta_i[i + 1];
        w1 = fmin(fmax((theta - p0) / (p1 - p0), 0.0), 1.0);
    }
    const int64_t patches = 9 * (W->ny - 1) * (W->nx - 1);
    I->w0 = 1.0 - w1, I->w1 = w1;
    I->t0 = W->tables + i * patches;
    I->t1 = W->tables + (W->S > 1 ? i + 1 : i) * patches;
}

/* the blended patch (py, px) */
FT_INLINE void warp_patch(const ft_warp *W, const ft_wi *I, int64_t py, int64_t px, double *v) {
    const int64_t at = 9 * (py * (W->nx - 1) + px);
    for (int k = 0; k < 9; k++) v[k] = I->t0[at + k] * I->w0 + I->t1[at + k] * I->w1;
}

/* _warp_to_s within patch v at (fx, fy): s x (over the row total), s y, zero row, density */
FT_INLINE void warp_within(const double *t, double fx, double fy, double *sx, double *sy, int *zero, double *density) {
    const double gy = 1.0 - fy;
    double row_total = gy * t[6] + fy * t[7];
    *zero = row_total == 0.0;
    if (*zero) row_total = 1.0;
    const double c0 = gy * t[0] + fy * t[2], c1 = gy * t[1] + fy * t[3];
    *sx = (fx * (c0 + 0.5 * fx * (c1 - c0)) + gy * t[4] + fy * t[5]) / row_total;
    *sy = fy * (t[6] + 0.5 * fy * (t[7] - t[6])) + t[8];
    *density = (1.0 - fx) * c0 + fx * c1;
}

/* WarpedCoords._rim: s x at the horizon in row (py, fy), 1 without `horizon` */
FT_INLINE double warp_rim(const ft_warp *W, const ft_wi *I, int64_t py, double fy) {
    if (!W->horizon) return 1.0;
    const double cos_i = I->wz, sin_i = sqrt(fmax(1.0 - cos_i * cos_i, 0.0));
    const double delta = (((double)py + fy) / (double)(W->ny - 1)) * TWO_PI - PI;
    const double theta_h = 0.5 * atan2(cos_i, -sin_i * cos(delta));
    int64_t px;
    double fx, sx, sy, density, v[9];
    int zero;
    rgl_patch(theta2u(theta_h), W->nx, &px, &fx);
    warp_patch(W, I, py, px, v);
    warp_within(v, fx, fy, &sx, &sy, &zero, &density);
    return sx < 1e-300 ? 1e-300 : (sx > 1.0 ? 1.0 : sx);
}

/* WarpedCoords._jac: d omega_o / d s at half vector h (u_m x = u_x), the warp's density there */
FT_INLINE double warp_jac(const ft_warp *W, const ft_wi *I, double u_x, const double *h, double density) {
    const double theta_h = u_x * u_x * (0.5 * PI);
    const double cos_ih = fabs(h[0] * I->wx + h[1] * I->wy + h[2] * I->wz);
    const double d_omega_d_u = 4.0 * cos_ih * sin(theta_h) * (PI * u_x) * TWO_PI;
    return density > 0.0 ? d_omega_d_u / (density * (double)(W->nx - 1) * (double)(W->ny - 1)) : INFINITY;
}

/* WarpedCoords._root: x in [0, 1] with start x + slope_half x² = d */
FT_INLINE double warp_root(double slope_half, double start, double d) {
    const double root = sqrt(fmax(start * start + 4.0 * slope_half * d, 0.0));
    const double x = 2.0 * d / (start + root);
    return isnan(x) ? 0.0 : clip01(x);
}

FT_EXPORT void ft_warp_to_s(const ft_warp *W, int64_t n, const double *wi, int64_t wi_stride, const double *wo,
                            double *s, double *jac) {
    for (int64_t k = 0; k < n; k++) {
        ft_wi I;
        warp_incident(W, wi + k * wi_stride, &I);
        double h[3] = {I.wx + wo[3 * k], I.wy + wo[3 * k + 1], I.wz + wo[3 * k + 2]};
        const double norm = sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2]);
        h[0] /= norm, h[1] /= norm, h[2] /= norm;
        const double dist = sqrt(h[0] * h[0] + h[1] * h[1] + (h[2] - 1.0) * (h[2] - 1.0));
        const double u_x = theta2u(2.0 * asin(fmin(0.5 * dist, 1.0)));
        double u_y = (atan2(h[1], h[0]) - I.phi_i + PI) * (0.5 / PI);
        u_y -= floor(u_y);
        int64_t px, py;
        double fx, fy, sx, sy, density, v[9];
        int zero;
        rgl_patch(u_x, W->nx, &px, &fx);
        rgl_patch(u_y, W->ny, &py, &fy);
        warp_patch(W, &I, py, px, v);
        warp_within(v, fx, fy, &sx, &sy, &zero, &density);
        const double rim = warp_rim(W, &I, py, fy);
        s[2 * k] = fmin(sx / rim, 1.0);
        s[2 * k + 1] = sy;
        jac[k] = warp_jac(W, &I, u_x, h, zero ? 0.0 : density) * rim;
    }
}

FT_EXPORT void ft_warp_from_s(const ft_warp *W, int64_t n, const double *wi, int64_t wi_stride, const double *s,
                              double *wo, double *jac) {
    const int64_t ny = W->ny, nx = W->nx;
    for (int64_t k = 0; k < n; k++) {
        ft_wi I;
        warp_incident(W, wi + k * wi_stride, &I);
        const double s_x = s[2 * k], s_y = s[2 * k + 1];
        double r[9], v[9];
        int64_t lo = 0, hi = ny - 1;       /* the last row with m0 <= s_y (0 when none) */
        warp_patch(W, &I, 0, 0, r);
        if (!(r[8] <= s_y)) hi = 0;
        while (hi - lo > 1) {
            const int64_t mid = (lo + hi) / 2;
            warp_patch(W, &I, mid, 0, r);
            if (r[8] <= s_y) lo = mid; else hi = mid;
        }
        const int64_t py = lo;
        warp_patch(W, &I, py, 0, r);
        const double r0 = r[6], r1 = r[7];
        const double fy = warp_root(0.5 * (r1 - r0), r0, s_y - r[8]), gy = 1.0 - fy;
        const double rim = warp_rim(W, &I, py, fy);
        const double target = s_x * rim * (gy * r0 + fy * r1);
        lo = 0, hi = nx - 1;               /* the last patch whose start <= target (0 when none) */
        if (!(gy * r[4] + fy * r[5] <= target)) hi = 0;
        while (hi - lo > 1) {
            const int64_t mid = (lo + hi) / 2;
            warp_patch(W, &I, py, mid, v);
            if (gy * v[4] + fy * v[5] <= target) lo = mid; else hi = mid;
        }
        const int64_t px = lo;
        warp_patch(W, &I, py, px, v);
        const double c0 = gy * v[0] + fy * v[2], c1 = gy * v[1] + fy * v[3];
        const double fx = warp_root(0.5 * (c1 - c0), c0, target - (gy * v[4] + fy * v[5]));
        const double u_x = ((double)px + fx) / (double)(nx - 1), u_y = ((double)py + fy) / (double)(ny - 1);
        const double theta_h = u_x * u_x * (0.5 * PI), phi_h = u_y * TWO_PI - PI + I.phi_i;
        const double h[3] = {sin(theta_h) * cos(phi_h), sin(theta_h) * sin(phi_h), cos(theta_h)};
        const double cos_ih = h[0] * I.wx + h[1] * I.wy + h[2] * I.wz;
        double *o = wo + 3 * k;
        o[0] = 2.0 * cos_ih * h[0] - I.wx;
        o[1] = 2.0 * cos_ih * h[1] - I.wy;
        o[2] = 2.0 * cos_ih * h[2] - I.wz;
        const int reached = cos_ih > 0.0 && o[2] > 0.0;
        if (!reached) o[2] = fmin(o[2], 0.0);
        const double j = warp_jac(W, &I, u_x, h, (1.0 - fx) * c0 + fx * c1) * rim;
        jac[k] = reached && isfinite(j) ? j : 0.0;
    }
}

/* ------------------------------------------------------------------ the baker's polar nodes */

/* np.maximum(x, 0.0) of numpy's scalar loop (x when x >= 0 or NaN). */
FT_INLINE double np_max0(double x) { return (x >= 0.0 || isnan(x)) ? x : 0.0; }

/* halfvector.polar_grid_from_ab after its per-b-node part (cos b, sin b and the cap, which numpy
 * computes): per cell i, a node j (qa of them), b node k (qb), the same products in the same
 * order as the numpy reference, so the same bits (only + - * and sqrt, correctly rounded either
 * way; no fused multiply-add). wi: the incident direction in the frame; (c, s): cos and sin of
 * the frame angle, turning wo back (rotate_z). wo: (cells * qa * qb, 3), jac: cells * qa * qb. */
FT_EXPORT void ft_polar_grid(int64_t cells, int64_t qa, int64_t qb, const double *a, const double *cos_b,
                             const double *sin_b, const double *cap, const double *wi, double c, double s,
                             double *wo, double *jac) {
    for (int64_t i = 0; i < cells; i++)
        for (int64_t j = 0; j < qa; j++) {
            const double aj = a[i * qa + j];
            const int64_t at = (i * qa + j) * qb;
            for (int64_t k = 0; k < qb; k++) {
                const double cb = cos_b[i * qb + k], sb = sin_b[i * qb + k], cp = cap[i * qb + k];
                const double omc = aj * cp;
                const double sin_h = sqrt(np_max0(omc * (2.0 - omc)));
                const double h0 = sin_h * cb, h1 = sin_h * sb, h2 = 1.0 - omc;
                const double cos_ih = wi[0] * h0 + wi[1] * h1 + wi[2] * h2;
                const double twice = 2.0 * cos_ih;
                const double x = twice * h0 - wi[0], y = twice * h1 - wi[1];
                const double z = np_max0(twice * h2 - wi[2]);
                double *o = wo + 3 * (at + k);
                o[0] = c * x - s * y;
                o[1] = s * x + c * y;
                o[2] = z;
                jac[at + k] = 4.0 * cos_ih * cp;
            }
        }
}
