"""Analytic BSDF models and the GGX sampling helpers (bake/materials/analytic.py)."""
import math

import numpy as np
import pytest

from bake.errors import FlowBSDFError
from bake.maths.geometry import incident, reflect, spherical_dir
from bake.materials import open_material
from bake.materials.analytic import (
    Lambert, Microfacet, Mixture, Retro, RoughPlastic, Sheen, beckmann_ndf, fresnel_conductor,
    from_spec, ggx_g1, ggx_lambda, ggx_ndf, ggx_reflection_pdf, ggx_sample_reflection,
    ggx_sample_vndf, ggx_vndf_pdf,
)
from bake.maths.warps import rotate_z

CU_ETA, CU_K = [0.2004, 0.9240, 1.1022], [3.9129, 2.4528, 2.1421]

SPECS = {
    "lambert": {"model": "lambert", "albedo": [0.8, 0.5, 0.2]},
    "ggx_iso": {"model": "ggx", "alpha": 0.1},
    "ggx_sharp": {"model": "ggx", "alpha": 0.01, "f0": [0.9, 0.6, 0.3]},
    "ggx_aniso": {"model": "ggx", "alpha_x": 0.01, "alpha_y": 0.5, "angle": 180,
                  "fresnel": "conductor", "eta": CU_ETA, "k": CU_K},
    "ggx_aniso_rot": {"model": "ggx", "alpha_x": 0.3, "alpha_y": 0.05, "angle": 37},
    "beckmann": {"model": "beckmann", "alpha_x": 0.2, "alpha_y": 0.08, "angle": -20, "f0": 0.5},
    "plastic": {"model": "plastic", "albedo": [0.6, 0.3, 0.1], "alpha": 0.15, "ior": 1.45},
    "sheen": {"model": "sheen", "color": [0.9, 0.7, 0.8], "roughness": 0.4},
    "retro": {"model": "retro", "alpha": 0.2, "color": 0.7},
    "mix": {"model": "mix", "components": [
        {"weight": 0.3, "model": "lambert", "albedo": 0.9},
        {"weight": 0.5, "model": "ggx", "alpha_x": 0.05, "alpha_y": 0.2, "angle": 60},
        {"weight": 0.2, "model": "retro", "alpha": 0.3}]},
}


# --------------------------------------------------------------------------- integration helpers

def hemisphere_grid(nt, nphi, power=1, quarter=False):
    """Midpoint rule on the upper hemisphere: directions and their solid-angle weights.

    theta = (pi/2) t^power with t uniform, so power > 1 crowds the nodes near the pole
    (where sharp lobes live); quarter=True covers phi in [0, pi/2) only.
    """
    t = (np.arange(nt) + 0.5) / nt
    theta = 0.5 * np.pi * t ** power
    dtheta = 0.5 * np.pi * power * t ** (power - 1) / nt
    span = 0.5 * np.pi if quarter else 2.0 * np.pi
    phi = (np.arange(nphi) + 0.5) / nphi * span - (0.0 if quarter else np.pi)
    T, P = np.meshgrid(theta, phi, indexing="ij")
    w = (np.sin(T) * dtheta[:, None] * (span / nphi)).ravel()
    return spherical_dir(T.ravel(), P.ravel()), w


def albedo(mat, wi, nt=300, nphi=256):
    """Integral of f cos over wo, through the half vector: wo = reflect(wi, m), d(wo) = 4 (wi.m) d(m).

    The map covers the whole sphere of wo once (m over the hemisphere with wi.m > 0), so this is
    exact for any material; the crowded-pole m grid resolves sharp specular lobes.
    """
    m, w = hemisphere_grid(nt, nphi, power=3)
    wi = np.broadcast_to(np.asarray(wi, float), m.shape)
    c = np.sum(wi * m, axis=-1)
    wo = reflect(wi, m)
    ok = (c > 0) & (wo[:, 2] > 0)
    f = mat.eval(wi[ok], wo[ok])
    return np.sum(f * (wo[ok, 2] * 4.0 * c[ok] * w[ok])[:, None], axis=0)


def albedo_direct(mat, wi, nt=400, nphi=800):
    """Integral of f cos over a plain (theta_o, phi_o) grid: for smooth or off-specular lobes."""
    wo, w = hemisphere_grid(nt, nphi)
    return np.sum(mat.eval(wi, wo) * (wo[:, 2] * w)[:, None], axis=0)


def random_dirs(rng, n, zmin=1e-3):
    z = rng.uniform(zmin, 1.0, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    return spherical_dir(np.arccos(z), phi)


def pairs(rng, mat, n=2000):
    """Random (wi, wo) pairs, half of them near the material's specular direction."""
    wi = random_dirs(rng, n)
    wo = random_dirs(rng, n)
    # Perturbed mirror directions: where sharp lobes are non-zero.
    m = spherical_dir(rng.uniform(0, 0.05, n // 2), rng.uniform(-np.pi, np.pi, n // 2))
    wo[: n // 2] = reflect(wi[: n // 2], m)
    keep = wo[:, 2] > 1e-3
    return wi[keep], wo[keep]


# --------------------------------------------------------------------------- basic properties

@pytest.mark.parametrize("key", sorted(SPECS))
def test_reciprocity(key):
    mat = from_spec(SPECS[key])
    wi, wo = pairs(np.random.default_rng(1), mat)
    a, b = mat.eval(wi, wo), mat.eval(wo, wi)
    assert np.all(np.isfinite(a)) and np.all(a >= 0)
    assert np.max(a) > 0
    np.testing.assert_allclose(a, b, rtol=1e-10, atol=0)


@pytest.mark.parametrize("key", sorted(SPECS))
def test_zero_below_horizon_and_broadcast(key):
    mat = from_spec(SPECS[key])
    rng = np.random.default_rng(2)
    wi, wo = random_dirs(rng, 50), random_dirs(rng, 50)
    below = wo * np.array([1, 1, -1])
    assert np.all(mat.eval(wi, below) == 0) and np.all(mat.eval(below, wo) == 0)
    f = mat.eval(wi[0], wo)                    # wi (3,) against wo (N,3)
    assert f.shape == (50, 3)
    np.testing.assert_array_equal(f, mat.eval(np.tile(wi[0], (50, 1)), wo))


def test_isotropic_flags_and_names():
    assert from_spec(SPECS["ggx_iso"]).isotropic
    assert not from_spec(SPECS["ggx_aniso"]).isotropic
    assert not from_spec(SPECS["mix"]).isotropic
    for key in ("lambert", "plastic", "sheen", "retro"):
        assert from_spec(SPECS[key]).isotropic
    assert from_spec(SPECS["ggx_iso"]).name == "ggx(a=0.1)"
    assert "conductor" in from_spec(SPECS["ggx_aniso"]).name
    assert from_spec({"model": "lambert", "albedo": 0.5, "name": "chalk"}).name == "chalk"


def test_fingerprints():
    fp = {k: from_spec(s).fingerprint() for k, s in SPECS.items()}
    assert len(set(fp.values())) == len(fp)
    assert from_spec(SPECS["mix"]).fingerprint() == fp["mix"]
    changed = {"model": "mix", "components": [dict(c) for c in SPECS["mix"]["components"]]}
    changed["components"][1]["alpha_y"] = 0.21
    assert from_spec(changed).fingerprint() != fp["mix"]
    assert Microfacet("ggx", 0.1).fingerprint() != Microfacet("ggx", 0.1 + 1e-12).fingerprint()
    assert Microfacet("ggx", 0.1).fingerprint() != Microfacet("beckmann", 0.1).fingerprint()
    # The name does not change the BSDF, the model does.
    assert Lambert(0.5, name="chalk").fingerprint() == Lambert(0.5).fingerprint()
    assert Retro(0.2, 0.5).fingerprint() != Retro(0.2, 0.6).fingerprint()


def test_open_material_dispatch():
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.1})
    assert isinstance(mat, Microfacet) and mat.alpha_x == mat.alpha_y == 0.1


# --------------------------------------------------------------------------- energy

def test_lambert_albedo_exact():
    mat = Lambert([0.8, 0.5, 0.2])
    for theta in (0, 45, 85):
        np.testing.assert_allclose(albedo(mat, incident(theta), 400, 128), [0.8, 0.5, 0.2], rtol=2e-4)
    np.testing.assert_array_equal(mat.eval(incident(10), incident(50, 2.0)), [[0.8 / np.pi, 0.5 / np.pi, 0.2 / np.pi]])


@pytest.mark.parametrize("spec", [
    {"model": "ggx", "alpha": a} for a in (0.002, 0.01, 0.1, 0.5, 1.0)] + [
    {"model": "beckmann", "alpha": a} for a in (0.01, 0.3, 1.0)] + [
    {"model": "ggx", "alpha_x": 0.01, "alpha_y": 0.5, "angle": 30},
    {"model": "beckmann", "alpha_x": 0.5, "alpha_y": 0.02, "angle": 200}],
    ids=lambda s: from_spec(s).name)
def test_conductor_albedo_at_most_one(spec):
    mat = from_spec(spec)                       # F = 1: every loss is Smith masking
    for theta in (0, 45, 80, 89):
        a = albedo(mat, incident(theta, 0.4))
        assert np.all(a <= 1.0 + 2e-4), (theta, a)
        assert np.all(a > 0.2), (theta, a)


def test_ggx_albedo_near_one_for_small_alpha():
    # Single-scattering Smith GGX loses the energy of multiple bounces between microfacets:
    # negligible for sharp lobes, about 1 % at alpha 0.1, 12 % at 0.3, 31 % at 0.5 (normal incidence).
    expected = {0.002: 0.9999, 0.01: 0.999, 0.1: 0.985, 0.3: 0.87, 0.5: 0.68}
    for alpha, lo in expected.items():
        a = albedo(Microfacet("ggx", alpha), incident(0))[0]
        assert lo <= a <= 1.0 + 1e-4, (alpha, a)


def test_albedo_matches_vndf_sampling_estimate():
    """The grid integral agrees with the importance-sampled estimate mean(f cos / pdf)."""
    rng = np.random.default_rng(3)
    for ax, ay, theta, phi in [(0.1, 0.1, 60, 0.0), (0.5, 0.5, 85, 1.0), (0.05, 0.4, 40, 2.0)]:
        mat = Microfacet("ggx", ax, ay)
        wi = incident(theta, phi)
        wo = ggx_sample_reflection(wi, ax, ay, rng.random((100_000, 2)))
        pdf = ggx_reflection_pdf(wi, wo, ax, ay)
        ok = pdf > 0
        est = np.zeros(len(wo))
        est[ok] = mat.eval(wi, wo[ok])[:, 0] * wo[ok, 2] / pdf[ok]
        stderr = est.std() / math.sqrt(len(est))
        grid = albedo(mat, wi, 400, 512)[0]
        assert abs(est.mean() - grid) < 4 * stderr + 1e-4, (ax, ay, theta, est.mean(), grid, stderr)


def test_fresnel_terms():
    n, k = np.array(CU_ETA), np.array(CU_K)
    normal = ((n - 1) ** 2 + k ** 2) / ((n + 1) ** 2 + k ** 2)
    np.testing.assert_allclose(fresnel_conductor(np.array([1.0]), n, k)[0], normal, rtol=1e-12)
    np.testing.assert_allclose(fresnel_conductor(np.array([0.0]), n, k)[0], 1.0, rtol=1e-12)
    # A dielectric-like conductor (k = 0) matches the dielectric formula.
    from bake.materials.analytic import fresnel_dielectric
    c = np.linspace(0.01, 1, 7)
    np.testing.assert_allclose(fresnel_conductor(c, 1.5, 0.0)[:, 0], fresnel_dielectric(c, 1.5), rtol=1e-10)
    # Copper: below the F = 1 lobe, and reddish.
    cu = from_spec(SPECS["ggx_aniso"])
    white = Microfacet("ggx", 0.01, 0.5, angle=180)
    a_cu, a_white = albedo(cu, incident(30)), albedo(white, incident(30))
    assert np.all(a_cu < a_white) and a_cu[0] > a_cu[1] > a_cu[2]


def test_other_models_energy():
    for theta in (0, 45, 80, 89):
        wi = incident(theta)
        for alpha in (0.05, 0.5):
            assert np.all(albedo(RoughPlastic(1.0, alpha, 1.5), wi) < 0.95)
        for r in (0.1, 0.5, 1.0):
            assert np.all(albedo_direct(Sheen(1.0, r), wi) < 0.96)
        # The retro lobe is the GGX lobe with wo turned by pi: exactly the same albedo
        # (on a grid symmetric under that turn, to rounding).
        np.testing.assert_allclose(albedo_direct(Retro(0.2), wi), albedo_direct(Microfacet("ggx", 0.2), wi),
                                   rtol=1e-10)
    mix = from_spec(SPECS["mix"])
    parts = [0.3 * albedo(Lambert(0.9), incident(40)),
             0.5 * albedo(Microfacet("ggx", 0.05, 0.2, angle=60), incident(40)),
             0.2 * albedo(Retro(0.3), incident(40))]
    np.testing.assert_allclose(albedo(mix, incident(40)), sum(parts), rtol=1e-12)


def test_retro_peaks_at_wi():
    mat = Retro(0.1)
    wi = incident(50, 0.7)
    wo = spherical_dir(*np.meshgrid(np.radians(np.linspace(0.5, 89.5, 179)), np.linspace(-np.pi, np.pi, 361),
                                    indexing="ij"))
    f = mat.eval(wi, wo.reshape(-1, 3))[:, 0]
    best = wo.reshape(-1, 3)[np.argmax(f)]
    assert np.dot(best, wi) > np.cos(np.radians(0.75))


# --------------------------------------------------------------------------- GGX NDF and VNDF

@pytest.mark.parametrize("ax,ay", [(0.002, 0.002), (0.01, 0.01), (0.1, 0.1), (0.5, 0.5), (1.0, 1.0),
                                   (0.01, 0.5), (0.5, 0.01), (0.002, 0.1)])
def test_ndf_normalization(ax, ay):
    # D is even in m.x and m.y: integrate one quadrant of phi, times 4.
    m, w = hemisphere_grid(2000, 8 if ax == ay else 512, power=3, quarter=True)
    for ndf in (ggx_ndf, beckmann_ndf):
        total = 4.0 * np.sum(ndf(m, ax, ay) * m[:, 2] * w)
        assert abs(total - 1.0) < 1e-5, (ndf.__name__, total)


def test_material_ndf_rotation_normalized():
    mat = Microfacet("ggx", 0.01, 0.5, angle=123)
    m, w = hemisphere_grid(1000, 2048, power=3)
    assert abs(np.sum(mat.ndf(m) * m[:, 2] * w) - 1.0) < 1e-5


@pytest.mark.parametrize("ax,ay", [(0.002, 0.002), (0.1, 0.1), (1.0, 1.0), (0.01, 0.5), (0.5, 0.01)])
def test_vndf_pdf_integrates_to_one(ax, ay):
    m, w = hemisphere_grid(600, 1024, power=3)
    for theta in (0, 45, 80, 89.9):
        total = np.sum(ggx_vndf_pdf(incident(theta, 0.3), m, ax, ay) * w)
        assert abs(total - 1.0) < 2e-5, (theta, total)


def test_g1_and_lambda():
    w = random_dirs(np.random.default_rng(4), 1000)
    for ax, ay in [(0.1, 0.1), (0.02, 0.7)]:
        np.testing.assert_allclose(ggx_g1(w, ax, ay), 1.0 / (1.0 + ggx_lambda(w, ax, ay)), rtol=1e-12)
    assert ggx_g1(np.array([0.0, 0.0, 1.0]), 0.5, 0.5) == 1.0
    assert ggx_g1(np.array([0.0, 1.0, -0.1]), 0.5, 0.5) == 0.0


def _chi2_quantile(dof, z=3.29):
    """Wilson-Hilferty approximation of the chi-square quantile (z = 3.29: p = 0.9995)."""
    return dof * (1 - 2 / (9 * dof) + z * math.sqrt(2 / (9 * dof))) ** 3


@pytest.mark.parametrize("ax,ay,theta,phi", [
    (0.3, 0.3, 0, 0.0), (0.2, 0.6, 60, 0.7), (0.5, 0.1, 85, 2.5), (0.05, 0.05, 45, -1.0),
    (0.01, 0.3, 89, 3.0)])
def test_vndf_histogram_matches_pdf(ax, ay, theta, phi):
    """Chi-square comparison of ggx_sample_vndf with ggx_vndf_pdf on (theta_m, phi_m) bins."""
    n = 200_000
    wi = incident(theta, phi)
    m = ggx_sample_vndf(wi, ax, ay, np.random.default_rng(5).random((n, 2)))
    assert np.all(np.isfinite(m))
    np.testing.assert_allclose(np.linalg.norm(m, axis=1), 1.0, atol=1e-12)
    assert np.all(m[:, 2] >= 0) and np.all(m @ wi >= -1e-12)

    tmax = min(0.5 * np.pi, math.atan(6 * max(ax, ay)))
    nt, nphi, sub = 16, 24, 10
    theta_m = np.arctan2(np.hypot(m[:, 0], m[:, 1]), m[:, 2])
    phi_m = np.arctan2(m[:, 1], m[:, 0])
    it = np.minimum((theta_m / tmax * nt).astype(int), nt)            # nt = the overflow bin
    ip = np.minimum(((phi_m + np.pi) / (2 * np.pi) * nphi).astype(int), nphi - 1)
    counts = np.zeros((nt + 1, nphi))
    np.add.at(counts, (it, np.where(it == nt, 0, ip)), 1)
    # Expected probabilities: midpoint rule with sub x sub nodes per bin.
    tt = (np.arange(nt * sub) + 0.5) / (nt * sub) * tmax
    pp = (np.arange(nphi * sub) + 0.5) / (nphi * sub) * 2 * np.pi - np.pi
    T, P = np.meshgrid(tt, pp, indexing="ij")
    dens = ggx_vndf_pdf(wi, spherical_dir(T.ravel(), P.ravel()), ax, ay).reshape(T.shape) * np.sin(T)
    prob = dens.reshape(nt, sub, nphi, sub).sum(axis=(1, 3)) * (tmax / (nt * sub)) * (2 * np.pi / (nphi * sub))
    expected = np.zeros((nt + 1, nphi))
    expected[:nt] = prob * n
    expected[nt, 0] = max(n - expected[:nt].sum(), 0.0)
    e, c = expected.ravel(), counts.ravel()
    big = e >= 5
    e_pool, c_pool = np.append(e[big], e[~big].sum()), np.append(c[big], c[~big].sum())
    keep = e_pool > 0
    stat = np.sum((c_pool[keep] - e_pool[keep]) ** 2 / e_pool[keep])
    dof = keep.sum() - 1
    assert stat < _chi2_quantile(dof), (stat, dof)


def test_sample_vndf_edge_cases():
    rng = np.random.default_rng(6)
    u = rng.random((5000, 2))
    for ax, ay in [(0.002, 0.002), (0.002, 0.1), (1.0, 0.02)]:
        for theta in (0.0, 30.0, 89.0, 89.999):
            wi = incident(theta, 0.9)
            m = ggx_sample_vndf(wi, ax, ay, u)
            assert np.all(np.isfinite(m)) and np.all(m[:, 2] >= 0) and np.all(m @ wi >= -1e-12)
            pdf = ggx_vndf_pdf(wi, m, ax, ay)
            assert np.all(np.isfinite(pdf)) and np.all(pdf > 0)
    # Per-row parameters broadcast.
    wi = random_dirs(rng, 100)
    ax, ay = rng.uniform(0.01, 1, 100), rng.uniform(0.01, 1, 100)
    m = ggx_sample_vndf(wi, ax, ay, u[:100])
    one = np.array([ggx_sample_vndf(wi[i], ax[i], ay[i], u[i:i + 1])[0] for i in range(5)])
    np.testing.assert_allclose(m[:5], one, rtol=1e-12)


def test_reflection_pdf_is_vndf_pdf_over_4_wi_dot_m():
    rng = np.random.default_rng(7)
    ax, ay = 0.15, 0.4
    wi = incident(70, 1.2)
    m = ggx_sample_vndf(wi, ax, ay, rng.random((1000, 2)))
    wo = 2 * (m @ wi)[:, None] * m - wi
    up = wo[:, 2] > 0
    np.testing.assert_allclose(ggx_reflection_pdf(wi, wo[up], ax, ay),
                               ggx_vndf_pdf(wi, m[up], ax, ay) / (4 * np.abs(m[up] @ wi)), rtol=1e-9)
    assert np.all(ggx_reflection_pdf(wi, wo[~up], ax, ay) == 0)
    # Integrates over the upper hemisphere of wo to the probability of landing there.
    grid_wo, w = hemisphere_grid(600, 1024, power=1)
    total = np.sum(ggx_reflection_pdf(wi, grid_wo, ax, ay) * w)
    assert 0.9 < total <= 1.0 + 1e-4 and abs(total - up.mean()) < 0.03


# --------------------------------------------------------------------------- anisotropy and its rotation

def test_rotation_is_a_rotation_of_the_lobe():
    rng = np.random.default_rng(8)
    wi, wo = pairs(rng, None, 1000)
    base = Microfacet("ggx", 0.05, 0.4, fresnel="schlick", f0=0.7)
    for deg in (30, 180, -135):
        rot = Microfacet("ggx", 0.05, 0.4, angle=deg, fresnel="schlick", f0=0.7)
        a = math.radians(deg)
        np.testing.assert_allclose(rot.eval(rotate_z(wi, a), rotate_z(wo, a)), base.eval(wi, wo), rtol=1e-10)
    # A half turn maps the (centrally symmetric) lobe onto itself; a quarter turn swaps the axes.
    np.testing.assert_allclose(Microfacet("ggx", 0.05, 0.4, angle=180).eval(wi, wo),
                               Microfacet("ggx", 0.05, 0.4).eval(wi, wo), rtol=1e-10)
    np.testing.assert_allclose(Microfacet("ggx", 0.05, 0.4, angle=90).eval(wi, wo),
                               Microfacet("ggx", 0.4, 0.05).eval(wi, wo), rtol=1e-10)


@pytest.mark.parametrize("deg", [0, 30, 90, 180, 250])
def test_anisotropic_lobe_lies_along_rotated_axis(deg):
    """Normal incidence, alpha_y >> alpha_x: the lobe stretches along azimuth angle + 90 deg."""
    mat = Microfacet("ggx", 0.02, 0.5, angle=deg)
    wi = np.array([0.0, 0.0, 1.0])
    azimuths = np.radians(deg + np.arange(0, 360, 5.0))
    f = mat.eval(wi, spherical_dir(np.radians(30), azimuths))[:, 0]
    best = np.degrees(azimuths[f >= 0.999 * f.max()]) - deg
    assert set(np.round(best) % 180) == {90.0}
    assert f.max() > 1e3 * f.min()


def test_lobe_straddling_phi_pi():
    """wi at phi = 0 reflects around phi = pi; a lobe wide along y covers both sides of the seam."""
    mat = from_spec({"model": "ggx", "alpha_x": 0.01, "alpha_y": 0.5, "angle": 180})
    wi = incident(40, 0.0)
    phis = np.radians(np.arange(-180, 180, 0.5))
    wo = spherical_dir(np.radians(40), phis)
    f = mat.eval(wi, wo)[:, 0]
    assert abs(abs(np.degrees(phis[np.argmax(f)])) - 180) < 1e-9
    # Along the lobe (microfacet normals tilted along +-y), wo falls on both sides of the seam.
    for slope in (0.1, 0.3, 0.6):
        m = np.array([[0.0, slope, 1.0], [0.0, -slope, 1.0]]) / math.hypot(slope, 1.0)
        wo_pair = reflect(np.tile(wi, (2, 1)), m)
        phi_pair = np.degrees(np.arctan2(wo_pair[:, 1], wo_pair[:, 0]))
        assert 90 < phi_pair[0] < 180 and -180 < phi_pair[1] < -90     # straddles phi = +-180
        left, right = mat.eval(wi, wo_pair)[:, 0]
        assert left == pytest.approx(right, rel=1e-10) and left > 1e-2 * f.max()
    assert mat.eval(wi, spherical_dir(np.radians(40), 0.0))[0, 0] < 1e-6 * f.max()
    # Turning the lobe by 90 deg narrows it across the seam.
    turned = from_spec({"model": "ggx", "alpha_x": 0.01, "alpha_y": 0.5, "angle": 90})
    assert turned.eval(wi, spherical_dir(np.radians(40), np.radians(160)))[0, 0] < 1e-3 * f.max()


# --------------------------------------------------------------------------- from_spec validation

@pytest.mark.parametrize("spec,words", [
    ({"model": "phong", "alpha": 0.1}, ["model", "phong"]),
    ({"alpha": 0.1}, ["model"]),
    ({"kind": "merl", "model": "ggx", "alpha": 0.1}, ["kind"]),
    ({"model": "ggx", "alhpa": 0.1}, ["alhpa"]),
    ({"model": "ggx"}, ["alpha"]),
    ({"model": "ggx", "alpha": 0.0}, ["alpha", "range"]),
    ({"model": "ggx", "alpha": -0.1}, ["alpha"]),
    ({"model": "ggx", "alpha": 1.5}, ["alpha"]),
    ({"model": "ggx", "alpha": "rough"}, ["alpha", "number"]),
    ({"model": "ggx", "alpha": True}, ["alpha"]),
    ({"model": "ggx", "alpha": float("nan")}, ["alpha", "finite"]),
    ({"model": "ggx", "alpha_x": 0.1}, ["alpha_y"]),
    ({"model": "ggx", "alpha": 0.1, "alpha_x": 0.1, "alpha_y": 0.2}, ["alpha_x"]),
    ({"model": "ggx", "alpha_x": 0.1, "alpha_y": 0.0}, ["alpha_y"]),
    ({"model": "ggx", "alpha": 0.1, "fresnel": "fancy"}, ["fresnel", "fancy"]),
    ({"model": "ggx", "alpha": 0.1, "fresnel": "conductor", "eta": 0.2}, ["'k'"]),
    ({"model": "ggx", "alpha": 0.1, "fresnel": "conductor", "eta": [0.2, 0.9, 1.1], "k": -1}, ["'k'"]),
    ({"model": "ggx", "alpha": 0.1, "eta": [0.0, 0.9, 1.1], "k": 1}, ["eta"]),
    ({"model": "ggx", "alpha": 0.1, "fresnel": "conductor", "eta": 1, "k": 1, "f0": 0.5}, ["f0"]),
    ({"model": "ggx", "alpha": 0.1, "f0": 1.2}, ["f0"]),
    ({"model": "ggx", "alpha": 0.1, "angle": "north"}, ["angle"]),
    ({"model": "lambert", "albedo": [0.5, -0.1, 0.2]}, ["albedo"]),
    ({"model": "lambert", "albedo": [0.5, 0.1]}, ["albedo", "3"]),
    ({"model": "lambert"}, ["albedo", "missing"]),
    ({"model": "lambert", "albedo": 0.5, "alpha": 0.1}, ["alpha", "unknown"]),
    ({"model": "lambert", "albedo": 0.5, "name": 3}, ["name"]),
    ({"model": "plastic", "albedo": 0.5, "alpha": 0.1, "ior": 0.9}, ["ior"]),
    ({"model": "plastic", "albedo": 0.5}, ["alpha"]),
    ({"model": "sheen", "color": 0.5, "roughness": 0.0}, ["roughness"]),
    ({"model": "retro", "color": 0.5}, ["alpha"]),
    ({"model": "mix", "components": []}, ["components"]),
    ({"model": "mix", "components": [{"model": "lambert", "albedo": 0.5}]}, ["weight", "components[0]"]),
    ({"model": "mix", "components": [{"weight": 0.0, "model": "lambert", "albedo": 0.5}]}, ["weight"]),
    ({"model": "mix", "components": [{"weight": -1, "model": "lambert", "albedo": 0.5}]}, ["weight"]),
    ({"model": "mix", "components": [{"weight": 0.5, "model": "lambert", "albedo": 0.5},
                                     {"weight": 0.5, "model": "ggx", "alpha": 0}]}, ["components[1]", "alpha"]),
    ({"model": "mix", "components": [{"weight": 1, "model": "mix", "components": [
        {"weight": 1, "model": "lambert", "albdo": 1}]}]}, ["components[0].components[0]", "albdo"]),
    ({"model": "mix", "components": "lambert"}, ["components"]),
])
def test_from_spec_errors(spec, words):
    with pytest.raises(FlowBSDFError) as e:
        from_spec(spec)
    for word in words:
        assert word in str(e.value), (word, str(e.value))


def test_from_spec_builds_the_right_models():
    m = from_spec(SPECS["ggx_aniso"])
    assert isinstance(m, Microfacet) and (m.alpha_x, m.alpha_y, m.angle, m.fresnel) == (0.01, 0.5, 180.0, "conductor")
    assert m.eta == tuple(CU_ETA) and m.k == tuple(CU_K)
    assert from_spec({"model": "ggx", "alpha": 0.1, "f0": 0.04}).fresnel == "schlick"
    assert from_spec({"model": "ggx", "alpha": 0.1}).fresnel == "none"
    assert isinstance(from_spec(SPECS["plastic"]), RoughPlastic)
    assert isinstance(from_spec(SPECS["sheen"]), Sheen)
    assert isinstance(from_spec(SPECS["retro"]), Retro)
    mix = from_spec(SPECS["mix"])
    assert isinstance(mix, Mixture) and mix.weights == [0.3, 0.5, 0.2]
    assert from_spec({"model": "ggx", "alpha": 0.002}).alpha_x == 0.002
    with pytest.raises(FlowBSDFError):
        from_spec(["ggx"])
