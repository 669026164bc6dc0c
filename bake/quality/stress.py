"""`flowbsdf stress`: the long part of the stability suite (issue 8); numpy only.

Hard cases: every sampler of the product on materials built to break it, with

  - no NaN/inf/negative pdf, no non-finite direction or weight f·cos/pdf, in every sample;
  - samples either in the upper hemisphere with pdf > 0, or invalid (pdf 0) consistently:
    pdf() returns the same value at the sample (checked on a share of each chunk);
  - chi-square of sample() against pdf() (bake.core.metrics.chi2_test, Šidák-corrected over
    every test of the run);
  - rv (relative variance of the albedo estimator) finite.

Samplers: the baked tables (anisotropic materials: bins over theta_i x phi_i), the ideal
sampler, and flow models when given (`--models DIR` with <case>.flow.npz files, or `--train-flows`, which
trains tiny ones with `python -m trainer` in a subprocess: bake/ never imports torch).

Load: bake 50 varied analytic materials in one batch, then a soak run that samples
`--soak` directions through their tables in chunks, recording RSS and throughput per chunk
(CSV, and PNG when matplotlib is there) and whether both stay flat.

tests/test_hard_cases.py runs the same cases with modest counts.
"""
import functools
import json
import math
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..materials import open_material
from ..materials.base import Material, as_dirs
from ..materials.rgl import write_tensor_file
from ..maths.geometry import luminance, reflect

# ------------------------------------------------------------------------------ materials


class Cap(Material):
    """Lambertian inside a cone of half-angle `deg` around the normal, zero elsewhere: f·cos is
    zero over most of the hemisphere (98.5 % of it at 10 degrees)."""

    isotropic = True

    def __init__(self, deg=10.0, albedo=0.9):
        self.deg, self.albedo = float(deg), float(albedo)
        self.name = f"cap({deg:g})"

    def eval(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        inside = (wi[:, 2] > 0) & (wo[:, 2] > math.cos(math.radians(self.deg)))
        return np.where(inside[:, None], self.albedo / math.pi, 0.0) * np.ones((1, 3))


class MirrorCone(Material):
    """Constant inside a cone of half-angle `deg` around the mirror direction of wi, zero
    elsewhere (hard edges; isotropic and reciprocal). At phi_i = 0 the cone straddles
    phi = +-pi."""

    isotropic = True

    def __init__(self, deg=8.0, value=3.0):
        self.deg, self.value = float(deg), float(value)
        self.name = f"mirror_cone({deg:g})"

    def eval(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        r = reflect(wi, np.array([0.0, 0.0, 1.0]))
        inside = (wi[:, 2] > 0) & (wo[:, 2] > 0) & (np.sum(r * wo, axis=1) > math.cos(math.radians(self.deg)))
        return np.where(inside[:, None], self.value, 0.0) * np.ones((1, 3))


def synthetic_rgl(path, seed=0, n_theta=6, n=32):
    """An isotropic RGL file with the measured data's troubles: `rgb` negative in about a third
    of its entries (one channel across the whole peak, like chm_mint), and empty rows: the vndf
    rows of half-vector azimuths facing away from wi are zero (all slices; half of them at 90
    degrees), and so are the matching rgb rows."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    theta_i = np.linspace(0, np.pi / 2, n_theta).astype(f32)
    x = np.linspace(0, 1, n)                                   # sqrt-mapped theta_m
    lobe = np.exp(-(x / 0.35) ** 2)[None, :]                   # (phi_m, theta_m)
    vndf = np.repeat(np.repeat(lobe, n, axis=0)[None, None], n_theta, axis=1).astype(f32)
    vndf[:, :, : n // 8] = 0.0                                 # empty rows
    vndf[:, -1, : n // 4] = 0.0
    vndf[:, -1, 3 * n // 4:] = 0.0
    rgb = np.empty((1, n_theta, 3, n, n), f32)
    base = rng.uniform(0.2, 1.0, (1, n_theta, n, n)) * lobe[None, None]
    rgb[:, :, 0] = -0.5 * base                                 # red negative over the whole peak
    rgb[:, :, 1] = base
    rgb[:, :, 2] = base * rng.uniform(-0.3, 1.0, base.shape)   # blue partly negative
    rgb[:, :, :, : n // 8] = 0.0
    lum = np.maximum(luminance(np.moveaxis(rgb, 2, -1)), 1e-4).astype(f32)
    sigma = np.full((2, n), 0.8, f32)
    ndf = (2.0 * np.repeat(lobe, 2, axis=0)).astype(f32)
    return write_tensor_file(path, {
        "description": np.frombuffer(b"stress: negative values and empty rows", np.uint8),
        "phi_i": np.zeros(1, f32), "theta_i": theta_i, "sigma": sigma, "ndf": ndf, "vndf": vndf,
        "luminance": lum, "rgb": rgb, "jacobian": np.array([1], np.uint8)})


def synthetic_merl(path, seed=0):
    """A MERL file with 40 % invalid (negative) entries, empty theta_h rows, and an albedo
    above one (a bright glossy lobe over a white base)."""
    from ..materials.analytic import Lambert, Microfacet, Mixture
    from ..materials.merl import DIMS, INVALID, tabulate
    rng = np.random.default_rng(seed)
    table = tabulate(Mixture([(1.0, Lambert(0.9)), (2.5, Microfacet("ggx", 0.08))]))
    table[:, 30:45] = 0.0                                       # empty rows of theta_h
    table[:, rng.random(DIMS) < 0.4] = INVALID                  # invalid entries
    Path(path).write_bytes(np.array(DIMS, "<i4").tobytes() + np.ascontiguousarray(table, "<f8").tobytes())
    return Path(path)


# ------------------------------------------------------------------------------ cases

GRAZING = (85.0, 87.0, 89.0, 89.9)


@dataclass
class Case:
    name: str
    build: object              # workdir -> Material
    wis: list                  # (theta_i, phi_i) in degrees
    note: str = ""
    flow_domain: str = "auto"  # the manifest default: slope for the sharp lobes, disk otherwise
    flow: bool = False         # train a tiny flow for it (`--train-flows`)
    chi2_binning: str = "halfvector"
    material: object = None

    def open(self, workdir):
        if self.material is None:
            self.material = self.build(Path(workdir))
        return self.material

    def directions(self):
        t, p = np.radians(np.array(self.wis, float)).T
        return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def _spec(**spec):
    return lambda workdir: open_material({"kind": "analytic", **spec})


def _thetas(thetas, phi=0.0):
    return [(t, phi) for t in thetas]


ANISO_PHI = tuple(np.linspace(-180.0, 150.0, 12))


def hard_cases():
    """The hard cases, fresh (materials are opened lazily by Case.open)."""
    return [
        Case("mirror_a0.002", _spec(model="ggx", alpha=0.002), _thetas((0.0, 30.0, 60.0, 85.0, 89.5)),
             "near-mirror GGX lobe", flow=True),
        Case("mirror_a0.005_conductor", _spec(model="ggx", alpha=0.005, eta=[0.2, 0.92, 1.1], k=[3.9, 2.45, 2.14]),
             _thetas((10.0, 45.0, 80.0, 88.0)), flow=True),
        Case("mirror_a0.01_plastic", _spec(model="plastic", albedo=[0.6, 0.2, 0.1], alpha=0.01),
             _thetas((0.0, 40.0, 75.0, 89.0)), "a sharp coat over a diffuse base", flow=True),
        Case("aniso_1to50", _spec(model="ggx", alpha_x=0.5, alpha_y=0.01),
             [(t, p) for t in (30.0, 70.0, 88.0) for p in ANISO_PHI], "anisotropy 1:50 at 12 phi_i",
             flow_domain="spherical", flow=True),
        Case("aniso_1to50_rotated", _spec(model="ggx", alpha_x=0.01, alpha_y=0.5, angle=37.0),
             [(t, p) for t in (20.0, 60.0, 85.0) for p in ANISO_PHI], flow_domain="spherical"),
        Case("grazing_ggx_a0.05", _spec(model="ggx", alpha=0.05), _thetas(GRAZING), "theta_i 85-89.9", flow=True),
        Case("grazing_lambert", _spec(model="lambert", albedo=0.8), _thetas(GRAZING)),
        Case("grazing_sheen", _spec(model="sheen", color=0.8, roughness=0.3), _thetas(GRAZING)),
        Case("seam_ggx_a0.03", _spec(model="ggx", alpha=0.03),
             [(45.0, 0.0), (45.0, 1e-9), (45.0, -1e-9), (70.0, 180.0), (70.0, -180.0), (30.0, 179.999)],
             "the lobe sits across phi = +-pi", flow_domain="spherical", flow=True),
        Case("seam_retro_a0.05", _spec(model="retro", alpha=0.05),
             [(50.0, 180.0), (50.0, -179.9999), (80.0, 180.0)], "retro lobe at phi_i = pi"),
        Case("near_black", _spec(model="mix", components=[
            {"weight": 1e-6, "model": "lambert", "albedo": 1.0},
            {"weight": 1e-6, "model": "ggx", "alpha": 0.05}]), _thetas((0.0, 50.0, 89.0)), "albedo ~ 1e-6"),
        Case("over_unity", _spec(model="mix", components=[
            {"weight": 2.5, "model": "lambert", "albedo": 1.0},
            {"weight": 3.0, "model": "ggx", "alpha": 0.02}]), _thetas((0.0, 50.0, 89.0)), "albedo ~ 5.5"),
        Case("rgl_negative_empty_rows", lambda d: open_material(synthetic_rgl(d / "stress_negative.bsdf")),
             _thetas((0.0, 35.0, 70.0, 89.0)), "synthetic RGL: negative rgb, empty vndf rows"),
        Case("merl_invalid_empty_rows", lambda d: open_material(synthetic_merl(d / "stress_invalid.binary")),
             _thetas((0.0, 35.0, 70.0, 89.0)), "synthetic MERL: 40 % invalid, empty theta_h rows, albedo > 1"),
        # halfvector bins: chi2_test's expected counts miss ~0.15 % of the tables' mass on this
        # hard-edged cap (integral 0.9985 vs 0.99998 in cosine bins): a false rejection at n >= 1e5.
        Case("cap_10deg", lambda d: Cap(10.0), _thetas((0.0, 45.0, 89.0)), "f·cos zero on 98.5 % of the hemisphere",
             chi2_binning="cosine"),
        Case("mirror_cone_8deg", lambda d: MirrorCone(8.0), [(40.0, 0.0), (70.0, 0.0), (87.0, 180.0)],
             "f·cos zero outside a hard-edged cone across phi = +-pi"),
    ]


# ------------------------------------------------------------------------------ samplers

TABLE_BINS = np.radians([0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 78.0, 84.0, 87.0, 89.0, 89.5])


def make_tables(material, ideal, size=32, grid=192, bins=TABLE_BINS, phi_count=8, coords=None):
    """Small baked tables of a material (anisotropic: phi_count azimuths over its period, in
    `coords`)."""
    from ..core.planner import lobe_width_of
    from ..core.tabulate import build_tables, default_phi_bins
    try:
        width = lobe_width_of(material, ideal)
    except Exception:   # noqa: BLE001 (a fit that fails on an odd material: no lobe zones)
        width = None
    phi_bins = None if material.isotropic else default_phi_bins(material, phi_count)
    return build_tables(material, ideal, bins, rows=size, cols=size, grid=grid, lobe_width=width, phi_bins=phi_bins,
                        coords=coords)


def make_samplers(case, workdir, ideal_resolution=128, table_size=32, grid=192, models=None):
    """{name: sampler} for a case: tables, ideal, flow (when a model is given)."""
    from ..core.sampler import open_sampler
    mat = case.open(workdir)
    ideal = open_sampler("ideal", mat, resolution=ideal_resolution)
    out = {"ideal": ideal, "tables": make_tables(mat, ideal, table_size, grid)}
    if mat.isotropic:       # the planner may bake either coordinates (planner.ISO_PLANNED)
        out["tables_halfpolar"] = make_tables(mat, ideal, table_size, grid, coords="halfpolar")
    model = (models or {}).get(case.name)
    if model is not None:
        out["flow"] = model
    return out


# ------------------------------------------------------------------------------ checks

@dataclass
class Tally:
    """What went wrong (or not) over many samples of one sampler on one case."""
    n: int = 0
    valid: int = 0
    bad_wo: int = 0            # non-finite direction
    bad_pdf: int = 0           # NaN, inf or negative pdf
    below_with_pdf: int = 0    # pdf > 0 but wo.z <= 0
    pdf_checked: int = 0
    pdf_mismatch: int = 0      # pdf() disagrees with the returned pdf (rel. 1e-6), or says > 0 for an invalid one
    bad_weight: int = 0        # non-finite f·cos/pdf
    negative_weight: int = 0   # lum(f)·cos/pdf < 0 (the data's own negative values)
    sum_w: float = 0.0
    sum_w2: float = 0.0
    seconds: float = 0.0
    worst_pdf_rel: float = 0.0
    examples: list = field(default_factory=list)

    def failures(self, allow_negative_weights=False):
        out = {k: getattr(self, k) for k in ("bad_wo", "bad_pdf", "below_with_pdf", "pdf_mismatch", "bad_weight")
               if getattr(self, k)}
        if self.negative_weight and not allow_negative_weights:
            out["negative_weight"] = self.negative_weight
        return out

    @property
    def rv(self):
        if self.n == 0:
            return math.nan
        mean = self.sum_w / self.n
        if mean == 0:
            return math.inf
        return max(self.sum_w2 / self.n - mean * mean, 0.0) / (mean * mean)

    def as_dict(self):
        d = {k: v for k, v in vars(self).items() if k != "examples"}
        d.update(rv=self.rv, samples_per_s=self.n / self.seconds if self.seconds else math.nan)
        return d


def check_chunk(material, sampler, wi, u, tally, pdf_share=1.0, rng=None, rtol=None):
    """Sample one chunk at one wi and add what is wrong to the tally. rtol: of pdf() against the
    returned pdf (1e-6; 1e-5 for the ideal sampler, whose pdf() recomputes the half vector's
    sqrt-mapped coordinate: near the pole that loses a few digits, 4e-6 seen at alpha 0.002)."""
    rtol = rtol or (1e-5 if getattr(sampler, "name", "") == "ideal" else 1e-6)
    t0 = time.perf_counter()
    with np.errstate(all="ignore"):
        wo, pdf = sampler.sample(wi, u)
    n = len(u)
    fin_wo = np.all(np.isfinite(wo), axis=1)
    fin_pdf = np.isfinite(pdf) & (pdf >= 0)
    valid = fin_wo & fin_pdf & (pdf > 0) & (wo[:, 2] > 0)
    tally.n += n
    tally.valid += int(valid.sum())
    tally.bad_wo += int((~fin_wo).sum())
    tally.bad_pdf += int((~fin_pdf).sum())
    tally.below_with_pdf += int((fin_pdf & (pdf > 0) & fin_wo & (wo[:, 2] <= 0)).sum())
    # pdf() at the samples: the same value for valid ones, 0 for invalid ones (a share of them).
    k = n if pdf_share >= 1.0 else max(1, int(n * pdf_share))
    idx = np.arange(n) if k == n else (rng or np.random.default_rng(0)).choice(n, k, replace=False)
    sel = idx[fin_wo[idx]]
    with np.errstate(all="ignore"):
        again = sampler.pdf(wi, wo[sel])
        rel = np.abs(again - pdf[sel]) / np.maximum(np.abs(pdf[sel]), 1e-300)
    mismatch = np.where(valid[sel], ~(rel <= rtol), (again != 0) & (wo[sel, 2] > 0) & (pdf[sel] == 0))
    tally.pdf_checked += len(sel)
    tally.pdf_mismatch += int(mismatch.sum())
    if valid[sel].any():
        tally.worst_pdf_rel = max(tally.worst_pdf_rel, float(np.nanmax(np.where(valid[sel], rel, 0.0))))
    # Weights of the valid samples (invalid ones count as w = 0).
    with np.errstate(all="ignore"):
        f = material.eval(wi, wo[valid])
        cos = wo[valid, 2:3]
        w_rgb = f * cos / pdf[valid, None]
        w = luminance(f) * cos[:, 0] / pdf[valid]
    tally.bad_weight += int((~np.all(np.isfinite(w_rgb), axis=1)).sum())
    tally.negative_weight += int((w < 0).sum())
    w = np.where(np.isfinite(w), np.maximum(w, 0.0), 0.0)     # the estimator of max(lum f, 0)·cos
    tally.sum_w += float(w.sum())
    tally.sum_w2 += float(np.dot(w, w))
    tally.seconds += time.perf_counter() - t0
    if len(tally.examples) < 5:
        bad = np.flatnonzero(~fin_wo | ~fin_pdf)[:2]
        tally.examples += [{"wi": wi.tolist(), "u": u[i].tolist(), "pdf": float(pdf[i])} for i in bad]
    return tally


def run_case(case, sampler, n, workdir, chunk=1 << 18, seed=0, pdf_share=1.0, log=None, every=10.0):
    """Sample n directions (round-robin over the case's incident directions) and tally them."""
    mat = case.open(workdir)
    wis = case.directions()
    tally = Tally()
    rng = np.random.default_rng(seed)
    last = time.perf_counter()
    k = 0
    while tally.n < n:
        m = min(chunk, n - tally.n)
        check_chunk(mat, sampler, wis[k % len(wis)], rng.random((m, 2)), tally, pdf_share, rng)
        k += 1
        if log and time.perf_counter() - last > every:
            last = time.perf_counter()
            log(f"    {tally.n:.3g}/{n:.3g} samples, {tally.n / tally.seconds:.3g}/s, "
                f"failures {tally.failures(True) or 'none'}")
    return tally


def chi2_cases(case, sampler, workdir, n=200_000, n_tests=1, seed=1, max_wis=3, binning=None):
    """chi2_test at up to max_wis of the case's incident directions (spread over the list). The
    ideal sampler is binned on its own half-vector grid (its density is constant per cell there)."""
    binning = binning or ("halfvector" if getattr(sampler, "name", "") == "ideal" else case.chi2_binning)
    from ..core.metrics import chi2_test
    wis = case.directions()
    pick = np.unique(np.linspace(0, len(wis) - 1, min(max_wis, len(wis))).round().astype(int))
    return [(tuple(case.wis[i]), chi2_test(sampler, wis[i], n=n, n_tests=n_tests, seed=seed + int(i),
                                           binning=binning)) for i in pick]


# ------------------------------------------------------------------------------ flows

def train_flows(cases, workdir, log=print, python=None):
    """Tiny flows for the analytic cases, trained by `python -m trainer` in a subprocess
    (bake/ stays free of torch). Returns {case name: FlowModel}; {} when training fails."""
    from ..core.flow import load_model
    workdir = Path(workdir)
    lines = []
    specs = {c.name: ({"kind": "analytic", **_analytic_spec(c)}, c.flow_domain) for c in cases
             if c.flow and _analytic_spec(c)}
    for name, (spec, domain) in specs.items():
        lines.append(textwrap.dedent(f"""
            [[material]]
            name = "{name}"
            source = {_toml_inline(spec)}
            domain = "{domain}"
            [material.train]
            preset = "fast"
            theta_i = [2, 20, 40, 60, 75, 85, 89]
            resolution = 64
            pool = 65536
            phi_i_count = 8
            batch = 512
            base_steps = 100
            flow_steps = 400
            flow_eval_every = 200
            flow_eval_steps = 8
            reflow_pairs = 8192
            reflow_ode_steps = 16
            reflow_steps = 300
            reflow_eval_every = 150
            holdout = 512
            ckpt_every = 100
            warmup = 20
            teacher = {{ vel_width = 32, vel_depth = 2 }}
        """))
    manifest = workdir / "flows.toml"
    manifest.write_text("".join(lines))
    out = workdir / "models"
    python = python or sys.executable
    log(f"[flows] training {len(specs)} tiny flows -> {out}")
    r = subprocess.run([python, "-m", "trainer", "train", str(manifest), "--out", str(workdir), "--no-progress",
                        "--threads", "1"], capture_output=True, text=True)
    if r.returncode != 0:
        log(f"[flows] training failed ({r.returncode}): {r.stderr.strip()[-400:]}")
    return {name: load_model(out / f"{name}.flow.npz") for name in specs if (out / f"{name}.flow.npz").is_file()}


def _analytic_spec(case):
    """The manifest spec behind an analytic case (the closure of `_spec`)."""
    cells = getattr(case.build, "__closure__", None) or ()
    for cell in cells:
        if isinstance(cell.cell_contents, dict):
            return dict(cell.cell_contents)
    return {}


def _toml_inline(value):
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_inline(v)}" for k, v in value.items()) + " }"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_inline(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value)
    return repr(float(value)) if isinstance(value, float) else str(value)


def load_models(folder, cases):
    from ..core.flow import load_model
    folder = Path(folder)
    return {c.name: load_model(folder / f"{c.name}.flow.npz") for c in cases
            if (folder / f"{c.name}.flow.npz").is_file()}


# ------------------------------------------------------------------------------ load

def rss_bytes():
    """Resident set size of this process (Linux /proc; 0 where unavailable)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def load_materials(n=50, seed=0):
    """n varied analytic material specs (isotropic: the soak measures the C fast path)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        kind = ("lambert", "ggx", "beckmann", "plastic", "sheen", "retro", "mix")[i % 7]
        a = float(np.round(10 ** rng.uniform(-2.3, -0.2), 4))
        c = [float(x) for x in np.round(rng.uniform(0.05, 0.95, 3), 3)]
        spec = {"lambert": dict(model="lambert", albedo=c),
                "ggx": dict(model="ggx", alpha=a, f0=c),
                "beckmann": dict(model="beckmann", alpha=max(a, 0.01)),
                "plastic": dict(model="plastic", albedo=c, alpha=a, ior=float(np.round(rng.uniform(1.3, 2.0), 2))),
                "sheen": dict(model="sheen", color=c, roughness=float(np.round(rng.uniform(0.1, 1.0), 2))),
                "retro": dict(model="retro", alpha=max(a, 0.02), color=c),
                "mix": dict(model="mix", components=[dict(weight=0.5, model="lambert", albedo=c),
                                                     dict(weight=0.5, model="ggx", alpha=a)])}[kind]
        out.append((f"load{i:02d}_{kind}", {"kind": "analytic", **spec}))
    return out


def write_load_manifest(path, materials, bake):
    lines = [f"[defaults]\nbake = {_toml_inline(bake)}\n"]
    for name, spec in materials:
        lines.append(f'[[material]]\nname = "{name}"\nsource = {_toml_inline(spec)}\n')
    Path(path).write_text("\n".join(lines))
    return Path(path)


LOAD_BAKE = dict(resolution=16, tol=0.5, grid=96, samples=2048, first_bins=4, ideal_resolution=64)


def run_load(workdir, bake, current_tables, n_materials=50, soak=10 ** 9, chunk=1 << 20, log=print, plot=True):
    """Bake n materials in one batch, then sample `soak` directions through their tables. The
    pipeline's part is handed in (bake/plumbing/cli.py): bake(manifest_path, out_dir) bakes a
    manifest's materials, returning the table files written; current_tables(manifest_path,
    out_dir) opens them, None where one is not current."""
    workdir = Path(workdir)
    manifest = write_load_manifest(workdir / "load.toml", load_materials(n_materials), LOAD_BAKE)
    out = workdir / "load_out"
    t0 = time.perf_counter()
    rss0 = rss_bytes()
    written = bake(manifest, out)
    bake_s = time.perf_counter() - t0
    log(f"[load] baked {len(written)} materials in {bake_s:.0f} s (RSS {rss0 / 2**20:.0f} -> "
        f"{rss_bytes() / 2**20:.0f} MiB)")
    tables = current_tables(manifest, out)
    assert all(t is not None for t in tables), "a baked table is not current right after the bake"
    rng = np.random.default_rng(0)
    rows, done, k = [], 0, 0
    csv = workdir / "soak.csv"
    with open(csv, "w") as fh:
        fh.write("chunk,samples_done,seconds,samples_per_s,rss_mib,bad\n")
        while done < soak:
            n = min(chunk, soak - done)
            tab = tables[k % len(tables)]
            theta = math.acos(rng.uniform(0.0, 1.0))
            phi = rng.uniform(-math.pi, math.pi)
            wi = np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])
            t = time.perf_counter()
            wo, pdf = tab.sample(wi, rng.random((n, 2)))
            bad = int(np.sum(~np.isfinite(pdf) | (pdf <= 0) | ~np.all(np.isfinite(wo), axis=1) | (wo[:, 2] <= 0)))
            dt = time.perf_counter() - t
            done += n
            rows.append((k, done, dt, n / dt, rss_bytes() / 2 ** 20, bad))
            fh.write(",".join(f"{x:.6g}" if isinstance(x, float) else str(x) for x in rows[-1]) + "\n")
            k += 1
            if k % 100 == 0:
                fh.flush()
                log(f"[soak] {done:.3g}/{soak:.3g} samples, {np.median([r[3] for r in rows[-100:]]):.3g}/s, "
                    f"RSS {rows[-1][4]:.0f} MiB, bad {sum(r[5] for r in rows)}")
    summary = soak_summary(rows)
    summary.update(bake_seconds=bake_s, materials=len(written), csv=str(csv))
    if plot:
        summary["png"] = plot_soak(rows, workdir / "soak.png")
    log(f"[soak] {json.dumps(summary)}")
    return summary


def soak_summary(rows):
    """Flatness of memory and throughput: first vs last tenth of the chunks (after a warm-up tenth)."""
    rows = np.array([r[:6] for r in rows], float)
    n = len(rows)
    tenth = max(1, n // 10)
    first, last = rows[tenth:2 * tenth], rows[-tenth:]
    rss_growth = float(np.median(last[:, 4]) - np.median(first[:, 4]))
    speed_ratio = float(np.median(last[:, 3]) / np.median(first[:, 3]))
    return {"samples": int(rows[-1, 1]), "chunks": n, "bad_samples": int(rows[:, 5].sum()),
            "rss_first_mib": float(np.median(first[:, 4])), "rss_last_mib": float(np.median(last[:, 4])),
            "rss_max_mib": float(rows[:, 4].max()), "rss_growth_mib": rss_growth,
            "speed_first": float(np.median(first[:, 3])), "speed_last": float(np.median(last[:, 3])),
            "speed_ratio": speed_ratio,
            "memory_flat": abs(rss_growth) < 20.0, "throughput_flat": 0.8 < speed_ratio < 1.25}


def plot_soak(rows, path):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    rows = np.array([r[:6] for r in rows], float)
    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    ax[0].plot(rows[:, 1], rows[:, 4])
    ax[0].set_ylabel("RSS (MiB)")
    ax[1].plot(rows[:, 1], rows[:, 3] / 1e6, lw=0.5)
    ax[1].set_ylabel("M samples/s")
    ax[1].set_xlabel("samples")
    fig.suptitle("flowbsdf stress: soak through baked tables")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)


# ------------------------------------------------------------------------------ the command

def run_hard_cases(workdir, samples=10 ** 8, ideal_samples=None, flow_samples=None, chi2_n=1_000_000,
                   models=None, only=None, log=print):
    """Every case x sampler; returns a list of result dicts (JSON-able)."""
    workdir = Path(workdir)
    cases = [c for c in hard_cases() if not only or c.name in only]
    ideal_samples = ideal_samples or samples
    flow_samples = flow_samples or samples
    plans = []
    for c in cases:
        t = time.perf_counter()
        # ideal at resolution 128: at 256 chi2_test's expected counts of its piecewise-constant
        # density are off by ~0.1-0.2 % (tol 0.01/n per cell adds up), a false rejection.
        samplers = make_samplers(c, workdir, ideal_resolution=128, table_size=48, grid=256, models=models)
        log(f"[case] {c.name}: {c.note or ''} samplers {sorted(samplers)} ({time.perf_counter() - t:.0f} s to build)")
        plans.append((c, samplers))
    n_chi2 = sum(min(3, len(c.wis)) * len(s) for c, s in plans)
    results = []
    for c, samplers in plans:
        for name, sampler in sorted(samplers.items()):
            n = {"ideal": ideal_samples, "flow": flow_samples}.get(name, samples)
            log(f"[run] {c.name} / {name}: {n:.3g} samples over {len(c.wis)} incident directions")
            share = 1.0 if n <= 1e6 else 0.05 if name == "flow" else 0.25
            tally = run_case(c, sampler, n, workdir, pdf_share=share, log=log,
                             chunk=1 << 18 if name != "flow" else 1 << 15)
            # the flow's pdf() (a Newton inverse per point) makes the expected counts costly: fewer
            chi = chi2_cases(c, sampler, workdir, n=chi2_n if name != "flow" else min(chi2_n, 20_000),
                             n_tests=n_chi2, max_wis=3 if name != "flow" else 1)
            measured = "rgl" in c.name or "merl" in c.name
            fails = tally.failures(allow_negative_weights=measured)
            res = {"case": c.name, "sampler": name, **tally.as_dict(), "failures": fails,
                   "chi2": [{"wi": list(w), "passed": r.passed, "p": r.p_value, "note": r.note} for w, r in chi],
                   "rv_finite": math.isfinite(tally.rv)}
            res["ok"] = not fails and all(r.passed for _, r in chi) and res["rv_finite"]
            results.append(res)
            log(f"[done] {c.name} / {name}: {'OK' if res['ok'] else 'PROBLEM'} n={tally.n:.3g} "
                f"({res['samples_per_s']:.3g}/s), valid {tally.valid / tally.n:.4%}, rv {tally.rv:.4g}, "
                f"pdf checked {tally.pdf_checked:.3g} (worst rel {tally.worst_pdf_rel:.2g}), "
                f"negative weights {tally.negative_weight}, failures {fails or 'none'}, chi2 "
                + ", ".join(f"{'pass' if r.passed else 'FAIL'} p={r.p_value:.3g}" for _, r in chi))
    return results


def add_parser(sub, bake, current_tables):
    """`flowbsdf stress`; bake and current_tables: the pipeline's, for the load run (run_load)."""
    s = sub.add_parser("stress", help="the long stability suite: hard cases, load and soak (issue 8)")
    s.add_argument("--out", default="out/stress", help="work folder (materials, tables, logs, CSV/PNG)")
    s.add_argument("--samples", type=float, default=1e8, help="samples per case through the tables")
    s.add_argument("--ideal-samples", type=float, default=None, help="per case through the ideal sampler")
    s.add_argument("--flow-samples", type=float, default=None, help="per case through the flow")
    s.add_argument("--chi2-samples", type=float, default=1e6)
    s.add_argument("--case", action="append", help="only this case (repeatable)")
    s.add_argument("--models", help="folder of <case>.flow.npz models to include")
    s.add_argument("--train-flows", action="store_true", help="train tiny flows for the analytic cases first")
    s.add_argument("--load", type=int, default=50, help="materials baked in the load test (0: skip)")
    s.add_argument("--soak", type=float, default=1e9, help="directions sampled in the soak run (0: skip)")
    s.add_argument("--skip-cases", action="store_true", help="only the load test and soak")
    s.set_defaults(func=functools.partial(cmd_stress, bake=bake, current_tables=current_tables))
    return s


def cmd_stress(args, bake, current_tables):
    from ..errors import FlowBSDFError
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    def log(msg):
        print(msg, flush=True)

    report = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "args": {k: v for k, v in vars(args).items()
                                                                      if k != "func"}}
    if not args.skip_cases:
        cases = [c for c in hard_cases() if not args.case or c.name in args.case]
        models = load_models(args.models, cases) if args.models else {}
        if args.train_flows:
            models.update(train_flows(cases, out, log=log))
        report["cases"] = run_hard_cases(out, int(args.samples), args.ideal_samples and int(args.ideal_samples),
                                         args.flow_samples and int(args.flow_samples), int(args.chi2_samples),
                                         models=models, only=args.case, log=log)
        (out / "stress.json").write_text(json.dumps(report, indent=1, default=str))
    if args.load and args.soak:
        report["load"] = run_load(out, bake, current_tables, args.load, int(args.soak), log=log)
    (out / "stress.json").write_text(json.dumps(report, indent=1, default=str))
    problems = [f"{r['case']}/{r['sampler']}" for r in report.get("cases", []) if not r["ok"]]
    log(f"[stress] wrote {out / 'stress.json'}; problems: {problems or 'none'}")
    if problems:
        raise FlowBSDFError(f"stress found problems in {', '.join(problems)} (see {out / 'stress.json'})")
