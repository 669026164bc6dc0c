import numpy as np

from bake.maths.geometry import incident, luminance, spherical_dir
from bake.core.ideal import IdealSampler, training_pairs
from bake.core.domains import Disk
from bake.materials import open_material
from bake.core.metrics import relative_variance
from contract import assert_sampler_contract


def test_lambert_albedo_and_sampling():
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": [0.2, 0.5, 0.8]})
    ideal = IdealSampler(mat, resolution=64)
    for theta in (0, 45, 85):
        np.testing.assert_allclose(ideal.albedo(incident(theta)), [0.2, 0.5, 0.8], rtol=1e-3)
        rv, estimate = relative_variance(mat, ideal, incident(theta), n=50000)
        assert rv < 0.01
        assert abs(estimate - luminance([0.2, 0.5, 0.8])) < 0.01


def test_sample_and_pdf_agree_for_a_sharp_lobe():
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.01})
    ideal = IdealSampler(mat)
    rng = np.random.default_rng(0)
    for theta, phi in [(0, 0), (30, 1.0), (80, -2.5), (89, 3.1)]:
        wi = incident(theta, phi)
        assert_sampler_contract(ideal, wi, rng.random((20000, 2)), pdf_rtol=1e-8, max_lost=0.001, where=theta)
        rv, _ = relative_variance(mat, ideal, wi, n=50000)
        assert rv < 0.01, (theta, rv)


def test_isotropic_materials_share_one_table_per_elevation():
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.2})
    ideal = IdealSampler(mat, resolution=32)
    u = np.random.default_rng(0).random((100, 2))
    wo_a, pdf_a = ideal.sample(incident(40, 0.0), u)
    wo_b, pdf_b = ideal.sample(incident(40, 2.0), u)
    assert len(ideal._tables) == 1
    np.testing.assert_allclose(pdf_a, pdf_b)
    c, s = np.cos(2.0), np.sin(2.0)
    np.testing.assert_allclose(wo_b[:, 0], c * wo_a[:, 0] - s * wo_a[:, 1], atol=1e-12)


def test_black_material_has_no_samples():
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.0})
    ideal = IdealSampler(mat, resolution=16)
    wo, pdf = ideal.sample(incident(30), np.full((10, 2), 0.5))
    assert np.all(pdf == 0) and np.all(wo[:, 2] <= 0)
    assert np.all(ideal.pdf(incident(30), np.array([[0, 0, 1.0]])) == 0)


def test_training_pairs_follow_the_target():
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.5})
    rng = np.random.default_rng(3)
    wi, x = training_pairs(mat, Disk(), 40000, rng, np.radians([10, 50]))
    assert wi.shape == (40000, 3) and x.shape == (40000, 2)
    assert set(np.round(np.degrees(np.arccos(wi[:, 2])), 6)) == {10.0, 50.0}
    # Cosine-distributed directions are uniform on the projected disk: E[r²] = 1/2.
    assert abs(np.mean(np.sum(x * x, axis=1)) - 0.5) < 0.01


def test_tables_share_their_sub_cell_grid_and_stay_the_same():
    """ideal._sub_cells (the u grid and its half vectors, shared by every wi's Table) is
    read-only, and a Table built after others is the one built first."""
    from bake.core.ideal import Table, _sub_cells
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.2})
    wi = spherical_dir(np.radians(40.0), 0.0)
    first = Table(mat, wi, 32, 2)
    Table(mat, spherical_dir(np.radians(70.0), 0.0), 32, 2)
    again = Table(mat, wi, 32, 2)
    np.testing.assert_array_equal(first.density, again.density)
    np.testing.assert_array_equal(first.albedo_rgb, again.albedo_rgb)
    u, m, sin_m = _sub_cells(32, 64, 2, 0, 32)
    assert not u.flags.writeable and not m.flags.writeable and not sin_m.flags.writeable


def test_table_is_reflect_and_dwo_du_averaged_over_sub_cells_bit_for_bit():
    """Table computes wi.m once for reflect and dwo_du and averages the sub-cells' RGB in whole
    slices, and samples with the dot products written out: the same numbers as the plain formulas
    (geometry.reflect and normalize, warps.dwo_du, mean over the sub-cell axes), byte for byte,
    at normal and grazing incidence."""
    from bake.maths.geometry import luminance, reflect
    from bake.core.ideal import Table, _sub_cells
    from bake.maths.warps import dwo_du
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.3})
    n1, n2, s = 16, 32, 3
    for theta in (0.0, 55.0, 88.0):
        wi = spherical_dir(np.radians(theta), 0.0)
        tab = Table(mat, wi, n1, s)
        u, m, _ = _sub_cells(n1, n2, s, 0, n1)
        wo = reflect(wi[None, :], m)
        value = mat.eval(wi, wo)
        jac = dwo_du(wi[None, :], m, u[:, 0]) * (wo[:, 2] > 0)
        cos_o = np.maximum(wo[:, 2], 0.0)
        mass = (np.maximum(luminance(value), 0.0) * cos_o * jac).reshape(n1, s, n2, s).mean(axis=(1, 3))
        rgb = (value * (cos_o * jac)[:, None]).reshape(n1, s, n2, s, 3).mean(axis=(1, 3))
        assert tab.density.tobytes() == (mass / (mass.sum() * (1.0 / (n1 * n2)))).tobytes()
        assert tab.albedo_rgb.tobytes() == (rgb.sum(axis=(0, 1)) * (1.0 / (n1 * n2))).tobytes()
        # sampling and its pdf: reflect, normalize and dwo_du as written in geometry and warps
        from bake.maths.geometry import normalize
        from bake.maths.warps import half_vector, u_of_half_vector
        w, pdf = tab.sample_dir(np.random.default_rng(1).random((5000, 2)))
        m = half_vector(tab.sample_u(np.random.default_rng(1).random((5000, 2))))
        assert w.tobytes() == reflect(wi[None, :], m).tobytes()
        h = normalize(wi[None, :] + w)
        v = u_of_half_vector(h)
        jac = dwo_du(wi[None, :], h, v[:, 0])
        with np.errstate(divide="ignore", invalid="ignore"):
            want = np.where((w[:, 2] > 0) & (jac > 0), tab.density_u(v) / jac, 0.0)
        assert pdf.tobytes() == want.tobytes()


def test_ideal_pdf_has_the_same_bits_in_every_thread():
    """The baker samples the ideal from a thread pool and its tables must not depend on which
    thread ran a bin: pdf (theta_phi of half vectors near the pole) from four threads equals the
    main thread's, bit for bit (it did not with numpy's arctan2 on strided views: 1 ulp apart in
    about a third of the threaded calls)."""
    from concurrent.futures import ThreadPoolExecutor
    from bake.core.ideal import Table
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.05})
    g = (np.arange(96) + 0.5) / 96
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    tables = [Table(mat, spherical_dir(t, 0.0), 64, 2) for t in np.radians(np.linspace(0.0, 85.0, 8))]
    serial = [tab.sample_dir(u)[1] for tab in tables]
    with ThreadPoolExecutor(4) as pool:
        for _ in range(10):
            threaded = list(pool.map(lambda tab: tab.sample_dir(u)[1], tables * 3))
            assert all(np.array_equal(a, b) for a, b in zip(threaded, serial * 3))
