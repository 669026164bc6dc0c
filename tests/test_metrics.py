import math

import numpy as np
import pytest

from bake.core.baselines import CosineSampler, GGXSampler, UniformSampler, fit_ggx
from bake.maths.geometry import incident
from bake.core.ideal import IdealSampler
from bake.materials import open_material
from bake.core.metrics import (chi2_sf, chi2_test, integrate_bins, relative_variance, relative_variance_ref,
                                  sidak_alpha)

# One Šidák family for every chi-square test in this file.
N_TESTS = 16


def chi2(sampler, wi, **kw):
    return chi2_test(sampler, wi, n=200_000, n_tests=N_TESTS, **kw)


def test_chi2_sf_known_values():
    assert chi2_sf(3.841458820694124, 1) == pytest.approx(0.05, rel=1e-9)
    assert chi2_sf(10.0, 10) == pytest.approx(0.4404932850652124, rel=1e-12)
    for x in (0.1, 3.0, 40.0, 700.0):       # dof 2 is exponential: sf = exp(-x/2)
        assert chi2_sf(x, 2) == pytest.approx(math.exp(-x / 2), rel=1e-12)
    # Large dof, far tail: the Wilson-Hilferty normal approximation is good to ~1%.
    k, x = 1000, 1200.0
    z = ((x / k) ** (1 / 3) - (1 - 2 / (9 * k))) / math.sqrt(2 / (9 * k))
    assert chi2_sf(x, k) == pytest.approx(0.5 * math.erfc(z / math.sqrt(2)), rel=0.02)
    assert chi2_sf(0.0, 5) == 1.0
    assert sidak_alpha(0.01, 1) == pytest.approx(0.01)
    assert sidak_alpha(0.01, 10) == pytest.approx(1 - 0.99 ** 0.1)


def test_adaptive_integration_finds_a_narrow_peak():
    """A normalized Gaussian of width 1e-3 inside one of 8x8 bins: the coarse rule alone
    misses it; the quadtree must recover its mass to 1e-6."""
    c, s = np.array([0.3141, 0.7771]), 1e-3

    def density(a, b):
        return np.exp(-((a - c[0]) ** 2 + (b - c[1]) ** 2) / (2 * s * s)) / (2 * np.pi * s * s)

    bins = integrate_bins(density, (8, 8), tol=1e-9)
    assert bins.sum() == pytest.approx(1.0, abs=1e-6)
    assert bins[2, 6] == pytest.approx(1.0, abs=1e-6)


def test_adaptive_integration_finds_a_sliver_where_samples_are():
    """Mass in a strip of width 1e-4 along one edge (like the horizon cutting through a
    half-vector bin at grazing incidence): every quadrature node misses it, so only the
    samples can point the quadtree there (250 per bin here)."""
    w = 1e-4

    def density(a, b):
        return np.where(a > 1.0 - w, 1.0 / w, 0.0)

    rng = np.random.default_rng(3)
    samples = np.stack([1.0 - w * rng.random(2000), rng.random(2000)], axis=-1)
    assert integrate_bins(density, (8, 8), tol=1e-9).sum() < 0.5       # blind without samples
    bins = integrate_bins(density, (8, 8), samples, tol=1e-9)
    assert bins.sum() == pytest.approx(1.0, abs=0.01)
    np.testing.assert_allclose(bins[7], 1 / 8, rtol=0.05)      # gaps between samples: a few %


def test_adaptive_integration_follows_samples_the_nodes_undercount():
    """A narrow cell of mass between the nodes over a base the nodes do see (tables at a hard
    edge: the cone case's 16x16 tables put 2e-4 of their mass in a bin whose integral came
    out ~0, and a correct sampler failed its chi-square): a bin holding many more samples
    than its integral expects is refined, though fewer than `crowd` of them."""
    lo, w, spike = 0.5003, 2e-4, 0.05

    def density(a, b):
        return (1.0 - spike) + spike * ((a > lo) & (a < lo + w) & (b > lo) & (b < lo + w)) / (w * w)

    rng = np.random.default_rng(4)
    n, k = 1000, 50
    samples = np.concatenate([rng.random((n - k, 2)), lo + w * rng.random((k, 2))])
    blind = integrate_bins(density, (8, 8), samples[:n - k], tol=1e-6, crowd=64)
    assert blind[4, 4] < 1.0 / 64 + 0.2 * spike             # the nodes miss the spike
    found = integrate_bins(density, (8, 8), samples, tol=1e-6, crowd=64)
    # most of it: refinement stops where a few samples are no longer evidence (was 0 before)
    assert (1.0 - spike) / 64 + 0.8 * spike < found[4, 4] < (1.0 - spike) / 64 + 1.01 * spike


@pytest.mark.parametrize("theta", [0, 45, 89])
def test_correct_samplers_pass(theta):
    wi = incident(theta, 0.7)
    for sampler in [UniformSampler(), CosineSampler(), GGXSampler(0.01), GGXSampler(0.005, 0.25),
                    GGXSampler(0.3, diffuse=0.4)]:
        r = chi2(sampler, wi)
        assert r.passed, (sampler, theta, r)


class WrongPdf:
    """Samples one sampler, claims another's pdf."""

    def __init__(self, sampling, claimed):
        self.sampling, self.claimed = sampling, claimed

    def sample(self, wi, u):
        wo, _ = self.sampling.sample(wi, u)
        return wo, self.claimed.pdf(wi, wo)

    def pdf(self, wi, wo):
        return self.claimed.pdf(wi, wo)


@pytest.mark.parametrize("sampling,claimed", [
    (CosineSampler(), UniformSampler()),
    (GGXSampler(0.1), GGXSampler(0.11)),                        # a 10% roughness error
    (GGXSampler(0.01, 0.2), GGXSampler(0.2, 0.01)),               # axes swapped
    (GGXSampler(0.2, diffuse=0.3), GGXSampler(0.2, diffuse=0.35)),  # lobe weights off by 5 points
])
def test_wrong_samplers_are_rejected(sampling, claimed):
    r = chi2(WrongPdf(sampling, claimed), incident(40, 0.3))
    assert not r.passed, r


def test_lost_samples_must_be_accounted_for():
    """A sampler that silently drops 2% of its samples (pdf 0) while its pdf() still
    integrates to 1 is rejected; honest about the loss (pdf scaled by 0.98), it passes."""
    class Dropping:
        def __init__(self, honest):
            self.honest, self.inner = honest, CosineSampler()

        def sample(self, wi, u):
            wo, pdf = self.inner.sample(wi, u)
            return wo, np.where(u[:, 0] < 0.02, 0.0, self.pdf(wi, wo))

        def pdf(self, wi, wo):
            return self.inner.pdf(wi, wo) * (0.98 if self.honest else 1.0)

    # Dropping by u[0] < 0.02 removes the directions nearest the normal: a real distortion,
    # so use uniform random dropping instead to isolate the accounting.
    class RandomDrop(Dropping):
        def sample(self, wi, u):
            wo, pdf = self.inner.sample(wi, u)
            drop = (np.floor(u[:, 1] * 1e6) % 50) == 0
            return wo, np.where(drop, 0.0, self.pdf(wi, wo))

    assert not chi2(RandomDrop(False), incident(20)).passed
    assert chi2(RandomDrop(True), incident(20)).passed


def test_ideal_sampler_passes_on_a_sharp_lobe():
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.005})
    ideal = IdealSampler(mat)
    for theta in (0, 75, 89):
        r = chi2(ideal, incident(theta))
        assert r.passed and r.dof > 50, (theta, r)


def test_relative_variance_of_exact_sampling_is_zero():
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.5})
    rv, albedo = relative_variance(mat, CosineSampler(), incident(30), n=10000)
    assert rv == pytest.approx(0.0, abs=1e-20) and albedo == pytest.approx(0.5)
    rv_uniform, _ = relative_variance(mat, UniformSampler(), incident(30), n=200_000)
    assert rv_uniform == pytest.approx(1 / 3, rel=0.02)     # Var[2 cos] / E[2 cos]² = 4/3 - 1


def test_relative_variance_ref_agrees_with_the_direct_estimate():
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.5})
    rv, tail = relative_variance_ref(mat, UniformSampler(), incident(30), CosineSampler(), k=256)
    assert rv == pytest.approx(1 / 3, rel=1e-3) and tail < 1e-4
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.3})
    ideal = IdealSampler(mat, resolution=128)
    for theta in (0, 60):
        direct = relative_variance(mat, CosineSampler(), incident(theta), n=400_000, seed=1)[0]
        ref = relative_variance_ref(mat, CosineSampler(), incident(theta), ideal, k=256)[0]
        assert ref == pytest.approx(direct, rel=0.05), theta


class _FlatTarget:
    """f·cos = 1 / (2 pi) for every wo: f·cos does not vanish at the horizon (as in measured data)."""
    isotropic = True

    def eval(self, wi, wo):
        wo = np.atleast_2d(wo)
        return np.repeat((0.5 / np.pi / np.maximum(wo[:, 2], 1e-300))[:, None], 3, axis=1)


def test_relative_variance_ref_exposes_an_infinite_rv():
    """Cosine sampling of a target that stays positive at the horizon: rv = integral of
    1/(2 cos) over uniform wo - 1 diverges like ln k on a k x k grid. The direct estimate looks
    finite; the reference estimate grows by ~ln 8 from k = 128 to 1024 (plus heavy-tailed noise
    of ~0.5 per run, hence medians over seeds) and says that one point carries a visible share."""
    mat, wi, seeds = _FlatTarget(), incident(30), range(5)
    coarse = np.median([relative_variance_ref(mat, CosineSampler(), wi, UniformSampler(), 128, s)[0] for s in seeds])
    fine = [relative_variance_ref(mat, CosineSampler(), wi, UniformSampler(), 1024, s) for s in seeds]
    assert np.median([f[0] for f in fine]) - coarse > 0.5 * math.log(8)
    assert min(f[1] for f in fine) > 1e-3
    direct = np.median([relative_variance(mat, CosineSampler(), wi, n=1 << 16, seed=s)[0] for s in seeds])
    assert direct < np.median([f[0] for f in fine])
    # A sampler with the right tail: uniform sampling is exact for this target.
    assert relative_variance_ref(mat, UniformSampler(), wi, UniformSampler(), 256)[0] == pytest.approx(0, abs=1e-12)


def test_ggx_fit_in_threads_is_the_fit_of_one_thread(monkeypatch):
    """fit_ggx (the planner's lobe width, at the start of every bake) evaluates its angles and
    scores its alphas in threads, the angles' samples drawn in turn from the one generator: the
    same fit as in one thread, on a material whose best lobe is neither end of the grids."""
    import threading
    from bake.core import baselines
    from bake.io import threads as pool
    monkeypatch.setattr(pool, "workers", lambda: 2)
    mat = open_material({"kind": "analytic", "model": "plastic", "albedo": 0.5, "alpha": 0.12})
    seen, pdf = set(), baselines.ggx_reflection_pdf

    def spy(*args):
        seen.add(threading.current_thread().name.split("_")[0])
        return pdf(*args)
    monkeypatch.setattr(baselines, "ggx_reflection_pdf", spy)
    fits = {}
    for cores in (1, 2):
        monkeypatch.setattr(pool, "free_workers", lambda c, cores=cores: cores)
        fit = fit_ggx(mat, IdealSampler(mat, resolution=32), n=1 << 11)
        fits[cores] = (fit.alpha_x, fit.diffuse)
    assert fits[1] == fits[2]
    assert baselines.FIT_ALPHAS[0] < fits[1][0] < baselines.FIT_ALPHAS[-1]
    assert baselines.FIT_DIFFUSE[0] < fits[1][1] < baselines.FIT_DIFFUSE[-1]
    assert seen == {"MainThread", "flowbsdf-bake"}


def test_ggx_fit_recovers_a_ggx_material():
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.08})
    fit = fit_ggx(mat, IdealSampler(mat, resolution=128))
    assert fit.diffuse == 0.0
    assert fit.alpha_x == pytest.approx(0.08, rel=0.3)
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.5})
    assert fit_ggx(mat, IdealSampler(mat, resolution=32)).diffuse == 1.0
