"""The yardstick table: rv of every sampler per material and incident angle (Markdown + CSV),
and the speed-vs-error report: rv, lost samples, throughput and memory per sampler, with
Pareto plots (error vs time) and pdf slices over the hemisphere (matplotlib, imported only
by the plotting functions, so bake/ stays importable in Blender without it)."""
import csv
from pathlib import Path
import math
import time

import numpy as np

from ..core.baselines import CosineSampler, fit_ggx
from ..core.ideal import IdealSampler
from ..core.metrics import relative_variance, relative_variance_ref
from ..maths.geometry import incident, luminance

THETAS_DEG = (0, 30, 60, 75, 85)


def yardstick_rows(name, material, thetas=THETAS_DEG, n=1 << 17, seed=0, extra=(), log=print):
    """One row per (sampler, theta_i): rv (metrics.relative_variance_ref, sampled from the ideal
    tabulation: the direct estimate understates heavy tails), the direct estimate `rv_direct`
    with its albedo estimate, and the quadrature albedo. Same sample budget n for both."""
    t0 = time.perf_counter()
    ideal = IdealSampler(material)
    ggx = fit_ggx(material, ideal)
    samplers = [CosineSampler(), ggx, ideal, *extra]
    rows = []
    for theta in thetas:
        wi = incident(theta)
        albedo = float(luminance(ideal.albedo(wi)))
        for sampler in samplers:
            rv_direct, estimate = relative_variance(material, sampler, wi, n=n, seed=seed)
            rv = relative_variance_ref(material, sampler, wi, ideal, k=math.isqrt(n), seed=seed)[0]
            rows.append({"material": name, "sampler": sampler.name, "theta_i": theta, "rv": rv,
                         "rv_direct": rv_direct, "albedo_mc": estimate, "albedo_quadrature": albedo})
    log(f"[yardsticks] {name}: {repr(ggx)}, {time.perf_counter() - t0:.1f}s")
    return rows


def median_rv(rows, sampler):
    return float(np.median([r["rv"] for r in rows if r["sampler"] == sampler]))


def markdown_table(rows, thetas=THETAS_DEG):
    """Materials x theta_i, one rv column block per sampler."""
    samplers = list(dict.fromkeys(r["sampler"] for r in rows))
    materials = list(dict.fromkeys(r["material"] for r in rows))
    rv = {(r["material"], r["sampler"], r["theta_i"]): r["rv"] for r in rows}
    head = "| material | sampler | " + " | ".join(f"{t}°" for t in thetas) + " |"
    lines = [head, "|" + "---|" * (len(thetas) + 2)]
    present = {(r["material"], r["sampler"]) for r in rows}
    for m in materials:
        for s in samplers:
            if (m, s) not in present:      # a sampler run on some materials only
                continue
            cells = " | ".join(_fmt(rv.get((m, s, t), float("nan"))) for t in thetas)
            lines.append(f"| {m} | {s} | {cells} |")
    lines.append("")
    lines.append("median rv over all cells: " + ", ".join(f"{s} {_fmt(median_rv(rows, s))}" for s in samplers))
    return "\n".join(lines)


def _fmt(x):
    if not np.isfinite(x):
        return "inf" if x > 0 else "nan"
    return f"{x:.3g}" if x >= 1e-3 else f"{x:.2e}"


def write_csv(rows, path):
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


# ------------------------------------------------------------------ speed vs error

SPEED_ERROR_FIELDS = ("material", "sampler", "theta_i", "rv", "rv_direct", "albedo_mc", "albedo_quadrature", "lost",
                      "sample_per_s", "pdf_per_s", "both_per_s", "ns_per_sample",
                      "sample_rwi_per_s", "pdf_rwi_per_s", "both_rwi_per_s", "folds", "nbytes")


def _weights(material, sampler, wi, n, seed):
    """One-sample albedo weights (as metrics.sample_weights computes them) and the lost mask."""
    rng = np.random.default_rng(seed)
    wo, pdf = sampler.sample(wi, rng.random((n, 2)))
    ok = (pdf > 0) & (wo[:, 2] > 0) & np.isfinite(pdf)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(ok, luminance(material.eval(wi, wo)) * np.maximum(wo[:, 2], 0) / pdf, 0.0)
    return w, ~ok


def speed_error_rows(name, material, samplers, thetas=THETAS_DEG, n=1 << 17, seed=0,
                     speed_n=1 << 15, speed_repeat=3, speed=True, quadrature=True, log=print):
    """One row per (sampler label, theta_i) with the fields of SPEED_ERROR_FIELDS:

    rv: with quadrature (an ideal sampler at hand) metrics.relative_variance_ref against it
    (wo from the ideal on a jittered isqrt(n)² grid: sees the tails the sampler's own samples
    rarely reach), else the direct estimate; `rv_direct` and the albedo estimate of the
    one-sample estimator (as metrics.relative_variance: same samples for the same seed), the
    quadrature albedo (from the ideal sampler's table: an
    IdealSampler among `samplers` is reused), `lost` = fraction of samples with pdf 0,
    non-finite pdf or below the horizon, throughput of sample() and pdf() (bench, one
    thread; NaN with speed=False) at that wi and, per sampler, with a new wi per sample
    (`*_rwi_per_s`: wi uniform in cos theta and phi, as a path tracer asks; NaN for the
    ideal sampler, which would build a table per sample), `folds` (a
    flow's share of samples whose Euler map folds, where its pdf is wrong: a flow run at
    fewer steps than it was trained for can fold; NaN for other samplers), and `nbytes`
    when the sampler has that attribute.
    """
    from .bench import random_incident, samples_per_second
    t0 = time.perf_counter()
    samplers = dict(samplers)
    ideal = None
    if quadrature:
        ideal = next((s for s in samplers.values() if isinstance(s, IdealSampler)), None) or IdealSampler(material)
    random_wi = {}
    if speed:
        wis = random_incident(speed_n, seed + 2)
        random_wi = {label: samples_per_second(sampler, wis, n=speed_n, repeat=speed_repeat, seed=seed + 1)
                     for label, sampler in samplers.items() if not getattr(sampler, "tabulates_per_wi", False)}
    rows = []
    for theta in thetas:
        wi = incident(theta)
        albedo = float(luminance(ideal.albedo(wi))) if ideal is not None else math.nan
        for label, sampler in samplers.items():
            w, lost = _weights(material, sampler, wi, n, seed)
            folds = (getattr(sampler, "last_stats", None) or {}).get("fold_fraction", math.nan)
            mean = w.mean()
            rv_direct = float(w.var() / mean ** 2) if mean != 0 else math.inf
            rv = rv_direct if ideal is None else \
                relative_variance_ref(material, sampler, wi, ideal, k=math.isqrt(n), seed=seed)[0]
            sp = samples_per_second(sampler, wi, n=speed_n, repeat=speed_repeat, seed=seed + 1) if speed else {}
            nbytes = getattr(sampler, "nbytes", None)
            rows.append({
                "material": name, "sampler": label, "theta_i": theta, "rv": rv, "rv_direct": rv_direct,
                "albedo_mc": float(mean), "albedo_quadrature": albedo, "lost": float(lost.mean()),
                "sample_per_s": sp.get("sample_per_s", math.nan), "pdf_per_s": sp.get("pdf_per_s", math.nan),
                "both_per_s": sp.get("both_per_s", math.nan), "ns_per_sample": sp.get("ns_per_sample", math.nan),
                **{f"{k}_rwi_per_s": random_wi.get(label, {}).get(f"{k}_per_s", math.nan)
                   for k in ("sample", "pdf", "both")},
                "folds": folds, "nbytes": None if nbytes is None else int(nbytes),
            })
    log(f"[speed-error] {name}: {len(samplers)} samplers x {len(thetas)} angles, {time.perf_counter() - t0:.1f}s")
    return rows


def summary_rows(rows):
    """Per (material, sampler): median and max rv over theta_i, max lost fraction, median speed, memory."""
    out = []
    keys = list(dict.fromkeys((r["material"], r["sampler"]) for r in rows))
    for m, s in keys:
        sel = [r for r in rows if r["material"] == m and r["sampler"] == s]
        rv = np.array([r["rv"] for r in sel], float)
        nbytes = [r.get("nbytes") for r in sel if r.get("nbytes") is not None]
        out.append({
            "material": m, "sampler": s, "median_rv": float(np.median(rv)), "max_rv": float(np.max(rv)),
            "max_lost": max(r.get("lost", math.nan) for r in sel),
            "both_per_s": _nanmedian([r.get("both_per_s", math.nan) for r in sel]),
            "ns_per_sample": _nanmedian([r.get("ns_per_sample", math.nan) for r in sel]),
            "sample_per_s": _nanmedian([r.get("sample_per_s", math.nan) for r in sel]),
            "pdf_per_s": _nanmedian([r.get("pdf_per_s", math.nan) for r in sel]),
            **{k: _nanmedian([r.get(k, math.nan) for r in sel])
               for k in ("sample_rwi_per_s", "pdf_rwi_per_s", "both_rwi_per_s")},
            "max_folds": _nanmax([r.get("folds", math.nan) for r in sel]),
            "nbytes": max(nbytes) if nbytes else None,
        })
    return out


def _finite(values):
    v = np.array([math.nan if x is None else x for x in values], float)
    return v[np.isfinite(v)]


def _nanmedian(values):
    v = _finite(values)
    return float(np.median(v)) if len(v) else math.nan


def _nanmax(values):
    v = _finite(values)
    return float(v.max()) if len(v) else math.nan


def _fmt_rate(x):
    if x is None or not np.isfinite(x):
        return "-"
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= scale:
            return f"{x / scale:.3g}{unit}"
    return f"{x:.3g}"


def _fmt_bytes(x):
    if x is None:
        return "-"
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if x >= scale:
            return f"{x / scale:.3g} {unit}"
    return f"{int(x)} B"


def summary_markdown(rows):
    """Per material x sampler: median / max rv, lost fraction, speed (1 thread; one wi per
    call, then a new wi per sample), memory; then the median rv of each sampler over every cell."""
    lines = ["| material | sampler | median rv | max rv | max lost | sample+pdf /s | ns/sample | sample /s "
             "| pdf /s | random wi: sample+pdf /s | sample /s | pdf /s | memory |", "|" + "---|" * 13]
    for s in summary_rows(rows):
        ns = s["ns_per_sample"]
        folds = s["max_folds"]
        label = s["sampler"] + (f" (folds {100 * folds:.2g} %: pdf wrong there)"
                                if folds is not None and np.isfinite(folds) and folds > 0 else "")
        lines.append(f"| {s['material']} | {label} | {_fmt(s['median_rv'])} | {_fmt(s['max_rv'])} | "
                     f"{s['max_lost']:.3g} | {_fmt_rate(s['both_per_s'])} | "
                     f"{'-' if not np.isfinite(ns) else f'{ns:.3g}'} | {_fmt_rate(s['sample_per_s'])} | "
                     f"{_fmt_rate(s['pdf_per_s'])} | {_fmt_rate(s['both_rwi_per_s'])} | "
                     f"{_fmt_rate(s['sample_rwi_per_s'])} | {_fmt_rate(s['pdf_rwi_per_s'])} | "
                     f"{_fmt_bytes(s['nbytes'])} |")
    return "\n".join(lines)


def write_report(rows, out_dir, slices=(), plots=True, title="Speed vs error"):
    """Write the speed-vs-error report into out_dir; returns {what: path}.

    - speed_error.md: rv per material x sampler x theta_i, median rv per sampler, speed and
      memory per material x sampler;
    - speed_error.csv (every row, SPEED_ERROR_FIELDS) and speed_error_summary.csv;
    - with plots (needs matplotlib): pareto_<material>.png, error (median rv) vs time per
      sample, one point per sampler; and for each (name, material, samplers, theta_i) in
      `slices`, pdf_<name>_<theta>.png (see plot_pdf_slices).
    """
    from pathlib import Path
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    thetas = sorted(dict.fromkeys(r["theta_i"] for r in rows))
    written = {}
    md = [f"# {title}", "", "## rv of the one-sample albedo estimator (0 is perfect)", "",
          markdown_table(rows, thetas), "", "## Per sampler: error, lost samples, speed (one thread), memory", "",
          summary_markdown(rows), "",
          "rv = Var[lum(f·cos)/pdf] / E[...]²; lost = fraction of samples with pdf 0 or below the horizon; "
          "speed: best-of-k wall clock of sample() and pdf() on one thread (bake.quality.bench).", ""]
    path = out / "speed_error.md"
    written["markdown"] = path
    write_csv([{k: r.get(k) for k in SPEED_ERROR_FIELDS} for r in rows], out / "speed_error.csv")
    written["csv"] = out / "speed_error.csv"
    write_csv(summary_rows(rows), out / "speed_error_summary.csv")
    written["summary_csv"] = out / "speed_error_summary.csv"
    if plots:
        for m in dict.fromkeys(r["material"] for r in rows):
            p = plot_pareto(rows, m, out / f"pareto_{_slug(m)}.png")
            if p is not None:
                written[f"pareto:{m}"] = p
                md.append(f"![{m}: error vs time]({p.name})")
        for name, material, samplers, theta in slices:
            p = plot_pdf_slices(material, samplers, theta, out / f"pdf_{_slug(name)}_{int(round(theta))}.png",
                                title=f"{name}, θi = {theta}°")
            written[f"pdf:{name}:{theta}"] = p
            md.append(f"![{name} pdf at {theta}°]({p.name})")
    path.write_text("\n".join(md) + "\n")
    return written


def _slug(s):
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in str(s))


def _pyplot():
    """matplotlib's pyplot on the Agg back end (imported here only: bake/ runs in Blender without it)."""
    try:
        import matplotlib
    except ImportError:
        from ..errors import FlowBSDFError
        raise FlowBSDFError("the report's plots need matplotlib (`pip install matplotlib`)") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


RV_FLOOR, RV_CEIL = 1e-6, 1e6


def plot_pareto(rows, material, path):
    """Error vs time for one material: x = ns per sample (sample + pdf, log), y = median rv over
    theta_i (log), one labelled point per sampler, the Pareto front as a step line. rv 0 is
    drawn at 1e-6 and inf at 1e6. Returns the path, or None when no row has a speed."""
    sel = [s for s in summary_rows(rows) if s["material"] == material and np.isfinite(s["ns_per_sample"])]
    if not sel:
        return None
    plt = _pyplot()
    x = np.array([s["ns_per_sample"] for s in sel])
    y = np.clip(np.nan_to_num(np.array([s["median_rv"] for s in sel]), nan=RV_CEIL, posinf=RV_CEIL), RV_FLOOR, RV_CEIL)
    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
    ax.scatter(x, y, s=40, zorder=3)
    for xi, yi, s in zip(x, y, sel):
        ax.annotate(s["sampler"], (xi, yi), textcoords="offset points", xytext=(5, 4), fontsize=9)
    order = np.argsort(x)
    front, best = [], math.inf
    for k in order:
        if y[k] < best:
            front.append(k)
            best = y[k]
    if len(front) > 1:
        ax.step(x[front], y[front], where="post", color="0.6", lw=1, zorder=2, label="Pareto front")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    lo, hi = x.min(), x.max()
    ax.set_xlim(lo / 2, hi * 3)
    ylo, yhi = y.min(), y.max()
    ax.set_ylim(ylo / 3, yhi * 3)
    ax.set_xlabel("ns per sample (sample() + pdf(), one thread)")
    ax.set_ylabel("median rv over θi")
    ax.set_title(f"{material}: error vs time")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def disk_directions(res):
    """The (res x res) grid over [-1, 1]² of the disk projection (x = wo.x, y = wo.y):
    directions (M, 3) of the pixels inside the unit disk, their mask, and d omega per pixel."""
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    X, Y = np.meshgrid(c, -c)            # image row 0 at the top: y = +1
    r2 = X * X + Y * Y
    inside = r2 < 1.0
    z = np.sqrt(np.maximum(1.0 - r2[inside], 0.0))
    wo = np.stack([X[inside], Y[inside], z], axis=-1)
    d_omega = (2.0 / res) ** 2 / np.maximum(z, 1e-12)
    return wo, inside, d_omega


def target_density(material, wi, res=256):
    """The normalized target max(lum f, 0)·cos / integral on the disk grid (an image with NaN
    outside the disk), i.e. the pdf a perfect sampler would have."""
    wo, inside, d_omega = disk_directions(res)
    t = material.target(wi, wo)
    total = np.sum(t * d_omega)
    img = np.full(inside.shape, np.nan)
    img[inside] = t / total if total > 0 else 0.0
    return img


def pdf_image(sampler, wi, res=256):
    wo, inside, _ = disk_directions(res)
    img = np.full(inside.shape, np.nan)
    img[inside] = sampler.pdf(wi, wo)
    return img


def _show_panels(panels, wi, path, title=None, decades=4):
    """Images side by side on one log colour scale (pdf 0 in black, outside the disk white)."""
    plt = _pyplot()
    from matplotlib.colors import LogNorm
    finite = [p[np.isfinite(p) & (p > 0)] for _, p in panels]
    peak = max((np.percentile(f, 99.9) for f in finite if len(f)), default=1.0)
    norm = LogNorm(vmin=peak * 10.0 ** -decades, vmax=peak)
    cmap = plt.get_cmap("inferno").with_extremes(under="black", bad="white")
    k = len(panels)
    fig, axes = plt.subplots(1, k, figsize=(2.6 * k + 1.0, 3.0), dpi=100, squeeze=False, layout="constrained")
    for ax, (label, img) in zip(axes[0], panels):
        shown = np.where(np.isfinite(img) & (img <= 0), peak * 10.0 ** -(decades + 3), img)
        im = ax.imshow(shown, extent=(-1, 1, -1, 1), norm=norm, cmap=cmap, interpolation="nearest")
        ax.plot([-wi[0]], [-wi[1]], "+", color="cyan", ms=8, mew=1)   # the mirror direction
        ax.set_title(label, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=list(axes[0]), shrink=0.9, label="pdf (1/sr)", extend="both")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_pdf_slices(material, samplers, theta_i, path, res=200, target=True, title=None, decades=4):
    """The pdf over the hemisphere at theta_i (disk projection x = wo.x, y = wo.y; per
    steradian) of the ideal sampler and every other sampler given, side by side on a shared
    log colour scale, like the paper's Figures 19-29. `samplers` is {label: sampler}; an
    IdealSampler is added first when none is given. With target, the first panel is the
    true normalized f·cos. The cyan cross marks the mirror direction."""
    from pathlib import Path
    samplers = dict(samplers)
    if not any(isinstance(s, IdealSampler) for s in samplers.values()):
        samplers = {"ideal": IdealSampler(material), **samplers}
    else:   # the ideal sampler first
        samplers = dict(sorted(samplers.items(), key=lambda kv: not isinstance(kv[1], IdealSampler)))
    wi = incident(theta_i)
    panels = [("target f·cos (normalized)", target_density(material, wi, res))] if target else []
    panels += [(label, pdf_image(s, wi, res)) for label, s in samplers.items()]
    return _show_panels(panels, wi, Path(path), title, decades)


def plot_target(material, theta_i, path, res=256, title=None, decades=4):
    """The material's true f·cos (luminance, normalized to a pdf) at theta_i on the same
    disk projection and log scale as plot_pdf_slices."""
    from pathlib import Path
    wi = incident(theta_i)
    return _show_panels([("target f·cos (normalized)", target_density(material, wi, res))], wi, Path(path),
                        title or f"θi = {theta_i}°", decades)


def manifest_samplers(entry, material, flow=None, tables=None, steps=(2, 4, 8), log=print):
    """Every sampler the report compares for one material: baselines, the ideal tabulation, the
    trained `flow` at several step counts (always its trained N), the baked `tables` (current ones,
    as rendered: bake/plumbing/reports.py finds both in an output folder; and a half-resolution
    rebuild on the same bins), plain tabulation at the tables' memory, and Mitsuba's sampler for
    RGL files."""
    from ..core.ideal import BinnedIdeal
    from ..core.sampler import open_sampler
    ideal = open_sampler("ideal", material)
    samplers = {kind: open_sampler(kind, material, ideal=ideal) for kind in ("uniform", "cosine", "ggx")}
    samplers["ideal"] = ideal
    if flow is not None:
        for n in sorted(set(steps) | {flow.steps}):
            samplers[f"flow N={n}"] = flow.with_steps(n)
    if tables is not None:
        from ..core.tabulate import build_tables
        samplers["tables"] = tables
        own = getattr(tables, "tables", tables)     # carried tables (bake/core/carried.py): their tables
        half = max(own.rows // 2, 4)
        azimuths = {}
        if own.phi_bins is not None:    # anisotropic: the same azimuths (halfvector ones store the closing one too)
            azimuths = {"phi_bins": own.phi_bins[:-1] if own.coords == "halfvector" else own.phi_bins,
                        "coords": own.coords}
        label, tenth = f"tables {half}x{half}", [0]

        def built(done, total):
            """About ten lines (anisotropic: the rebuild can take as long as the bake); no total, as
            `total` counts a closing azimuth that build_tables may turn instead of building."""
            if done * 10 // total > tenth[0]:
                tenth[0] = done * 10 // total
                log(f"[report] {entry.name}: {label}: {done} tables built")
        samplers[label] = build_tables(material, ideal, own.theta_bins, half, half,
                                       lobe_width=own.meta.get("lobe_width"), progress=built if azimuths else None,
                                       **azimuths)
        if azimuths:    # BinnedIdeal snaps theta_i only: a table per phi_i would be neither plain nor equal memory
            log(f"[report] {entry.name}: no plain (equal memory) baseline for anisotropic tables")
        else:
            samplers["plain (equal memory)"] = BinnedIdeal.with_memory(material, own.theta_bins, tables.nbytes)
    path = entry.source_path()
    if path is not None and path.suffix.lower() == ".bsdf":
        try:
            from .mitsuba_peer import MitsubaMeasuredSampler
            samplers["mitsuba"] = MitsubaMeasuredSampler(path)
        except Exception as e:      # an optional peer: any failure only drops it from the report
            log(f"[report] {entry.name}: no Mitsuba peer ({e})")
    return samplers


SLICE_THETA = 60.0


def entry_report(entry, material, flow=None, tables=None, thetas=THETAS_DEG, n=1 << 17, steps=(2, 4, 8),
                 log=print, speed_n=1 << 15, speed_repeat=3):
    """One manifest material: its speed_error_rows and its pdf slice for write_report (the
    ideal sampler, the trained flow and the tables at SLICE_THETA)."""
    samplers = manifest_samplers(entry, material, flow, tables, steps=steps, log=log)
    rows = speed_error_rows(entry.name, material, samplers, thetas=thetas, n=n, speed_n=speed_n,
                            speed_repeat=speed_repeat, log=log)
    trained = next((f"flow N={m.meta['steps']}" for k, m in samplers.items() if k.startswith("flow N=")), None)
    shown = {k: samplers[k] for k in ("ideal", trained, "tables") if k in samplers}
    return rows, (entry.name, material, shown, SLICE_THETA)
