"""The speed-vs-error report (tables, CSV, Pareto and pdf-slice plots), the speed helper, and
Mitsuba's `measured` sampler as a peer (our conventions: pdf per steradian, lost samples
with pdf 0, eval = f without the cosine)."""
import csv
import math
import sys

import numpy as np
import pytest

from bake.materials import open_material
from bake.core.baselines import CosineSampler, fit_ggx
from bake.quality.bench import samples_per_second, single_thread_env
from bake.errors import FlowBSDFError
from bake.maths.geometry import incident, spherical_dir
from bake.core.ideal import IdealSampler
from bake.core.metrics import chi2_test, relative_variance, relative_variance_ref
from bake.quality.report import (SPEED_ERROR_FIELDS, plot_pdf_slices, plot_target, speed_error_rows,
                         summary_markdown, summary_rows, write_report)


@pytest.fixture(scope="module")
def ggx():
    material = open_material({"kind": "analytic", "model": "ggx", "alpha": 0.2})
    ideal = IdealSampler(material, resolution=64)
    samplers = {"cosine": CosineSampler(), "ideal": ideal, "ggx-fit": fit_ggx(material, ideal, n=1 << 12)}
    return material, samplers


@pytest.fixture(scope="module")
def ggx_rows(ggx):
    material, samplers = ggx
    return speed_error_rows("ggx02", material, samplers, thetas=(0, 60), n=1 << 13, speed_n=1 << 10,
                            speed_repeat=1, log=lambda *_: None)


def png_stats(path):
    import matplotlib.image as mpimg
    img = mpimg.imread(path)
    rgb = img[..., :3].reshape(-1, 3)
    return img.shape, float(rgb.std()), len(np.unique(np.round(rgb * 255).astype(int), axis=0))


def test_speed_error_rows(ggx, ggx_rows):
    material, samplers = ggx
    assert len(ggx_rows) == 6
    assert all(set(r) == set(SPEED_ERROR_FIELDS) for r in ggx_rows)
    rv = {(r["sampler"], r["theta_i"]): r["rv"] for r in ggx_rows}
    for t in (0, 60):
        assert rv[("ideal", t)] < rv[("ggx-fit", t)] < rv[("cosine", t)]
    # The same samples as metrics.relative_variance for the same seed.
    row = next(r for r in ggx_rows if r["sampler"] == "ggx-fit" and r["theta_i"] == 60)
    ref_rv, ref_albedo = relative_variance(material, samplers["ggx-fit"], incident(60), n=1 << 13, seed=0)
    assert row["rv_direct"] == pytest.approx(ref_rv, rel=1e-12)
    # rv itself is relative_variance_ref against the ideal sampler (same budget, isqrt(n)² points).
    honest, _ = relative_variance_ref(material, samplers["ggx-fit"], incident(60), samplers["ideal"], k=90)
    assert row["rv"] == pytest.approx(honest, rel=1e-12) and row["rv"] == pytest.approx(ref_rv, rel=0.3)
    assert row["albedo_mc"] == pytest.approx(ref_albedo, rel=1e-12)
    assert row["albedo_mc"] == pytest.approx(row["albedo_quadrature"], rel=0.05)
    for r in ggx_rows:
        assert 0.0 <= r["lost"] < 0.2
        assert r["sample_per_s"] > 0 and r["pdf_per_s"] > 0 and r["ns_per_sample"] > 0
        # with a new wi per sample: measured once per sampler, the same in each of its rows
        # (not for the ideal sampler: a table per distinct wi)
        if r["sampler"] == "ideal":
            assert math.isnan(r["sample_rwi_per_s"])
        else:
            assert 0 < r["both_rwi_per_s"] < min(r["sample_rwi_per_s"], r["pdf_rwi_per_s"])
        assert r["nbytes"] is None
    for name in set(samplers) - {"ideal"}:
        assert len({r["sample_rwi_per_s"] for r in ggx_rows if r["sampler"] == name}) == 1
    assert next(r for r in ggx_rows if r["sampler"] == "cosine")["lost"] == 0.0


def test_write_report_tables_and_plots(tmp_path, ggx, ggx_rows):
    pytest.importorskip("matplotlib")
    material, samplers = ggx
    rows = [dict(r) for r in ggx_rows]
    rows[0]["nbytes"] = 3 << 20          # a sampler that knows its size
    out = write_report(rows, tmp_path, slices=[("ggx02", material, samplers, 60)])
    md = out["markdown"].read_text()
    assert "| ggx02 | ideal |" in md and "median rv over all cells" in md and "3 MiB" in md
    with open(out["csv"], newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == SPEED_ERROR_FIELDS
        assert len(list(reader)) == len(rows)
    with open(out["summary_csv"], newline="") as f:
        reader = csv.DictReader(f)
        assert {"material", "sampler", "median_rv", "max_rv", "max_lost", "ns_per_sample", "nbytes"} <= set(
            reader.fieldnames)
        assert [r["sampler"] for r in reader] == ["cosine", "ideal", "ggx-fit"]
    for key in ("pareto:ggx02", "pdf:ggx02:60"):
        path = out[key]
        assert path.is_file() and path.stat().st_size > 10_000
        shape, std, colours = png_stats(path)
        assert shape[0] >= 200 and shape[1] >= 300
        assert std > 0.05 and colours > 50, (key, std, colours)


def test_pdf_slices_and_target(tmp_path, ggx):
    pytest.importorskip("matplotlib")
    material, samplers = ggx
    # No ideal sampler given: one is added (first panel after the target).
    path = plot_pdf_slices(material, {"cosine": samplers["cosine"]}, 30, tmp_path / "s.png", res=64)
    shape, std, colours = png_stats(path)
    assert shape[1] > 2.5 * shape[0] and std > 0.05 and colours > 50
    path = plot_target(material, 75, tmp_path / "t.png", res=64)
    shape, std, colours = png_stats(path)
    assert std > 0.05 and colours > 30


def test_report_without_speed(tmp_path, ggx):
    material, samplers = ggx
    rows = speed_error_rows("g", material, {"cosine": samplers["cosine"]}, thetas=(30,), n=1 << 10,
                            speed=False, quadrature=False, log=lambda *_: None)
    assert np.isnan(rows[0]["ns_per_sample"]) and np.isnan(rows[0]["albedo_quadrature"])
    out = write_report(rows, tmp_path, plots=False)
    assert out["markdown"].is_file() and "pareto:g" not in out
    assert summary_rows(rows)[0]["median_rv"] == rows[0]["rv"]


def test_samples_per_second():
    result = samples_per_second(CosineSampler(), incident(45), n=1 << 10, repeat=2)
    assert result["sample_per_s"] > 0 and result["pdf_per_s"] > 0
    assert result["ns_per_sample"] == pytest.approx(result["sample_ns"] + result["pdf_ns"])
    assert result["both_per_s"] < min(result["sample_per_s"], result["pdf_per_s"])
    assert "blas" in result["threads"]
    assert single_thread_env({})["OMP_NUM_THREADS"] == "1"


# ---------------------------------------------------------------- Mitsuba peer

def test_mitsuba_peer_errors(monkeypatch, tmp_path):
    from bake.quality import mitsuba_peer
    with pytest.raises(FlowBSDFError, match="no such RGL file"):
        mitsuba_peer.MitsubaMeasuredSampler(tmp_path / "missing.bsdf")
    monkeypatch.setitem(sys.modules, "mitsuba", None)     # import mitsuba -> ImportError
    with pytest.raises(FlowBSDFError, match="pip install mitsuba"):
        mitsuba_peer._import_mitsuba()


def test_llvm_version_names():
    from bake.quality.mitsuba_peer import _llvm_version
    assert _llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert _llvm_version("libLLVM-19.so") == 19
    assert _llvm_version("libLLVM-15.so.1") == 15
    assert _llvm_version("libLLVM-14.0.6.so.1") == 14
    assert _llvm_version("libLLVMfoo.so") is None


@pytest.fixture(scope="module")
def mint(request):
    pytest.importorskip("mitsuba")
    from conftest import rgl_path
    from bake.materials.rgl import RGLMaterial
    from bake.quality.mitsuba_peer import MitsubaMeasuredSampler
    path = rgl_path("chm_mint_rgb")
    return RGLMaterial(path), MitsubaMeasuredSampler(path)


def test_mitsuba_peer_eval_matches_rgl_convention(mint):
    material, peer = mint
    rng = np.random.default_rng(3)
    wi = spherical_dir(np.radians(rng.uniform(0, 85, 300)), rng.uniform(-np.pi, np.pi, 300))
    wi[:30] = [0.0, 0.0, 1.0]      # exactly normal incidence (Mitsuba's LLVM variant needs a nudge)
    wo = spherical_dir(np.arccos(rng.uniform(0.05, 1, 300)), rng.uniform(-np.pi, np.pi, 300))
    ref = material.eval(wi, wo)
    ours = peer.eval(wi, wo)
    assert np.max(np.abs(ours - ref)) <= 1e-4 * np.abs(ref).max()
    assert np.all(peer.eval(wi, wo * [1, 1, -1]) == 0) and np.all(peer.pdf(wi, wo * [1, 1, -1]) == 0)


@pytest.mark.parametrize("theta", [0, 60])
def test_mitsuba_peer_sample_agrees_with_pdf(mint, theta):
    material, peer = mint
    wi = incident(theta)
    n = 1 << 16 if peer.vectorized else 1 << 10
    wo, pdf = peer.sample(wi, np.random.default_rng(theta).random((n, 2)))
    valid = pdf > 0
    assert np.all(wo[valid, 2] > 0) and 0.0 < 1.0 - valid.mean() < 0.2   # Mitsuba loses a few %
    # Float32 inside Mitsuba: near the mirror direction (half vector at the pole of the
    # sqrt-theta map) rounding moves pdf() by up to ~0.3 %.
    rel = np.abs(peer.pdf(wi, wo[valid]) / pdf[valid] - 1.0)
    assert np.quantile(rel, 0.999) < 1e-3 and rel.max() < 1e-2
    rv, albedo = relative_variance(material, peer, wi, n=n, seed=1)
    assert rv < 1.0 and albedo > 0
    if not peer.vectorized:
        pytest.skip("scalar Mitsuba variant: the chi-square test needs the LLVM variant (libLLVM >= 19)")
    result = chi2_test(peer, wi, n=1 << 18, res=(24, 24))
    assert result.passed, result
    # pdf() integrates to the fraction of samples sample() keeps (<= 1).
    integral = result.expected.sum() / (1 << 18)
    lost = 1.0 - valid.mean()
    assert integral <= 1.0 + 1e-3
    assert integral == pytest.approx(1.0 - lost, abs=0.01)


def test_mitsuba_variant_choice(monkeypatch):
    from bake.quality import mitsuba_peer
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.delenv("FLOWBSDF_MITSUBA_VARIANT", raising=False)
    monkeypatch.setattr(mitsuba_peer, "find_libllvm", lambda min_version=19: None)
    assert mitsuba_peer.default_variant() == "scalar_rgb"     # never an LLVM older than 19
    monkeypatch.setenv("FLOWBSDF_MITSUBA_VARIANT", "scalar_spectral")
    assert mitsuba_peer.default_variant() == "scalar_spectral"


def test_a_folding_flow_is_flagged_in_the_report():
    """A flow run at too few Euler steps folds (its pdf is wrong there): the rows carry the
    fold share and the summary says so; at enough steps the same flow does not fold."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from test_flow import random_net
    from bake.materials.analytic import Lambert
    net = random_net("disk", scale=1.0)
    samplers = {"flow N=1": net.to_numpy(1), "flow N=64": net.to_numpy(64)}
    rows = speed_error_rows("lambert", Lambert(0.8), samplers, thetas=(20,), n=1 << 12, speed=False)
    folds = {r["sampler"]: r["folds"] for r in rows}
    assert folds["flow N=1"] > 0.01 and folds["flow N=64"] == 0.0
    text = summary_markdown(rows)
    assert "flow N=1 (folds" in text and "flow N=64 (folds" not in text
