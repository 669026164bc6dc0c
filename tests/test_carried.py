"""CarriedTables (bake/core/carried.py): tables of an RGL file blended along the file's own
coordinates. The sampler contract between bins (sample and pdf agree, chi-square, nothing lost),
the bins' own tables at the bins, clear refusals, and on a real file what the carry is for: a
feature that moves with theta_i faster than the bins follow."""
from dataclasses import replace

import numpy as np
import pytest

from bake.core.carried import CarriedTables
from bake.maths.geometry import spherical_dir
from bake.core.ideal import IdealSampler
from bake.core.settings import BakeSettings
from bake.core.tabulate import build_tables
from bake.errors import FlowBSDFError
from bake.materials import open_material
from bake.materials.analytic import Lambert
from bake.materials.rgl import RGLMaterial, write_tensor_file
from bake.core.metrics import ReferencePoints
from contract import assert_sampler_contract
from test_rgl import synthetic_fields


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A small synthetic RGL material and its halfpolar tables at three incident angles."""
    path = write_tensor_file(tmp_path_factory.mktemp("carried") / "s.bsdf", synthetic_fields(n_theta=5))
    mat = RGLMaterial(path)
    tables = build_tables(mat, IdealSampler(mat, resolution=64), np.radians([0.0, 40.0, 80.0]), 16, 16, grid=128,
                          coords="halfpolar")
    return mat, tables


@pytest.mark.parametrize("theta_deg, phi", [(20.0, 0.7), (63.0, -2.0), (86.0, 1.5)])
def test_carried_sampler_contract_between_bins(synthetic, theta_deg, phi):
    mat, tables = synthetic
    carried = CarriedTables(tables, mat)
    wi = spherical_dir(np.radians(theta_deg), phi)
    assert_sampler_contract(carried, wi, np.random.default_rng(1).random((20000, 2)), pdf_rtol=1e-9,
                            chi2=dict(n=200_000, n_tests=3, seed=4), where=theta_deg)


def test_carried_at_a_bin_is_the_bins_table(synthetic):
    mat, tables = synthetic
    carried = CarriedTables(tables, mat)
    wi = spherical_dir(np.radians(40.0), 0.3)
    wo, pdf = carried.sample(wi, np.random.default_rng(2).random((5000, 2)))
    np.testing.assert_allclose(pdf, tables.pdf(wi, wo), rtol=1e-9)
    # several incident directions in one call: each sample's own
    wis = spherical_dir(np.radians(np.array([10.0, 40.0, 75.0] * 100)), 0.2)
    wo = spherical_dir(np.full(300, 0.6), np.linspace(-3, 3, 300))
    one_by_one = np.concatenate([carried.pdf(w, o[None]) for w, o in zip(wis, wo)])
    np.testing.assert_allclose(carried.pdf(wis, wo), one_by_one, rtol=1e-12)


def test_carried_refuses_what_it_cannot_carry(synthetic):
    _, tables = synthetic
    with pytest.raises(FlowBSDFError, match="isotropic RGL"):
        CarriedTables(tables, Lambert(0.5))


def test_carrying_follows_a_feature_the_bins_blend_away(rgl):
    """chm_mint between bins 84.64 and 85.17 deg (48², one placement, as the planner builds
    them): f·cos there has a feature that moves with theta_i, and the fixed-cell blend loses 2.5x
    the ideal tabulation's rv half-way (measured); carried along the file's coordinates the same
    tables stay within 1.5x of it (measured 1.0x)."""
    mat = open_material(rgl("chm_mint_rgb"))
    ideal = IdealSampler(mat)
    lo, hi = np.radians([84.64, 85.17])
    tables = build_tables(mat, ideal, [lo, hi], 48, 48, coords="halfpolar", window=None)
    mid = float(np.arccos(0.5 * (np.cos(lo) + np.cos(hi))))
    draws = ReferencePoints(mat, spherical_dir(mid, 0.0), ideal, 256, 7)
    floor = draws.rv(ideal)[0]
    plain, carried = draws.rv(tables)[0] / floor, draws.rv(CarriedTables(tables, mat))[0] / floor
    assert plain > 2.0 and carried < 1.5, (plain, carried)


def test_planner_plans_for_the_carried_blend(synthetic):
    """plan_tables(blend="carried") measures its probes on carried tables and says so in the
    tables' meta; a material it cannot carry, or an unknown blend, is refused before any build."""
    from bake.core.planner import plan_tables
    mat, _ = synthetic
    ideal = IdealSampler(mat, resolution=64)
    tables = plan_tables(mat, ideal, BakeSettings(memory_budget=120_000, samples=1 << 12, first_bins=3,
                                                  resolution=16), blend="carried", coords="halfpolar", window=None)
    assert tables.meta["blend"] == "carried"
    assert_sampler_contract(CarriedTables(tables, mat), spherical_dir(np.radians(50.0), 0.2),
                            np.random.default_rng(3).random((5000, 2)), pdf_rtol=1e-9)
    with pytest.raises(FlowBSDFError, match="isotropic RGL"):
        plan_tables(Lambert(0.5), IdealSampler(Lambert(0.5)), blend="carried")
    with pytest.raises(FlowBSDFError, match="blend"):
        plan_tables(mat, ideal, blend="displaced")


def test_intervals_that_do_not_carry_are_the_fixed_cell_blend(synthetic):
    """An interval flagged not to carry samples the tables themselves (the same wo and pdf); the
    flags are one per interval (a wrong count is refused); choose_intervals gives one per interval."""
    from bake.core.carried import choose_intervals
    mat, tables = synthetic
    mixed = CarriedTables(tables, mat, carry=[False, True])
    u = np.random.default_rng(5).random((3000, 2))
    low, high = spherical_dir(np.radians(25.0), 0.4), spherical_dir(np.radians(70.0), 0.4)
    wo, pdf = mixed.sample(low, u)
    plain_wo, plain_pdf = tables.sample(low, u)
    np.testing.assert_allclose(wo, plain_wo, atol=1e-12)        # wi rebuilt from its angles: rounding
    np.testing.assert_allclose(pdf, plain_pdf, rtol=1e-9)
    assert_sampler_contract(mixed, high, u, pdf_rtol=1e-9)
    assert not np.allclose(mixed.pdf(high, wo), tables.pdf(high, wo))      # 70 deg carries
    with pytest.raises(FlowBSDFError, match="one flag per interval"):
        CarriedTables(tables, mat, carry=[True])
    flags = choose_intervals(mat, tables, IdealSampler(mat, resolution=64), side=32)
    assert len(flags) == 2 and all(isinstance(f, bool) for f in flags)


def test_carried_eval_is_the_bins_f_cos_carried(synthetic):
    """CarriedTables.eval: at a bin the bin's baked f; between bins f cos carried like the pdf, so
    over each quarter of the file's coordinates s it integrates to the bins' integrals there,
    blended with the tables' weights (5 standard errors, 2^17 samples each; eval cos / pdf finite
    wherever a sample lands)."""
    from bake.materials.rgl import WarpedCoords
    mat, tables = synthetic
    carried = CarriedTables(tables, mat)
    rng = np.random.default_rng(8)
    at_bin = spherical_dir(np.radians(40.0), 0.3)
    wo = spherical_dir(np.arccos(rng.uniform(0.01, 1.0, 3000)), rng.uniform(-np.pi, np.pi, 3000))
    np.testing.assert_allclose(carried.eval(at_bin, wo), tables.eval(at_bin, wo), rtol=1e-9, atol=1e-12)

    def per_quarter(sampler, wi):
        """The integral of f cos over each quarter of s at wi, and its standard errors."""
        wo, pdf = sampler.sample(wi, rng.random((1 << 17, 2)))
        x = sampler.eval(wi, wo).mean(axis=1) * wo[:, 2] / pdf
        assert np.isfinite(x).all()
        s = WarpedCoords(mat, horizon=True, stored=True).to_s(wi, wo)[0]
        quarter = (s[:, 0] >= 0.5) + 2 * (s[:, 1] >= 0.5)
        xq = x[:, None] * (quarter[:, None] == np.arange(4))
        return xq.mean(axis=0), xq.std(axis=0) / np.sqrt(len(x))
    theta, phi = np.radians(63.0), -2.0
    lo, hi = np.radians([40.0, 80.0])
    t = (np.cos(lo) - np.cos(theta)) / (np.cos(lo) - np.cos(hi))
    a_lo, e_lo = per_quarter(tables, spherical_dir(lo, phi))
    a_hi, e_hi = per_quarter(tables, spherical_dir(hi, phi))
    got, err = per_quarter(carried, spherical_dir(theta, phi))
    want = (1 - t) * a_lo + t * a_hi
    assert np.all(np.abs(got - want) < 5 * np.sqrt(err ** 2 + ((1 - t) * e_lo) ** 2 + (t * e_hi) ** 2)), (got, want)


def test_the_fixed_plan_carries_unless_the_warp_would_crowd_the_budget(synthetic):
    """plan_tables(settings.carry): the fixed blend's plan with a flag per interval, its budget
    less the file's warp data; a budget the warp would take over half of (a preview bake) plans
    the tables alone, saying why."""
    from bake.core.planner import plan_tables
    mat, _ = synthetic
    ideal = IdealSampler(mat, resolution=64)
    settings = BakeSettings(samples=1 << 12, first_bins=3, resolution=16, carry=True)
    opts = dict(coords="halfpolar", window=None)
    tables = plan_tables(mat, ideal, replace(settings, memory_budget=120_000), **opts)
    assert len(tables.meta["carried"]) == len(tables.theta_bins) - 1 and "blend" not in tables.meta
    assert tables.nbytes <= 120_000 - mat.warp_nbytes
    log = []
    tables = plan_tables(mat, ideal, replace(settings, memory_budget=2 * mat.warp_nbytes - 1), log=log.append, **opts)
    assert "carried" not in tables.meta and any("carried blend off" in line for line in log), log
