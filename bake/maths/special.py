"""Special functions of the flow's base distributions (numpy only, float64, both tails accurate).

    erfc, ndtr, ndtri, log_normal_pdf          the standard normal: CDF, quantile, log density
    wrap_angle                                 an angle's representative in [-pi, pi)
    log_i0, vm_terms, vm_cdf, vm_icdf, vm_log_pdf
                                               the zero-mean von Mises distribution on the circle
    logsumexp, mix_radial_cdf, mix_radial_icdf the radius of a scale mixture of 2D Gaussians

flow.py samples a model's base through these inverse CDFs; flow_maps.py's spherical map uses
the normal CDF and quantile.
"""
import math

import numpy as np

LOG_2PI = math.log(2.0 * math.pi)
SQRT1_2 = math.sqrt(0.5)

_erfc = np.frompyfunc(math.erfc, 1, 1)


def erfc(x):
    """The complementary error function (libm's, vectorized)."""
    x = np.asarray(x, dtype=np.float64)
    return np.asarray(_erfc(x), dtype=np.float64).reshape(x.shape)


def ndtr(z):
    """Standard normal CDF, accurate in both tails."""
    return 0.5 * erfc(-np.asarray(z, dtype=np.float64) * SQRT1_2)


def log_normal_pdf(z):
    return -0.5 * np.asarray(z) ** 2 - 0.5 * LOG_2PI


# Acklam's rational approximation of the normal quantile (relative error 1.2e-9), refined below.
_A = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
      1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
_B = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
      6.680131188771972e+01, -1.328068155288572e+01)
_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
      -2.549732539343734e+00, 4.374664141464968e+00, 2.938163982698783e+00)
_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00, 3.754408661907416e+00)


def _poly(c, x):
    r = np.zeros_like(x) + c[0]
    for a in c[1:]:
        r = r * x + a
    return r


def _ndtri_lower(p):
    """Normal quantile for p in (0, 0.5] (the lower half, where p has full relative precision)."""
    p = np.asarray(p, dtype=np.float64)
    z = np.empty_like(p)
    tail = p < 0.02425
    q = np.sqrt(-2.0 * np.log(p[tail]))
    z[tail] = _poly(_C, q) / (_poly(_D, q) * q + 1.0)
    q = p[~tail] - 0.5
    r = q * q
    z[~tail] = _poly(_A, r) * q / (_poly(_B, r) * r + 1.0)
    # Two Halley steps on ndtr(z) = p make it the inverse of *this* module's ndtr to rounding.
    for _ in range(2):
        e = ndtr(z) - p
        d = e * np.exp(0.5 * z * z + 0.5 * LOG_2PI)
        z = z - d / (1.0 + 0.5 * z * d)
    return z


def ndtri(p):
    """Standard normal quantile, accurate in both tails (p = 0 -> -inf, p = 1 -> +inf)."""
    p = np.asarray(p, dtype=np.float64)
    out = np.full(p.shape, np.nan)
    lo = (p > 0.0) & (p <= 0.5)
    hi = (p > 0.5) & (p < 1.0)
    out[lo] = _ndtri_lower(p[lo])
    out[hi] = -_ndtri_lower(1.0 - p[hi])
    out[p == 0.0] = -np.inf
    out[p == 1.0] = np.inf
    return out


def wrap_angle(a):
    """The representative of an angle in [-pi, pi)."""
    return np.mod(np.asarray(a, dtype=np.float64) + np.pi, 2.0 * np.pi) - np.pi


def log_i0(kappa):
    """log I0(kappa), kappa >= 0 (np.i0 is exact enough below ~700; the base keeps kappa small)."""
    kappa = np.asarray(kappa, dtype=np.float64)
    big = kappa > 600.0
    k = np.where(big, 600.0, kappa)
    out = np.log(np.i0(k))
    # Asymptotic series for large kappa (never reached with the trainer's kappa_max).
    kb = np.where(big, kappa, 1.0)
    asym = kb - 0.5 * np.log(2.0 * np.pi * kb) + np.log1p(1.0 / (8.0 * kb) + 9.0 / (128.0 * kb * kb))
    return np.where(big, asym, out)


def vm_terms(kappa_max):
    """How many Fourier terms the von Mises CDF needs for kappa <= kappa_max (I_n/I_0 < 1e-18)."""
    return int(math.ceil(math.sqrt(90.0 * max(kappa_max, 1.0)))) + 20


def _bessel_ratios(kappa, m):
    """rho_n = I_n(kappa) / I_0(kappa), n = 1..m, shape (len(kappa), m), by Miller's backward recurrence."""
    kappa = np.asarray(kappa, dtype=np.float64)
    extra = 40
    r = np.zeros_like(kappa)
    ratios = np.empty((m, kappa.size))
    for n in range(m + extra, 0, -1):
        r = kappa / (2.0 * n + kappa * r)          # r_n = I_n / I_{n-1}
        if n <= m:
            ratios[n - 1] = r
    return np.cumprod(ratios, axis=0).T


def vm_cdf(psi, kappa, m):
    """CDF of a zero-mean von Mises at psi in [-pi, pi] (Fourier series, Clenshaw summation)."""
    psi = np.asarray(psi, dtype=np.float64)
    rho = _bessel_ratios(kappa, m)
    return _vm_cdf_rho(psi, rho)


def _vm_cdf_rho(psi, rho):
    m = rho.shape[1]
    c = rho / np.arange(1, m + 1)
    x2 = 2.0 * np.cos(psi)
    b1 = np.zeros_like(psi)
    b2 = np.zeros_like(psi)
    for n in range(m - 1, -1, -1):
        b1, b2 = c[:, n] + x2 * b1 - b2, b1
    return (psi + np.pi) / (2.0 * np.pi) + b1 * np.sin(psi) / np.pi


def vm_log_pdf(psi, kappa):
    kappa = np.asarray(kappa, dtype=np.float64)
    return kappa * np.cos(psi) - LOG_2PI - log_i0(kappa)


def vm_icdf(u, kappa, m, max_iter=100):
    """psi in [-pi, pi) with vm_cdf(psi) = u: safeguarded Newton (bisection fallback)."""
    u = np.asarray(u, dtype=np.float64)
    kappa = np.asarray(kappa, dtype=np.float64)
    rho = _bessel_ratios(kappa, m)
    lo = np.full(u.shape, -np.pi)
    hi = np.full(u.shape, np.pi)
    # Initial guess: uniform for small kappa, the Gaussian limit for large kappa.
    g_uniform = 2.0 * np.pi * u - np.pi
    g_normal = np.clip(ndtri(np.clip(u, 1e-300, 1.0 - 1e-16)) / np.sqrt(np.maximum(kappa, 1e-12)),
                       -np.pi, np.pi)
    psi = np.where(kappa < 2.0, g_uniform, g_normal)
    active = np.arange(u.size)
    log_norm = LOG_2PI + log_i0(kappa)
    for _ in range(max_iter):
        if active.size == 0:
            break
        p = psi[active]
        f = _vm_cdf_rho(p, rho[active]) - u[active]
        below = f < 0
        lo[active] = np.where(below, p, lo[active])
        hi[active] = np.where(below, hi[active], p)
        dens = np.exp(kappa[active] * np.cos(p) - log_norm[active])
        step = f / dens
        new = p - step
        l, h = lo[active], hi[active]
        bad = ~((new > l) & (new < h)) | ~np.isfinite(new)
        new = np.where(bad, 0.5 * (l + h), new)
        hit = np.abs(f) <= 2.5e-16                      # u resolved to its last bit: keep p
        psi[active] = np.where(hit, p, new)
        done = hit | (np.abs(new - p) <= 4e-16 * (1.0 + np.abs(p))) | (h - l <= 4e-16 * (1.0 + np.abs(l)))
        active = active[~done]
    return psi


# --------------------------------------------------------------------------- radial scale mixtures

def logsumexp(a, axis=-1):
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    return np.log(np.sum(np.exp(a - m), axis=axis)) + m[..., 0]


def mix_radial_cdf(q, logw, lam):
    """P(|z|² <= q) = sum_k w_k (1 - exp(-q / (2 v_k))), accurate for small q."""
    return np.sum(np.exp(logw) * -np.expm1(-0.5 * q[:, None] * np.exp(-2.0 * lam)), axis=-1)


def mix_radial_icdf(u1, logw, lam, max_iter=200):
    """q = |z|² with mix_radial_cdf(q) = u1: Newton on the convex, decreasing log tail from q = 0
    (its iterates approach the root from below, never past it)."""
    target = np.log1p(-u1)
    inv_v = np.exp(-2.0 * lam)
    q = np.zeros(len(u1))
    active = np.ones(len(u1), bool)
    for _ in range(max_iter):
        comp = logw[active] - 0.5 * q[active, None] * inv_v[active]
        g = logsumexp(comp)          # log P(|z|² > q) = logsumexp_k(log w_k - q / (2 v_k))
        # d/dq log tail = -sum_k w_k e^{-q/2v_k} / (2 v_k) / tail
        slope = -0.5 * np.sum(np.exp(comp - g[:, None]) * inv_v[active], axis=-1)
        step = (target[active] - g) / slope
        # At u1 ~ 0 the target sits within rounding of log(sum w) = 0: never step below q = 0.
        step = np.maximum(step, -q[active])
        q[active] += step
        done = np.abs(step) <= 1e-15 * np.maximum(q[active], 1e-300) + 1e-300
        idx = np.flatnonzero(active)
        active[idx[done]] = False
        if not active.any():
            break
    return q
