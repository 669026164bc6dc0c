"""The C fast path of Tables (bake/maths/_tables_c.c via bake/maths/fasttables.py) against the numpy
reference: same samples, pdfs, inverses and BSDF values to 1e-10, and a silent numpy
fallback when the library is disabled or missing."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bake.maths import fasttables
from bake.errors import FlowBSDFError
from bake.maths.geometry import incident, spherical_dir
from bake.core.ideal import IdealSampler
from bake.materials import open_material
from bake.core.table_files import open_tables
from bake.core.tables import Tables, from_ab
from bake.core.tabulate import build_tables

ROOT = Path(__file__).resolve().parents[1]
needs_c = pytest.mark.skipif(not fasttables.AVAILABLE, reason=f"C tables library unavailable: {fasttables.REASON}")

MATERIALS = {
    "ggx": {"kind": "analytic", "model": "ggx", "alpha": 0.05},
    "plastic": {"kind": "analytic", "model": "plastic", "albedo": [0.6, 0.2, 0.1], "alpha": 0.2},
}
# name -> (material, bins in degrees, rows, cols, coords): odd sizes exercise the bisection; one
# bin exercises K == 1.
CASES = {
    "ggx-5bins": ("ggx", [0.0, 30.0, 60.0, 80.0, 89.0], 16, 16, "wo"),
    "ggx-odd": ("ggx", [0.0, 45.0, 85.0], 13, 21, "wo"),
    "plastic-1bin": ("plastic", [40.0], 12, 9, "wo"),
    "ggx-polar": ("ggx", [0.0, 30.0, 60.0, 80.0, 89.0], 16, 16, "halfpolar"),
    "plastic-polar-odd": ("plastic", [0.0, 45.0, 85.0], 13, 21, "halfpolar"),
}
# The cell searches next to edges place wo by the "wo" map (from_ab) a relative 1e-9 off an edge;
# over the half vector the maps' conditioning (~1 / (wi.h)) is larger than that.
WO_CASES = sorted(name for name, case in CASES.items() if case[4] == "wo")


@pytest.fixture(scope="module")
def tables():
    out = {}
    for name, (mat_name, bins, rows, cols, coords) in CASES.items():
        mat = open_material(MATERIALS[mat_name])
        out[name] = build_tables(mat, IdealSampler(mat, resolution=64), np.radians(bins), rows=rows, cols=cols,
                                 grid=96, coords=coords)
        assert out[name].coords == coords
    return out


def reference(tab):
    """The same tables on the numpy path only."""
    return Tables(tab.theta_bins, tab.a_edges, tab.b_edges, tab.mass, tab.alpha, tab.beta, tab.weights,
                  backend="numpy", coords=tab.coords)


def fast(name, tab, *args):
    out = getattr(fasttables, name)(tab, *args)
    assert out is not None, f"the C path declined {name}"
    return out


def sphere(rng, n):
    """Uniform directions on the whole sphere: half of them below the horizon."""
    z = rng.uniform(-1.0, 1.0, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


SPECIAL_WO = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0],
                       [-0.6, 0.0, 0.8], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [1e-9, -1e-9, 1.0]])


def single_wis(rng, tab):
    """Incident directions (3,): on the pole, on and between the bins, near grazing, random azimuths."""
    bins = np.degrees(tab.theta_bins)
    thetas = [0.0, 89.9, 90.0, *bins, *((bins[:-1] + bins[1:]) / 2), *rng.uniform(0.0, 90.0, 3)]
    return [np.array([0.0, 0.0, 1.0])] + [incident(t, rng.uniform(-np.pi, np.pi)) for t in thetas]


def check_all(tab, ref, wi, u, wos):
    """C against numpy: 1e-10 over wo; over the half vector (halfpolar) the map's conditioning
    (~1 / (wi.h)) lifts libm's last-bit differences from numpy's, as on the anisotropic tables
    (measured: 1.7e-9 on pdf() of random wo)."""
    over_wo = tab.coords == "wo"
    tol = 1e-10 if over_wo else 1e-7
    wo_c, pdf_c = fast("sample", tab, wi, u)
    wo_r, pdf_r = ref.sample(wi, u)
    np.testing.assert_allclose(wo_c, wo_r, rtol=0, atol=1e-10 if over_wo else 1e-9)
    np.testing.assert_allclose(pdf_c, pdf_r, rtol=1e-10 if over_wo else 1e-9, atol=0)
    for wo in (wo_r, *wos):
        np.testing.assert_allclose(fast("pdf", tab, wi, wo), ref.pdf(wi, wo), rtol=tol, atol=0)
        np.testing.assert_allclose(fast("invert", tab, wi, wo), ref.invert(wi, wo), rtol=tol,
                                   atol=1e-12 if over_wo else 1e-11)
        np.testing.assert_allclose(fast("eval", tab, wi, wo), ref.eval(wi, wo), rtol=tol, atol=0)


@needs_c
@pytest.mark.parametrize("name", sorted(CASES))
def test_c_matches_numpy_at_one_wi(tables, name):
    tab = tables[name]
    ref = reference(tab)
    rng = np.random.default_rng(7)
    for wi in single_wis(rng, tab):
        n = 4000        # > rows * cols: the C code precomputes this wi's table ("flat" mode)
        check_all(tab, ref, wi, rng.random((n, 2)), [sphere(rng, n), SPECIAL_WO])


@needs_c
@pytest.mark.parametrize("name", sorted(CASES))
def test_c_matches_numpy_per_sample_wi(tables, name):
    tab = tables[name]
    ref = reference(tab)
    rng = np.random.default_rng(8)
    n = 20000
    theta = np.radians(rng.uniform(0.0, 90.0, n))
    theta[:8] = np.radians([0.0, 89.9, 90.0, 95.0, *np.degrees(tab.theta_bins[:1]), 0.0, 60.0, 30.0])
    wi = spherical_dir(theta, rng.uniform(-np.pi, np.pi, n))   # a few below the horizon
    wo_special = SPECIAL_WO[np.arange(n) % len(SPECIAL_WO)]
    check_all(tab, ref, wi, rng.random((n, 2)), [sphere(rng, n), wo_special])


def near_edges(ref, rng, wi, rel=1e-9):
    """Per wi, a wo a relative 1e-9 to either side of a row edge of its interpolated table
    and of a column edge of that row: the first and last column's ends (b = 0 and 2 pi,
    which wraps) and the last row's (a = 1) among them. 1e-9 is far above the few ulps by
    which libm's and numpy's angles differ: the cell is unambiguous."""
    n, R, C = len(wi), ref.rows, ref.cols
    bins, phi_ref = ref._bins(wi)
    side = lambda: rng.choice([-1.0, 1.0], n)    # noqa: E731
    i = rng.integers(0, R + 1, n)
    a = np.clip(Tables._lerp(ref._a, bins, i) + rel * side(), rel, 1.0 - rel)
    j = rng.integers(0, C + 1, n)
    j[::5], j[1::5] = C, 0
    b = Tables._lerp(ref._b, bins, np.minimum(i, R - 1), j) + rel * side()
    return from_ab(a, b, phi_ref)


@needs_c
@pytest.mark.parametrize("name", WO_CASES)
def test_c_finds_numpys_cell_next_to_cell_and_bin_edges(tables, name):
    """The C searches (theta bin, row, column) land in numpy's cell where it is closest to
    ambiguous: wo next to the cell edges of each wi's table, wi on the theta bins and
    between, a new wi per sample and one wi per call. A neighbouring cell has another
    density, so a wrong cell shows in pdf and eval."""
    tab = tables[name]
    ref = reference(tab)
    rng = np.random.default_rng(13)
    n = 20000
    theta = rng.uniform(0.0, 0.5 * np.pi, n)
    theta[::3] = rng.choice(tab.theta_bins, len(theta[::3]))
    wi = spherical_dir(theta, rng.uniform(-np.pi, np.pi, n))
    wo = near_edges(ref, rng, wi)
    np.testing.assert_allclose(fast("pdf", tab, wi, wo), ref.pdf(wi, wo), rtol=1e-10, atol=0)
    np.testing.assert_allclose(fast("eval", tab, wi, wo), ref.eval(wi, wo), rtol=1e-10, atol=0)
    for wi1 in wi[:3]:      # one wi per call (flat mode), on a bin and not
        wo1 = near_edges(ref, rng, np.tile(wi1, (4000, 1)))
        np.testing.assert_allclose(fast("pdf", tab, wi1, wo1), ref.pdf(wi1, wo1), rtol=1e-10, atol=0)


@needs_c
@pytest.mark.parametrize("name", WO_CASES)
def test_c_breaks_ties_on_row_edges_as_numpy(tables, name):
    """wo exactly on a row edge, a = edge(i), belongs to row i (edge(i) <= a < edge(i + 1)).
    At the pole wi (theta, phi, cos theta exact in numpy and libm alike, so the same
    interpolated edges) C and numpy compute the same a from wo, tie included."""
    tab = tables[name]
    ref = reference(tab)
    rng = np.random.default_rng(14)
    n = 5000
    wi = np.tile([0.0, 0.0, 1.0], (n, 1))
    bins, phi_ref = ref._bins(wi)
    i = rng.integers(1, tab.rows, n)
    a = Tables._lerp(ref._a, bins, i)
    b = Tables._lerp(ref._b, bins, i, rng.integers(0, tab.cols, n)) + 1e-6    # inside a column
    wo = from_ab(a, b, phi_ref)
    _, a_back = ref._bins(wi)[1], (wo[:, 0] ** 2 + wo[:, 1] ** 2) / (1.0 + wo[:, 2])
    assert np.mean(a_back == a) > 0.2, "the round trip should hit the edges exactly often"
    for w in (wi, wi[0]):       # a new wi per sample, and one wi per call
        np.testing.assert_allclose(fast("pdf", tab, w, wo), ref.pdf(w, wo), rtol=1e-10, atol=0)


@needs_c
@pytest.mark.parametrize("name", ["ggx-5bins", "ggx-polar"])
def test_flat_and_interpolated_modes_agree_bit_for_bit(tables, name):
    """One wi with many samples (table precomputed once) or few (interpolated per sample):
    the same arithmetic, so the same bits."""
    tab = tables[name]
    rng = np.random.default_rng(9)
    wi = incident(51.0, 0.7)
    u = rng.random((3000, 2))
    wo = sphere(rng, 3000)
    small = 100     # < rows * cols
    for name, x in (("sample", u), ("pdf", wo), ("invert", wo), ("eval", wo)):
        whole = fast(name, tab, wi, x)
        parts = [fast(name, tab, wi, x[i:i + small]) for i in range(0, len(x), small)]
        if name == "sample":
            assert np.array_equal(whole[0], np.concatenate([p[0] for p in parts]))
            assert np.array_equal(whole[1], np.concatenate([p[1] for p in parts]))
        else:
            assert np.array_equal(whole, np.concatenate(parts), equal_nan=True)


@needs_c
@pytest.mark.parametrize("name", ["ggx-5bins", "ggx-polar"])
def test_a_sample_does_not_depend_on_its_place_in_a_call(tables, name):
    """Blocks of 16 run in vector lanes; the last, partial block is padded. Each sample alone
    (padded) and inside a call of 37 (two full blocks and a partial one) gives the same bits."""
    tab = tables[name]
    rng = np.random.default_rng(12)
    n = 37
    wi = spherical_dir(np.radians(rng.uniform(0.0, 89.0, n)), rng.uniform(-np.pi, np.pi, n))
    u, wo = rng.random((n, 2)), sphere(rng, n)
    for name, x in (("sample", u), ("pdf", wo), ("invert", wo), ("eval", wo)):
        whole = fast(name, tab, wi, x)
        alone = [fast(name, tab, wi[i:i + 1], x[i:i + 1]) for i in range(n)]
        if name == "sample":
            assert np.array_equal(whole[0], np.concatenate([a[0] for a in alone]))
            assert np.array_equal(whole[1], np.concatenate([a[1] for a in alone]))
        else:
            assert np.array_equal(whole, np.concatenate(alone), equal_nan=True)


GROUP_PER_BIN = 1000    # _tables_c.c: from this many samples per bin a call with a new wi per sample runs grouped
GROUP_MAX = 1 << 18     # and in slices of this many samples


def assert_same_bits(name, got, expect):
    if name == "sample":
        assert np.array_equal(got[0], expect[0]) and np.array_equal(got[1], expect[1])
    else:
        assert np.array_equal(got, expect, equal_nan=True)


def grouped_matches_small_calls(tab, rng, n):
    """A call of n samples, a new wi each (on the whole sphere: some below the horizon), against
    the same samples in calls of 1000 (too few per bin to be grouped): the same bits, in order."""
    wi, u, wo = sphere(rng, n), rng.random((n, 2)), sphere(rng, n)
    wi[::2, 2] = np.abs(wi[::2, 2])
    small = 1000
    for name, x in (("sample", u), ("pdf", wo), ("invert", wo), ("eval", wo)):
        parts = [fast(name, tab, wi[i:i + small], x[i:i + small]) for i in range(0, n, small)]
        expect = (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])) \
            if name == "sample" else np.concatenate(parts)
        assert_same_bits(name, fast(name, tab, wi, x), expect)


@needs_c
@pytest.mark.parametrize("name, n", [("ggx-5bins", 3 * GROUP_PER_BIN * 5 + 37),      # 5 bins
                                     ("ggx-polar", 3 * GROUP_PER_BIN * 5 + 37), ("plastic-1bin", GROUP_MAX + 37)])
def test_grouped_samples_keep_their_bits_and_order(tables, name, n):
    """With a new wi per sample and many samples per bin, the C code runs them grouped by their
    wi's elevation (copies in that order, results copied back, in slices of GROUP_MAX: _tables_c.c
    "Grouping"): each sample gets the bits it gets in a call too small to be grouped, in the
    callers' order."""
    grouped_matches_small_calls(tables[name], np.random.default_rng(13), n)


@needs_c
def test_mixed_tables_in_c_give_each_sample_its_parts_values(tables):
    """MixedTables in one C call (each sample's part picked and the samples grouped by part in C,
    no numpy passes): each sample gets its part's C values bit for bit (the part picked as
    MixedTables.part_at picks it, wi near the boundary too), numpy's MixedTables' to its
    tolerance; one wi per call goes to its part; a grouped call keeps the bits of small ones."""
    from bake.maths.geometry import theta_phi
    from bake.core.mixed_tables import MixedTables
    five, odd = tables["ggx-5bins"], tables["ggx-odd"]      # 16 x 16 cells, and 13 x 21
    lower = Tables(five.theta_bins[:3], five.a_edges[:3], five.b_edges[:3], five.mass[:3], five.alpha[:3],
                   five.beta[:3], five.weights[:3])        # bins 0, 30, 60
    upper = Tables([five.theta_bins[2], np.radians(75.0), np.radians(89.0)], odd.a_edges, odd.b_edges, odd.mass,
                   odd.alpha, odd.beta, odd.weights)
    mixed = MixedTables([lower, upper])
    ref = MixedTables([reference(lower), reference(upper)], backend="numpy")
    assert mixed._fast is not None and ref._fast is None
    rng = np.random.default_rng(14)
    n = 6000
    theta = np.radians(rng.uniform(0.0, 95.0, n))
    theta[:200] = five.theta_bins[2] + np.radians(1e-6) * rng.choice([-1.0, 1.0], 200)    # at the boundary
    wi = spherical_dir(theta, rng.uniform(-np.pi, np.pi, n))
    part = mixed.part_at(theta_phi(wi)[0])
    assert 0 < np.sum(part == 1) < n
    u, wo = rng.random((n, 2)), sphere(rng, n)
    for name, x in (("sample", u), ("pdf", wo), ("invert", wo), ("eval", wo)):
        got = fast(name, mixed, wi, x)
        got = got if name == "sample" else (got,)
        for p in (0, 1):
            sel = part == p
            own = fast(name, mixed.parts[p], wi[sel], x[sel])
            for g, o in zip(got, own if name == "sample" else (own,)):
                assert np.array_equal(g[sel], o, equal_nan=True), (name, p)
        expect = getattr(ref, name)(wi, x)
        for g, e in zip(got, expect if name == "sample" else (expect,)):
            np.testing.assert_allclose(g, e, rtol=1e-10, atol=1e-10)
        for k in (0, 1, 5000):          # one wi for all
            assert_same_bits(name, fast(name, mixed, wi[k], x), fast(name, mixed.parts[part[k]], wi[k], x))
    assert_same_bits("sample", mixed.sample(wi, u), fast("sample", mixed, wi, u))      # the method runs in C
    grouped_matches_small_calls(mixed, rng, 2 * GROUP_PER_BIN * len(mixed.theta_bins) + 37)


@needs_c
def test_tables_methods_dispatch_to_c(tables):
    tab = tables["ggx-odd"]
    rng = np.random.default_rng(10)
    wi, u = incident(33.0), rng.random((500, 2))
    wo, pdf = tab.sample(wi, u)
    c_wo, c_pdf = fast("sample", tab, wi, u)
    assert np.array_equal(wo, c_wo) and np.array_equal(pdf, c_pdf)
    # shapes as numpy returns them, for one direction too
    assert tab.sample(wi, [0.3, 0.6])[0].shape == (1, 3)
    assert tab.pdf(wi, wo[0]).shape == (1,) and tab.invert(wi, wo[0]).shape == (1, 2)
    assert tab.eval(wi, wo[:5]).shape == (5, 3)
    # inputs the C path cannot take (wi rows that do not match) go to numpy, which raises as before
    with pytest.raises(ValueError):
        tab.pdf(np.tile(wi, (3, 1)), wo[:5])


def test_numpy_fallback_when_the_library_is_disabled(tables, monkeypatch):
    tab = tables["ggx-5bins"]
    ref = reference(tab)
    rng = np.random.default_rng(11)
    wi, u = incident(41.0, 0.2), rng.random((300, 2))
    monkeypatch.setattr(fasttables, "AVAILABLE", False)
    monkeypatch.setattr(fasttables, "_lib", None)
    wo, pdf = tab.sample(wi, u)
    wo_r, pdf_r = ref.sample(wi, u)
    assert np.array_equal(wo, wo_r) and np.array_equal(pdf, pdf_r)
    assert np.array_equal(tab.pdf(wi, wo), ref.pdf(wi, wo))
    assert np.array_equal(tab.eval(wi, wo), ref.eval(wi, wo))
    assert fasttables.sample(tab, wi, u) is None
    with pytest.raises(FlowBSDFError, match="not available"):
        Tables(tab.theta_bins, tab.a_edges, tab.b_edges, tab.mass, tab.alpha, tab.beta, tab.weights,
               backend="c").sample(wi, u)


def test_env_var_disables_the_library():
    """FLOWBSDF_NO_C=1: bake imports, says why in one line, and the tables sample with numpy."""
    code = ("import numpy as np; from bake.maths import fasttables as f; from bake.core.tables import Tables; "
            "t = Tables([0.0], [[0, 0.5, 1]], [[[0, 3, 6.3], [0, 3, 6.3]]], np.ones((1, 2, 2)), "
            "np.zeros((1, 2, 2, 3)), np.zeros((1, 2, 2, 3)), np.ones((1, 2, 2, 3))); "
            "wo, p = t.sample([0, 0, 1], np.random.default_rng(0).random((10, 2))); "
            "print(f.AVAILABLE, '|', f.REASON, '|', bool(np.all(p > 0)))")
    env = {**os.environ, "FLOWBSDF_NO_C": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    available, reason, ok = (s.strip() for s in out.stdout.split("|"))
    assert available == "False" and "FLOWBSDF_NO_C" in reason and ok == "True"


@needs_c
def test_stale_library_is_rejected_and_a_fresh_one_compiles(tmp_path):
    import shutil
    if not (shutil.which("cc") or shutil.which("gcc")):
        pytest.skip("no C compiler")
    sha = fasttables.source_sha()
    path = fasttables.compile_library(sha, tmp_path)
    assert fasttables._open(path, sha) is not None
    with pytest.raises(OSError, match="stale"):
        fasttables._open(path, "0" * 64)


def test_one_blas_thread_sets_openblas_to_one_thread_and_restores_it():
    """The baker runs BLAS in one thread (fasttables.one_blas_thread), nested or not, and gives
    the caller's thread count back; the products' bits do not change."""
    x = np.random.default_rng(3).normal(size=(200_000, 3))
    v = np.array([0.2, 0.7, 0.1])
    before = x @ v
    with fasttables.one_blas_thread():
        found = fasttables._blas[0]
        inside = found[0]() if found else None
        with fasttables.one_blas_thread():
            np.testing.assert_array_equal(x @ v, before)
        still = found[0]() if found else None
    if found is None:
        pytest.skip("numpy's BLAS is not an OpenBLAS found here")
    assert inside == 1 and still == 1
    assert fasttables._blas_users[0] == 0 and found[0]() == fasttables._blas_users[1]


@pytest.fixture(scope="module")
def brushed(tmp_path_factory):
    """Small anisotropic tables over the half vector (cycles_scenes.aniso_small_tables)."""
    import cycles_scenes
    return open_tables(cycles_scenes.aniso_small_tables(tmp_path_factory.mktemp("brushed")))


@needs_c
def test_c_matches_numpy_on_anisotropic_halfvector_tables(brushed):
    """The four-bin blend over theta_i x phi_i and the half vector's map, in C: numpy's results
    at one wi per call and at a new wi per sample (across the period's turns, on and between
    bins, below the horizon). rtol 1e-6: the map's conditioning (~1 / (wi.h)) lifts libm's
    last-bit differences from numpy's, the more so toward grazing wi, and a cell's profile turns
    a point's place in its cell into pdf by its slope (measured: 4e-11 on samples, up to 5e-7 on
    pdf() of random wo, at 1 of 4000; 4.4e-9 with one exponential per cell)."""
    tab = brushed
    ref = Tables(tab.theta_bins, tab.a_edges, tab.b_edges, tab.mass, tab.alpha, tab.beta, tab.weights,
                 backend="numpy", phi_bins=tab.phi_bins, phi_period=tab.phi_period, coords=tab.coords,
                 frame_angle=tab.frame_angle)
    assert tab._fast is not None and ref._fast is None
    rng = np.random.default_rng(7)
    n = 4000
    many = sphere(rng, n)
    many[:, 2] = np.abs(many[:, 2])
    for wi in single_wis(rng, tab) + [many]:
        u = rng.random((n, 2))
        wo_c, pdf_c = fast("sample", tab, wi, u)
        wo_r, pdf_r = ref.sample(wi, u)
        np.testing.assert_allclose(wo_c, wo_r, rtol=0, atol=1e-9)
        np.testing.assert_allclose(pdf_c, pdf_r, rtol=1e-9, atol=0)
        for wo in (wo_r, sphere(rng, n), SPECIAL_WO):
            wi_ = wi if np.ndim(wi) == 1 else wi[:len(wo)]
            np.testing.assert_allclose(fast("pdf", tab, wi_, wo), ref.pdf(wi_, wo), rtol=1e-6, atol=0)
            np.testing.assert_allclose(fast("invert", tab, wi_, wo), ref.invert(wi_, wo), rtol=1e-7, atol=1e-11)
            np.testing.assert_allclose(fast("eval", tab, wi_, wo), ref.eval(wi_, wo), rtol=1e-6, atol=0)


@needs_c
def test_grouped_samples_on_anisotropic_tables_keep_their_bits(brushed):
    """Grouped by elevation alone, anisotropic tables' samples (four bins each, over theta_i x phi_i)
    keep the bits of ungrouped calls too."""
    grouped_matches_small_calls(brushed, np.random.default_rng(15), GROUP_PER_BIN * len(brushed._a) + 37)


@needs_c
@pytest.mark.parametrize("horizon", [False, True])
def test_warped_coords_in_c_match_numpy(horizon, tmp_path):
    """rgl.WarpedCoords' to_s and from_s in C (ft_warp_to_s / ft_warp_from_s) against the numpy
    reference on a synthetic RGL file with a row of empty patches: the same s, directions and Jacobians to
    1e-9, the same unreached s and infinite Jacobians, at five incident angles and with an incident
    direction per sample."""
    from bake.materials.rgl import RGLMaterial, WarpedCoords, write_tensor_file
    from test_rgl import synthetic_fields
    f = synthetic_fields(n_vndf=16, n_rgb=8)
    f["vndf"][0, :, 4:6, :] = 0.0          # a patch row of no density
    mat = RGLMaterial(write_tensor_file(tmp_path / "w.bsdf", f))
    rng = np.random.default_rng(3)
    for theta in np.radians([0.0, 25.0, 60.0, 85.0, 89.9]):
        wi = spherical_dir(theta, 0.9)
        ref = WarpedCoords(mat, horizon=horizon, stored=True, backend="numpy")
        c = WarpedCoords(mat, horizon=horizon, stored=True)
        wo = spherical_dir(np.arccos(rng.uniform(0.0, 1.0, 4000)), rng.uniform(-np.pi, np.pi, 4000))
        s_ref, jac_ref = ref.to_s(wi, wo)
        s_c, jac_c = fasttables.warp_to_s(c, wi, wo)
        np.testing.assert_allclose(s_c, s_ref, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.isfinite(jac_c), np.isfinite(jac_ref))
        assert not np.isfinite(jac_ref).all()       # the zero row is hit
        fin = np.isfinite(jac_ref)
        np.testing.assert_allclose(jac_c[fin], jac_ref[fin], rtol=1e-9)
        s = np.concatenate([rng.random((4000, 2)), [[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]]])
        wo_ref, jac_ref = ref.from_s(wi, s)
        wo_c, jac_c = fasttables.warp_from_s(c, wi, s)
        np.testing.assert_allclose(wo_c, wo_ref, rtol=0, atol=1e-9)
        rim = np.abs(wo_ref[:, 2]) < 1e-12      # s_x = 1 with `horizon`: on the horizon, reached or not by rounding
        assert rim.sum() <= (2 if horizon else 0)
        np.testing.assert_allclose(jac_c[~rim], jac_ref[~rim], rtol=1e-9, atol=0)
        np.testing.assert_array_equal(jac_c[~rim] > 0, jac_ref[~rim] > 0)
    # an incident direction per sample (each its own slices), as a renderer asks
    wi = spherical_dir(np.radians(rng.uniform(0.0, 89.9, 4000)), rng.uniform(-np.pi, np.pi, 4000))
    wo = spherical_dir(np.arccos(rng.uniform(0.0, 1.0, 4000)), rng.uniform(-np.pi, np.pi, 4000))
    (s_ref, jac_ref), (s_c, jac_c) = ref.to_s(wi, wo), fasttables.warp_to_s(c, wi, wo)
    fin = np.isfinite(jac_ref)
    np.testing.assert_allclose(s_c, s_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jac_c[fin], jac_ref[fin], rtol=1e-9)
    (wo_ref, jac_ref), (wo_c, jac_c) = ref.from_s(wi, s_ref), fasttables.warp_from_s(c, wi, s_ref)
    reached = jac_ref > 0        # (s of the empty rows reach nothing: where, is a tie of equal CDF values)
    assert reached.mean() > 0.9
    np.testing.assert_array_equal(jac_c > 0, reached)
    np.testing.assert_allclose(wo_c[reached], wo_ref[reached], rtol=0, atol=1e-9)
    np.testing.assert_allclose(jac_c, jac_ref, rtol=1e-9, atol=1e-300)


def test_polar_grid_nodes_in_c_are_the_numpy_ones(monkeypatch):
    """halfvector.polar_grid_from_ab (the baker's halfpolar quadrature nodes) in C gives numpy's
    nodes and Jacobians byte for byte, at normal, oblique and grazing incidence, in the frame the
    baker turns by (pi) and another."""
    from bake.core import halfvector
    from bake.maths import fasttables
    if not fasttables.AVAILABLE:
        pytest.skip(fasttables.REASON)
    rng = np.random.default_rng(4)
    cells, qa, qb = 300, 8, 6
    a0 = rng.random(cells) * 0.95
    b0 = rng.random(cells) * 6.0
    s_a, s_b = (np.arange(qa) + 0.5) / qa, (np.arange(qb) + 0.5) / qb
    a = a0[:, None] + s_a[None, :] * (0.05 * rng.random(cells))[:, None]
    b = b0[:, None] + s_b[None, :] * (0.28 * rng.random(cells))[:, None]
    a[0, 0], a[1, :] = 0.0, 1.0            # the centre and the rim
    for theta in (0.0, 1.0, 1.569):
        wi = np.array([np.sin(theta), 0.0, np.cos(theta)])
        for frame in (np.pi, 0.7):
            fast = halfvector.polar_grid_from_ab(wi, a, b, frame)
            with monkeypatch.context() as m:
                m.setattr(fasttables, "polar_grid", lambda *args: None)
                slow = halfvector.polar_grid_from_ab(wi, a, b, frame)
            assert fast[0].tobytes() == slow[0].tobytes() and fast[1].tobytes() == slow[1].tobytes()
