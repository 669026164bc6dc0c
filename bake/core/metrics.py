"""Yardsticks for any sampler with `sample(wi, u) -> (wo, pdf)` and `pdf(wi, wo)`.

- `relative_variance`: rv = Var[w] / E[w]², w = lum(f·cos)/pdf of the one-sample albedo
  estimator (the chi-square divergence of the sampler from the ideal f·cos; 0 is perfect).
  Samples the sampler loses (pdf 0 or below the horizon) count as w = 0.
  `relative_variance_ref` estimates the same rv as an integral sampled from a reference (the
  ideal sampler), which does not understate heavy tails.
- `chi2_test`: goodness of fit of sample() against pdf(), binned on the half vector
  (`HalfVectorBins`, bake/maths/warps.py's map: fine near the specular direction; the default) or on
  (cos theta, phi) (`CosineBins`), with
  expected counts integrated adaptively (a quadtree refined where the quadrature error
  estimate is large or where samples crowd, so sharp lobes are integrated, not missed),
  low-count bins pooled, and a Šidák-corrected significance level.
"""
import math

import numpy as np

from ..maths.geometry import atan2, luminance, normalize, reflect
from ..maths.warps import dwo_du, half_vector, u_of_half_vector



def sample_weights(material, sampler, wi, n, seed=0):
    rng = np.random.default_rng(seed)
    wi = np.asarray(wi, float)
    wo, pdf = sampler.sample(wi, rng.random((n, 2)))
    ok = (pdf > 0) & (wo[:, 2] > 0) & np.isfinite(pdf)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(ok, luminance(material.eval(wi, wo)) * np.maximum(wo[:, 2], 0) / pdf, 0.0)
    return w


def relative_variance(material, sampler, wi, n=1 << 17, seed=0):
    """(rv, albedo estimate) of the one-sample estimator of lum(albedo) at wi."""
    w = sample_weights(material, sampler, wi, n, seed)
    mean = w.mean()
    if mean == 0.0:
        return math.inf, 0.0
    return float(w.var() / mean ** 2), float(mean)


def relative_variance_ref(material, sampler, wi, reference, k=512, seed=0):
    """(rv, tail share) of `sampler` at wi, rv = integral of g²/q d(omega) / A² - 1 (g = lum(f·cos),
    A its integral, q = sampler.pdf), estimated with wo drawn from `reference` (the ideal sampler:
    pdf close to g / A) on a jittered k x k grid of u.

    The same rv as relative_variance, but the direct estimate draws from q itself, so it sees the
    regions q rarely visits (where g/q is largest) rarely: its finite-sample value understates a
    heavy-tailed rv, and shows a finite number where rv is infinite (e.g. a pdf that vanishes like
    cos at the horizon under measured data whose f·cos does not). Here those regions come at the
    reference's rate. The tail share is the largest single point's share of the integral: ~1/k²
    for a smooth integrand, near 1 when one point decides the value (rv then grows with k).
    """
    return ReferencePoints(material, wi, reference, k, seed).rv(sampler)


class ReferencePoints:
    """relative_variance_ref's draws at one wi (the reference's directions, its pdf h and g there),
    kept to measure several samplers on: the material's evaluation is the costly part."""

    def __init__(self, material, wi, reference, k=512, seed=0):
        rng = np.random.default_rng(seed)
        grid = (np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), axis=-1).reshape(-1, 2)
                + rng.random((k * k, 2))) / k
        self.wi = np.asarray(wi, float)
        wo, h = reference.sample(self.wi, grid)
        ok = (h > 0) & (wo[:, 2] > 0) & np.isfinite(h)
        self.wo, self.h, self.count = wo[ok], h[ok], len(grid)
        self.g = luminance(material.eval(self.wi, self.wo)) * self.wo[:, 2]
        self.albedo = np.sum(self.g / self.h) / self.count

    def rv(self, sampler):
        """(rv, tail share) of `sampler` on these draws."""
        if self.albedo <= 0.0:
            return math.inf, 1.0
        g, h = self.g, self.h
        q = sampler.pdf(self.wi, self.wo)
        if np.any((q <= 0) & (g > 0)):
            return math.inf, 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            terms = np.where(g > 0, g * g / (h * q), 0.0)
        total = np.sum(terms)
        return float(total / self.count / self.albedo ** 2 - 1.0), float(np.max(terms) / total)


# ---------------------------------------------------------------------------- chi-square

def chi2_sf(x, dof):
    """P[X > x] for X ~ chi-square(dof): the regularized upper incomplete gamma Q(dof/2, x/2)."""
    a, x = 0.5 * dof, 0.5 * x
    if x <= 0:
        return 1.0
    log_prefix = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:   # series for P, then Q = 1 - P
        term = total = 1.0 / a
        k = a
        while abs(term) > abs(total) * 1e-15:
            k += 1.0
            term *= x / k
            total += term
        return max(0.0, 1.0 - total * math.exp(log_prefix))
    # continued fraction for Q (modified Lentz)
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 10000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-15:
            break
    return math.exp(log_prefix) * h


def sidak_alpha(alpha, n_tests):
    return 1.0 - (1.0 - alpha) ** (1.0 / n_tests)


# Tensor 3-point Gauss-Legendre on [0,1]²: nodes and weights.
_GL_X = 0.5 + 0.5 * np.array([-math.sqrt(0.6), 0.0, math.sqrt(0.6)])
_GL_W = np.outer([5.0, 8.0, 5.0], [5.0, 8.0, 5.0]).ravel() / 324.0


def _cell_integrals(density, a0, a1, b0, b1):
    """Gauss-Legendre integral of density(a, b) over the cells [a0,a1]x[b0,b1]."""
    da, db = a1 - a0, b1 - b0
    A = np.repeat(a0[:, None] + da[:, None] * _GL_X, 3, axis=1)     # (cells, 9), a index slow
    B = np.tile(b0[:, None] + db[:, None] * _GL_X, (1, 3))
    return (density(A.ravel(), B.ravel()).reshape(-1, 9) @ _GL_W) * da * db


def integrate_bins(density, res, samples=None, tol=1e-7, crowd=64, max_depth=20,
                   max_cells=2_000_000, with_error=False):
    """Integral of density(a, b) over each bin of a res[0] x res[1] grid of the unit square.

    Each bin is a quadtree: a cell is split into four while its children's integral differs
    from its own by more than `tol`, or while it holds more than `crowd` of the given
    samples ((n, 2) points in the square), or any of them while its integral is 0: where
    samples are, mass is, so a peak the quadrature nodes straddle is still found. with_error=True also returns each bin's
    error estimate: the sum of |children - parent| over the cells it accepted.
    """
    na, nb = res
    ai, bi = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
    bins = (ai * nb + bi).ravel()
    a0, a1 = ai.ravel() / na, (ai.ravel() + 1) / na
    b0, b1 = bi.ravel() / nb, (bi.ravel() + 1) / nb
    track = samples is not None
    if track:
        sa, sb = samples[:, 0], samples[:, 1]
        s_cell = np.clip((sa * na).astype(int), 0, na - 1) * nb + np.clip((sb * nb).astype(int), 0, nb - 1)
    out = np.zeros(na * nb)
    err = np.zeros(na * nb)
    whole = _cell_integrals(density, a0, a1, b0, b1)
    depth = evaluated = 0
    while len(bins):
        n = len(bins)
        am, bm = 0.5 * (a0 + a1), 0.5 * (b0 + b1)
        # Children in quadrant order q = 2 * (a >= am) + (b >= bm).
        ca0, ca1 = np.concatenate([a0, a0, am, am]), np.concatenate([am, am, a1, a1])
        cb0, cb1 = np.concatenate([b0, bm, b0, bm]), np.concatenate([bm, b1, bm, b1])
        kids = _cell_integrals(density, ca0, ca1, cb0, cb1)
        kid_sum = kids.reshape(4, n).sum(axis=0)
        refine = np.abs(kid_sum - whole) > tol
        if track:
            count = np.bincount(s_cell, minlength=n)
            # a crowd, or samples where the nodes saw nothing (a sliver: e.g. the horizon
            # cutting through a half-vector bin), or more samples than the nodes' integral can
            # explain (a narrow cell of mass between the nodes: tables at a hard edge; the
            # density integrates to about 1, so a cell expects kid_sum * len(samples))
            expect = np.maximum(kid_sum, 0.0) * len(samples)
            refine |= ((count > crowd) | ((count > 0) & (kid_sum <= 0))
                       | (count > expect + 4.0 * np.sqrt(expect) + 4.0))
        depth += 1
        evaluated += 4 * n
        if depth >= max_depth or evaluated > max_cells:
            refine[:] = False
        np.add.at(out, bins[~refine], kid_sum[~refine])
        np.add.at(err, bins[~refine], np.abs(kid_sum - whole)[~refine])
        keep = np.flatnonzero(refine)
        k = len(keep)
        if track:
            new_id = np.full(n, -1)
            new_id[keep] = np.arange(k)
            sel = new_id[s_cell] >= 0
            sa, sb, sc = sa[sel], sb[sel], s_cell[sel]
            s_cell = (2 * (sa >= am[sc]) + (sb >= bm[sc])) * k + new_id[sc]
        idx = np.concatenate([keep, keep + n, keep + 2 * n, keep + 3 * n])
        bins = np.tile(bins[keep], 4)
        a0, a1, b0, b1, whole = ca0[idx], ca1[idx], cb0[idx], cb1[idx], kids[idx]
    if with_error:
        return out.reshape(na, nb), err.reshape(na, nb)
    return out.reshape(na, nb)


class CosineBins:
    """Bins on (cos theta_o, phi_o): a = cos theta, b = (phi + pi) / 2 pi; d omega = 2 pi da db."""

    def __init__(self, wi):
        pass

    def to_dir(self, a, b):
        s = np.sqrt(np.maximum(0.0, 1.0 - a * a))
        phi = 2 * np.pi * b - np.pi
        return np.stack([s * np.cos(phi), s * np.sin(phi), a], axis=-1), np.full(a.shape, 2 * np.pi)

    def from_dir(self, wo):
        b = (atan2(wo[:, 1], wo[:, 0]) + np.pi) / (2 * np.pi)
        return np.stack([wo[:, 2], b - np.floor(b)], axis=-1)


class HalfVectorBins:
    """Bins on the half vector m = normalize(wi + wo) in the sqrt-theta unit square: fine near
    the specular direction, so the test has power on sharp lobes."""

    def __init__(self, wi):
        self.wi = np.asarray(wi, float).reshape(1, 3)

    def to_dir(self, a, b):
        u = np.stack([a, b], axis=-1)
        m = half_vector(u)
        wo = reflect(self.wi, m)
        jac = np.where(wo[:, 2] > 0, dwo_du(self.wi, m, a), 0.0)
        return wo, jac

    def from_dir(self, wo):
        return u_of_half_vector(normalize(self.wi + wo))


BINNINGS = {"cosine": CosineBins, "halfvector": HalfVectorBins}


class Chi2Result:
    def __init__(self, passed, p_value, statistic, dof, threshold, observed, expected, note=""):
        self.passed, self.p_value, self.statistic, self.dof = passed, p_value, statistic, dof
        self.threshold, self.observed, self.expected, self.note = threshold, observed, expected, note

    def __repr__(self):
        verdict = "pass" if self.passed else "FAIL"
        return (f"<chi2 {verdict}: p={self.p_value:.3g} (threshold {self.threshold:.3g}), "
                f"stat={self.statistic:.1f}, dof={self.dof}{', ' + self.note if self.note else ''}>")


def chi2_test(sampler, wi, n=1_000_000, res=(32, 32), binning="halfvector", seed=0, alpha=0.01,
              n_tests=1, min_expected=5.0, crowd=64, quad_tol=0.01):
    """Goodness of fit of sampler.sample(wi, .) against sampler.pdf(wi, .).

    Samples the sampler loses (pdf 0, or below the horizon) form one more bin whose
    expected count is n times the mass pdf() does not account for; a sampler whose pdf is
    normalized by construction (attribute `normalized`, e.g. Tables) must lose none.

    The expected counts come from adaptive quadrature, which on a pdf with jumps (tables
    of hard-edged materials) is off by up to ~1e-4 of the total: at 1e6 samples that alone
    would fail a correct sampler (quad_tol, in samples per cell, and crowd are integrate_bins'
    tol x n and crowd). So each bin's variance is its expected count plus the
    square of its quadrature error estimate (times 4n); the lost bin's is the total's. For
    smooth pdfs the error terms are ~1e-7 per bin and change nothing.
    """
    wi = np.asarray(wi, float)
    rng = np.random.default_rng(seed)
    wo, pdf = sampler.sample(wi, rng.random((n, 2)))
    if not np.all(np.isfinite(pdf)) or np.any(pdf < 0) or not np.all(np.isfinite(wo)):
        return Chi2Result(False, 0.0, math.inf, 0, 0.0, None, None, "NaN/inf/negative in sample()")
    valid = (pdf > 0) & (wo[:, 2] > 0)
    bins = BINNINGS[binning](wi)
    ab = np.clip(bins.from_dir(wo[valid]), 0.0, 1.0 - 1e-16)
    observed = np.histogram2d(ab[:, 0], ab[:, 1], bins=res, range=[[0, 1], [0, 1]])[0]

    def density(a, b):
        w, jac = bins.to_dir(a, b)
        return np.where(jac > 0, sampler.pdf(wi, w) * jac, 0.0)

    expected, quad_err = integrate_bins(density, res, ab, tol=quad_tol / n, crowd=crowd, with_error=True)
    # |children - parent| underestimates the error where a jump crosses the cells (measured:
    # 2-4x on the cap and cone cases at 1e6 samples), hence the factor.
    expected, quad_err = n * expected, 4.0 * n * quad_err
    total, total_err = expected.sum(), quad_err.sum()
    if total > n * (1 + 1e-3):
        return Chi2Result(False, 0.0, math.inf, 0, 0.0, observed, expected,
                          f"pdf integrates to {total / n:.4f} > 1")
    lost = n - valid.sum()
    if getattr(sampler, "normalized", False):
        # pdf() integrates to 1 by construction: no sample may be lost, and what the
        # quadrature misses of the total is its own error, not lost mass.
        if lost:
            return Chi2Result(False, 0.0, math.inf, 0, 0.0, observed, expected,
                              f"{lost} samples lost although the sampler's pdf is normalized")
        exp, err = expected.ravel(), quad_err.ravel()
        obs = observed.ravel()
    else:
        obs = np.append(observed.ravel(), lost)
        exp = np.append(expected.ravel(), max(n - total, 0.0))
        err = np.append(quad_err.ravel(), total_err)
    # Pool every bin with a small expected count into one (as Mitsuba and pbrt do).
    small = exp < min_expected
    obs_p = np.append(obs[~small], obs[small].sum())
    exp_p = np.append(exp[~small], exp[small].sum())
    err_p = np.append(err[~small], err[small].sum())
    if exp_p[-1] < min_expected and len(exp_p) > 1:   # the pool itself is small: merge it
        big = np.argmax(exp_p[:-1])
        obs_p[big] += obs_p[-1]
        exp_p[big] += exp_p[-1]
        err_p[big] += err_p[-1]
        obs_p, exp_p, err_p = obs_p[:-1], exp_p[:-1], err_p[:-1]
    if np.any((exp_p <= 0) & (obs_p > 0)):
        return Chi2Result(False, 0.0, math.inf, len(exp_p) - 1, 0.0, observed, expected,
                          "samples where pdf integrates to 0")
    nz = exp_p > 0
    stat = float(np.sum((obs_p[nz] - exp_p[nz]) ** 2 / (exp_p[nz] + err_p[nz] ** 2)))
    dof = int(nz.sum()) - 1
    p = chi2_sf(stat, dof) if dof > 0 else 1.0
    threshold = sidak_alpha(alpha, n_tests)
    return Chi2Result(p >= threshold, p, stat, dof, threshold, observed, expected)
