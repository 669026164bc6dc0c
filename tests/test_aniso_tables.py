"""Baked tables of anisotropic materials: bins over theta_i x phi_i (bake/core/tables.py).

The hard cases aniso_1to50 (GGX alpha 0.5 x 0.01) and its rotated twin (0.01 x 0.5 at 37
deg), small tables (16x16 cells, 5 theta bins x 8 phi bins over the period pi): sample, pdf
and invert are one exact bijection at any wi, on bins and between them; the blend wraps
around the period; chi-square passes between bins; rv is finite (and on bins as good as
the ideal sampler's); files round-trip; `flowbsdf bake` bakes an anisotropic manifest entry.
"""
import math

import numpy as np
import pytest

from bake.maths.geometry import incident
from conftest import slow_unless
from bake.core.ideal import IdealSampler
from bake.core.settings import BakeSettings
from bake.core.metrics import chi2_test, relative_variance, relative_variance_ref
from bake.export.osl_export import LAYOUT
from bake.quality.stress import hard_cases, make_tables
from bake.core.table_files import open_tables
from bake.maths.warps import rotate_z
from contract import assert_sampler_contract

NAMES = ("aniso_1to50", "aniso_1to50_rotated")
CASES = {c.name: c for c in hard_cases() if c.name in NAMES}
THETA_BINS = np.radians([0.0, 40.0, 75.0, 86.0, 89.5])
PHIS_DEG = (0.0, 7.0, 22.5, 37.0, 180.0, 359.9)      # 8 bins over pi: 0, 22.5 and 180 on a bin
CHI2_WIS = ((30.0, 7.0), (57.3, 100.0), (80.0, 211.0))       # all between bins
N_CHI2 = len(NAMES) * len(CHI2_WIS)                           # every chi-square of this file


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """{case: (material, ideal sampler, tables over (a, b) of wo: files baked before the half
    vector became anisotropic tables' default, still read and sampled)}."""
    workdir = tmp_path_factory.mktemp("aniso")
    out = {}
    for name in NAMES:
        mat = CASES[name].open(workdir)
        ideal = IdealSampler(mat, resolution=64)
        out[name] = (mat, ideal, make_tables(mat, ideal, size=16, grid=64, bins=THETA_BINS, coords="wo"))
    return out


@pytest.mark.parametrize("name", NAMES)
def test_tables_have_a_phi_axis(baked, name):
    mat, _, tab = baked[name]
    assert tab.anisotropic and tab.phi_period == pytest.approx(math.pi) == mat.phi_period
    np.testing.assert_allclose(tab.phi_bins, np.arange(8) * math.pi / 8)
    assert tab.mass.shape == (5, 8, 16, 16) and tab.a_edges.shape == (5, 8, 17)
    assert tab._fast is None            # the C path is isotropic only: numpy serves these


@pytest.mark.parametrize("name", NAMES)
def test_sample_pdf_invert_exact_on_and_between_bins(baked, name):
    _, _, tab = baked[name]
    rng = np.random.default_rng(1)
    for theta in (40.0, 30.0, 57.3, 88.0):          # on a theta bin, then between bins
        for phi in PHIS_DEG:
            wi = incident(theta, math.radians(phi))
            assert_sampler_contract(tab, wi, rng.random((20000, 2)), pdf_rtol=1e-9, invert_rtol=0,
                                    invert_atol=1e-9, where=(theta, phi))


@pytest.mark.parametrize("name", NAMES)
def test_phi_blend_is_periodic(baked, name):
    """phi_i just below 2 pi and just above 0 get the same table; so do wi and wi turned by the
    period (the material's symmetry), at the same wo turned alike."""
    _, _, tab = baked[name]
    rng = np.random.default_rng(2)
    wo = tab.sample(incident(50.0, 0.0), rng.random((5000, 2)))[0]
    below, above = tab.pdf(incident(50.0, -1e-12), wo), tab.pdf(incident(50.0, 1e-12), wo)
    np.testing.assert_allclose(below, above, rtol=1e-6)
    np.testing.assert_allclose(tab.pdf(incident(50.0, 2 * math.pi), wo), tab.pdf(incident(50.0, 0.0), wo),
                               rtol=1e-9)
    for phi in (0.3, 2.0):
        turned = tab.pdf(incident(61.0, phi + tab.phi_period), rotate_z(wo, phi + tab.phi_period))
        np.testing.assert_allclose(turned, tab.pdf(incident(61.0, phi), rotate_z(wo, phi)), rtol=1e-9)


@pytest.mark.parametrize("name,theta,phi", slow_unless([(n, t, p) for n in NAMES for t, p in CHI2_WIS],
                                                   default=[("aniso_1to50_rotated", 57.3, 100.0)], unpack=True))
def test_chi2_between_bins(baked, name, theta, phi):
    r = chi2_test(baked[name][2], incident(theta, math.radians(phi)), n=100_000, n_tests=N_CHI2, seed=11)
    assert r.passed, (name, theta, phi, r)


@pytest.mark.parametrize("name", NAMES)
def test_rv_against_the_ideal_sampler(baked, name):
    """On bins the tables come near the ideal sampler: rv within 4x of its, estimated from the
    ideal's samples (relative_variance_ref: the tables' own samples miss where their pdf is far
    below f·cos). Measured with profiles 0.12-0.70x, and 3.7x at (75, 90) on the rotated lobe;
    one exponential per cell measured 72x there (1.31x from the tables' own samples, which this
    test took before). Between bins rv is finite but far worse: the blend of two bins is no
    displacement of the thin 1:50 lobe (which, near phi_i = 0 mod pi, passes over the pole and
    across the seam b = 0). Measured with these tables: 2-980x the ideal sampler's rv (worst at
    theta_i and phi_i both between bins), hence the loose bound: a guard against NaN/inf/collapse only."""
    mat, ideal, tab = baked[name]
    for theta, phi in ((40.0, 0.0), (75.0, 90.0), (40.0, 157.5)):        # on bins
        wi = incident(theta, math.radians(phi))
        rv, ref = (relative_variance_ref(mat, s, wi, ideal, k=512, seed=7)[0] for s in (tab, ideal))
        assert rv < 4 * ref, (theta, phi, rv, ref)
    for theta, phi in CHI2_WIS:
        wi = incident(theta, math.radians(phi))
        rv, ref = relative_variance(mat, tab, wi, n=20000)[0], relative_variance(mat, ideal, wi, n=20000)[0]
        assert math.isfinite(rv) and rv < 2000 * ref, (theta, phi, rv, ref)


def test_file_round_trip(baked, tmp_path):
    _, _, tab = baked["aniso_1to50_rotated"]
    path = tmp_path / "aniso.exr"
    tab.save(path)
    back = open_tables(path)
    assert back.anisotropic and back.phi_period == tab.phi_period
    np.testing.assert_array_equal(back.phi_bins, tab.phi_bins)
    for key in ("a_edges", "b_edges", "mass", "alpha", "beta", "weights"):
        np.testing.assert_array_equal(getattr(back, key), getattr(tab, key))
    wi = incident(63.0, 2.5)
    u = np.random.default_rng(3).random((2000, 2))
    np.testing.assert_array_equal(back.sample(wi, u)[0], tab.sample(wi, u)[0])


@pytest.mark.slow
def test_bake_an_anisotropic_manifest_entry(tmp_path):
    """flowbsdf bake bakes it (no more "[skip] anisotropic"), with its OSL texture (the
    layout has phi bins) and closure fit; a second run finds it current."""
    from bake.plumbing.manifest import load_manifest
    from bake.io.paths import table_path
    from bake.plumbing.pipeline import bake_manifest
    manifest = tmp_path / "manifest.toml"
    manifest.write_text('[[material]]\nname = "brushed"\n'
                        'source = { kind = "analytic", model = "ggx", alpha_x = 0.3, alpha_y = 0.05, angle = 20 }\n'
                        'bake = { source = "ideal", resolution = 16, grid = 64, samples = 1024, first_bins = 3, '
                        'tol = 5.0, ideal_resolution = 32, phi_count = 4 }\n')
    out = tmp_path / "out"
    lines = []
    written = bake_manifest(load_manifest(manifest), out, log=lines.append)
    path = table_path(out, "brushed")
    assert written == [path], lines
    tab = open_tables(path)
    assert tab.anisotropic and len(tab.phi_bins) == 5 and tab.coords == "halfvector" and len(tab.theta_bins) == 3
    names = sorted(p.name for p in path.parent.iterdir())
    assert len(names) == 4 and names[0] == "brushed.exr" and names[1] == "brushed.fit.json", names
    assert names[2].startswith(f"brushed.osl{LAYOUT}-") and names[2].endswith(".exr"), names
    assert names[3].startswith("brushed.svm") and names[3].endswith(".exr"), names
    wi = incident(50.0, 1.0)
    assert_sampler_contract(tab, wi, np.random.default_rng(4).random((1000, 2)), pdf_rtol=1e-9)
    assert bake_manifest(load_manifest(manifest), out, log=lines.append) == []


# -- halfvector coordinates (bake/core/halfvector.py) -------------------------------------
BETWEEN_PHIS = [p * 15.0 + 7.0 for p in range(12)]      # 12 phi_i, none on a bin (22.5 deg apart)


@pytest.fixture(scope="module")
def baked_half(tmp_path_factory):
    """{case: (material, ideal sampler, tables over the half vector)}, as `baked` otherwise."""
    workdir = tmp_path_factory.mktemp("aniso_half")
    out = {}
    for name in NAMES:
        mat = CASES[name].open(workdir)
        ideal = IdealSampler(mat, resolution=64)
        out[name] = (mat, ideal, make_tables(mat, ideal, size=16, grid=64, bins=THETA_BINS))
    return out


@pytest.mark.parametrize("name", NAMES)
def test_halfvector_tables_close_the_period_and_follow_the_lobe(baked_half, name):
    mat, _, tab = baked_half[name]
    assert tab.coords == "halfvector" and tab.mass.shape == (5, 9, 16, 16)
    np.testing.assert_allclose(tab.phi_bins, np.arange(9) * math.pi / 8)      # 0 .. pi, closed
    # the lobe's axes found from the source: 0 (mod pi/2) for aniso_1to50, 37 deg for the rotated one
    expect = 37.0 if name.endswith("rotated") else 0.0
    assert abs((math.degrees(tab.frame_angle) - expect + 45.0) % 90.0 - 45.0) < 2.0, math.degrees(tab.frame_angle)


@pytest.mark.parametrize("name", NAMES)
def test_halfvector_sample_pdf_invert_exact_on_and_between_bins(baked_half, name):
    """The contract at any wi. pdf to 1e-8: at theta_i 88 the specular peak sits within 1e-6 of
    h = z, where h = normalize(wi + wo) from a sampled wo keeps ~1e-9 of its relative precision
    (wi.h ~ 0.035): the map's conditioning, not a mismatch of sample() and pdf()."""
    _, _, tab = baked_half[name]
    rng = np.random.default_rng(1)
    for theta in (40.0, 30.0, 57.3, 88.0):
        for phi in PHIS_DEG + (-30.0, 200.0, 539.0):
            wi = incident(theta, math.radians(phi))
            assert_sampler_contract(tab, wi, rng.random((20000, 2)), pdf_rtol=1e-8, invert_rtol=0,
                                    invert_atol=1e-7, where=(theta, phi))


@pytest.mark.parametrize("name", NAMES)
def test_halfvector_tables_hold_the_lobe_between_bins(baked_half, name):
    """rv at 12 phi_i between bins, three theta_i between bins, within 2x the ideal sampler's
    (measured 0.18-0.31x of this 64^2 ideal, 1.1-5x of a 256^2 one; the "wo" tables above:
    up to 15x of this ideal, 230x of the 256^2 one, at phi_i = 172)."""
    mat, ideal, tab = baked_half[name]
    worst = []
    for theta in (30.0, 57.3, 80.0):
        for phi in BETWEEN_PHIS:
            wi = incident(theta, math.radians(phi))
            rv, ref = relative_variance(mat, tab, wi, n=20000)[0], relative_variance(mat, ideal, wi, n=20000)[0]
            worst.append((rv / ref, theta, phi))
    assert max(worst)[0] < 2.0, max(worst)


@pytest.mark.parametrize("name", NAMES)
def test_halfvector_pdf_is_periodic(baked_half, name):
    """wi turned by the period, wo alike: the same pdf (the blend turns phi_i back by whole
    periods); across phi_i = 0 the closing bin (the first one's cells turned by pi) meets the
    first one, but for the odd wo on a cell's edge (float32 edges 1 - a, 2 pi - b round)."""
    _, _, tab = baked_half[name]
    rng = np.random.default_rng(2)
    wo = tab.sample(incident(50.0, 0.0), rng.random((5000, 2)))[0]
    for phi in (0.3, 2.0):
        turned = tab.pdf(incident(61.0, phi + tab.phi_period), rotate_z(wo, phi + tab.phi_period))
        np.testing.assert_allclose(turned, tab.pdf(incident(61.0, phi), rotate_z(wo, phi)), rtol=1e-9)
    below, above = tab.pdf(incident(50.0, -1e-9), wo), tab.pdf(incident(50.0, 1e-9), wo)
    close = np.isclose(below, above, rtol=1e-4, atol=0)
    assert close.mean() > 0.999 and np.allclose(below, above, rtol=0.1), (close.mean(), np.max(below / above))


def test_halfvector_chi2_between_bins(baked_half):
    r = chi2_test(baked_half["aniso_1to50_rotated"][2], incident(57.3, math.radians(100.0)), n=100_000,
                  n_tests=N_CHI2, seed=11)
    assert r.passed, r


def test_halfvector_file_round_trip(baked_half, tmp_path):
    _, _, tab = baked_half["aniso_1to50_rotated"]
    path = tmp_path / "aniso_half.exr"
    tab.save(path)
    back = open_tables(path)
    assert back.coords == "halfvector" and back.frame_angle == tab.frame_angle
    np.testing.assert_array_equal(back.phi_bins, tab.phi_bins)
    wi = incident(63.0, 2.5)
    u = np.random.default_rng(3).random((2000, 2))
    np.testing.assert_array_equal(back.sample(wi, u)[0], tab.sample(wi, u)[0])


def test_planner_adds_phi_bins_until_the_blend_holds():
    """plan_tables' phi_count "auto": for a 1:25 GGX (its cap turns with phi_i at grazing) at
    16^2 cells, 8, 16 and 32 azimuths over pi lose more than tol / 2 half-way between bins at
    theta_i 80 or 86 (over twice the rv on the bins), 64 lose the least and are the most it
    takes: 64 + the closing bin, every theta bin at all of them. (Measured 0.27, 0.10, 0.061,
    0.0084; with one exponential per cell 0.25, 0.084, 0.038, <= 0.002: profiles lowered the rv
    on the bins more than half-way, 2-3x below the exponentials' there, at 80 and 86 deg.)"""
    from bake.core.planner import plan_tables
    from bake.materials import open_material
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha_x": 0.02, "alpha_y": 0.5})
    lines = []
    settings = BakeSettings(resolution=16, grid=64, samples=1 << 12, first_bins=2, tol=0.004, memory_budget=1 << 16)
    tab = plan_tables(mat, IdealSampler(mat, resolution=64), settings, log=lines.append)
    losses = [float(line.rsplit(" ", 1)[1]) for line in lines if line.startswith("phi bins")]
    assert len(losses) == 4 and min(losses[:3]) > 0.002 and losses[3] < 0.5 * min(losses[:3]), lines
    assert tab.coords == "halfvector" and len(tab.phi_bins) == 65 and tab.mass.shape[1] == 65
