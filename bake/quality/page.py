"""The main job's page, OUT/index.html: what FlowBSDF did to each material and how well it
does, at a glance. Built from what the job's stages left on disk (bake/plumbing/job.py): per material
the equal-time renders of the shader ball with their error maps and MSE (render/<name>/,
tracer.compare), the speed-vs-error summary with its Pareto plot, and the pdf slices (ideal /
flow / tables) (report/<name>/, report.write_report). Images are linked by relative paths,
so the folder can be moved or shared whole."""
import html
import math
import re
import time
from pathlib import Path

from ..core.sampler import canonical_kind
from ..io.progress import fmt_seconds

STYLE = """
body { font: 15px/1.45 system-ui, sans-serif; margin: 2em auto; max-width: 1100px; padding: 0 1em; color: #222 }
h1 { margin-bottom: 0.2em } h2 { margin-top: 2.2em; border-bottom: 1px solid #ccc }
.lead { color: #555 } .headline { font-size: 1.1em; background: #f3f6ee; padding: 0.6em 0.9em; border-radius: 6px }
table { border-collapse: collapse; margin: 0.6em 0 } td, th { padding: 0.2em 0.7em; border-bottom: 1px solid #e4e4e4 }
th { text-align: left; background: #fafafa } td.n { text-align: right; font-variant-numeric: tabular-nums }
.row { display: flex; flex-wrap: wrap; gap: 10px; align-items: flex-start }
figure { margin: 0; text-align: center; font-size: 0.9em }
figure img.px { width: 192px; image-rendering: pixelated } figure img.plot { max-width: 100% }
figure img.pareto { width: 380px }
.scale { display: inline-block; width: 160px; height: 10px; vertical-align: middle;
         background: linear-gradient(to right, #440154, #3b528b, #21918c, #5ec962, #fde725) }
.files, .small { font-size: 0.88em; color: #555 }
.failed { background: #fbeaea; padding: 0.6em 0.9em; border-radius: 6px }
"""
SAMPLER_LABELS = {"tables": "learned tables", "ggx": "GGX fit"}


def _label(sampler):
    return SAMPLER_LABELS.get(canonical_kind(sampler), sampler)


def _e(x):
    return html.escape(str(x))


def _num(x, digits=3):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-" if x is None or math.isnan(x) else ("inf" if x > 0 else "-inf")
    return f"{x:.{digits}g}"


def _table(header, rows, numeric_from=1, groups=()):
    """An HTML table; groups: (label, columns spanned) of a header row above `header`."""
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    if groups:
        head = "".join(f"<th colspan={n}>{_e(g)}</th>" for g, n in groups) + "</tr><tr>" + head
    body = "".join("<tr>" + "".join(f"<td{' class=n' if i >= numeric_from else ''}>{c}</td>"
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _figure(src, caption, cls="px"):
    """An image with its caption (HTML; its text is the image's alt text)."""
    alt = re.sub(r"<[^>]+>", " ", caption)
    return f'<figure><img class="{cls}" src="{_e(src)}" alt="{alt}"><figcaption>{caption}</figcaption></figure>'


def _ns(rate):
    return 1e9 / rate if rate and math.isfinite(rate) and rate > 0 else math.nan


def render_section(name, stamp):
    """Equal-time pictures with error maps, the headline ratio, and every render's numbers."""
    rows = [r for r in stamp["rows"] if r["mode"] != "unavailable"]
    base = f"render/{name}/"
    timed = [r for r in rows if r["mode"] == "equal time"]
    first = timed[0] if timed else None
    out = []
    if first:
        others = "".join(f"; {_label(r['sampler'])} {_num(r['mse'])} (<b>{_times(r['mse'], first['mse'])}</b>)"
                         for r in timed[1:])
        out.append(f'<p class="headline">Same time for each ({first["seconds"]:.1f} s), image error (MSE against '
                   f'the reference): {_label(first["sampler"])} {_num(first["mse"])}{others}.</p>')
    figs = [_figure(base + "reference.png", f"reference<br>{_e(_label(stamp['settings']['reference_sampler']))}, "
                                            f"{stamp['settings']['reference_spp']} spp, MIS")]
    errs = []
    for r in timed:
        label = _label(r["sampler"])
        figs.append(_figure(f"{base}{r['sampler']}_time.png", f"{_e(label)}<br>{r['spp']} spp in {r['seconds']:.1f} s"))
        errs.append(_figure(f"{base}{r['sampler']}_time_error.png", f"error, MSE {_num(r['mse'])}"))
    out.append('<div class="row">' + "".join(figs) + "</div>")
    if errs:
        scale = rows[0].get("error_scale")
        out.append('<div class="row">' + f'<figure style="width:192px"><figcaption>|luminance error|<br>'
                   f'0 <span class="scale"></span> {_num(scale, 2)}<br>(and above)</figcaption></figure>'
                   + "".join(errs) + "</div>")
    out.append(_table(["sampler", "mode", "spp", "seconds", "MSE", "MAE", "SSIM", "paths/s"],
                      [[_e(_label(r["sampler"])), _e(r["mode"]), r["spp"],
                        f"{r['seconds']:.2f}", _num(r["mse"]), _num(r["mae"]), f"{r['ssim']:.3f}",
                        f"{r['paths_per_s']:,}"] for r in rows], numeric_from=2))
    ref_noise = rows[0]["reference_noise"] if rows else math.nan
    s = stamp["settings"]
    out.append(f'<p class="small">builtin:{_e(s["scene"])}, {s["size"]}×{s["size"]} pixels, ' + (
               "MIS (light and BSDF sampling)" if s["mis"] else "BSDF sampling only (the samplers' "
               "differences show plainly)") + f'; the reference with MIS. The reference\'s own '
               f'noise (mean variance of its pixel means) is {_num(ref_noise)}: MSEs near it are not resolved. '
               f'Equal time is wall clock on a shared machine (load average {stamp.get("load", math.nan):.1f} '
               f'when rendered). Full numbers: <a href="{base}metrics.md">metrics.md</a>, images as EXR in '
               f'<a href="{base}">{base}</a>.</p>')
    return "\n".join(out)


def report_section(name, stamp):
    """The speed-vs-error summary, its Pareto plot and the pdf slices."""
    base = f"report/{name}/"
    figs = []
    if stamp.get("pareto"):
        figs.append(_figure(base + stamp["pareto"], "error vs time per sample", "pareto"))
    figs.append(_figure(base + stamp["pdf_slice"], "pdf over the hemisphere (disk projection, log scale)", "plot"))
    rows = [[_e(s["sampler"]), _num(s["median_rv"]), _num(s["max_rv"]), _num(s["max_lost"], 2),
             _num(s["ns_per_sample"]), _num(_ns(s["both_rwi_per_s"])),
             "-" if s["nbytes"] is None else f"{s['nbytes'] / 1024:,.0f} KiB"]
            for s in summary_rows_of(stamp)]
    thetas = sorted({r["theta_i"] for r in stamp["rows"]})
    table = _table(["sampler", "median rv", "max rv", "lost", "ns/sample", "ns/sample, new wi", "memory"], rows)
    return "\n".join([
        f'<div class="row"><div>{table}</div>{figs[0] if len(figs) > 1 else ""}</div>',
        f'<p class="small">rv: relative variance of the one-sample albedo estimator, 0 is perfect '
        f'(θi = {", ".join(f"{t:g}°" for t in thetas)}); lost: share of samples with pdf 0; ns/sample: '
        f'sample() + pdf() on one thread, one incident direction per call or a new one per sample. '
        f'Every number: <a href="{base}speed_error.md">speed_error.md</a>.</p>',
        figs[-1]])


def _source(entry):
    path = entry.source_path()
    if path is not None:
        return f"measured, {_e(path.name)}"
    spec = entry.source if isinstance(entry.source, dict) else {}
    return _e(", ".join(f"{k} {v}" for k, v in spec.items() if k != "kind"))


def overview(rows):
    """One line per material: equal-time MSE and median rv of the tables, and how many times
    larger the GGX fit's and cosine's are. rows: (name, render stamp, report stamp)."""
    lines = []
    for name, render, report in rows:
        mse = {r["sampler"]: r["mse"] for r in (render or {}).get("rows", ()) if r["mode"] == "equal time"}
        rv = {canonical_kind(s["sampler"]): s["median_rv"] for s in summary_rows_of(report)}  # ggx-fit: older reports
        cells = [f'<a href="#{_e(name)}">{_e(name)}</a>']
        for values, names in ((mse, ("tables", "ggx", "cosine")), (rv, ("tables", "ggx", "cosine"))):
            ref = values.get(names[0])
            cells.append(_num(ref))
            cells += [_times(values.get(n), ref) for n in names[1:]]
        lines.append(cells)
    return _table(["", "tables", "GGX fit", "cosine", "tables", "GGX fit", "cosine"], lines,
                  groups=[("material", 1), ("image error (MSE), same time", 3), ("median rv", 3)])


def summary_rows_of(report):
    from .report import summary_rows
    return summary_rows(report["rows"]) if report else []


def _times(x, ref):
    """x as a multiple of ref ("4.2×"), or "-"."""
    if x is None or ref is None or not (ref > 0) or not math.isfinite(x):
        return "-" if x is None or math.isnan(x) else "inf"
    r = x / ref
    return f"{r:,.0f}×" if r >= 100 else f"{r:.2g}×"


def write_page(out_dir, manifest, entries, timings, failures=None):
    """Write OUT/index.html from the report and render folders of `entries`; returns its path.
    failures: {material: (stage, message)} of this run's failed stages, shown in their sections."""
    from ..io.files import atomic_path, read_stamp
    out = Path(out_dir)
    stamps = [(e.name, read_stamp(out / "render" / e.name), read_stamp(out / "report" / e.name)) for e in entries]
    parts = [f"<!doctype html><meta charset=utf-8><title>FlowBSDF: {_e(Path(manifest.path).name)}</title>",
             f"<style>{STYLE}</style>",
             f"<h1>FlowBSDF on {_e(Path(manifest.path).name)}</h1>",
             '<p class="lead">Per material, a small flow learns to sample the BSDF (f·cos); it is baked into '
             'exact tables that Blender and the reference path tracer sample from. Below: the shader ball '
             'rendered with those tables, with the GGX lobe fitted to the material (what a renderer would '
             'otherwise use) and with cosine sampling, <b>for the same time</b>, against a converged reference; '
             'then how each sampler trades error for time, and what its pdf looks like.</p>',
             "<h3>At a glance</h3>", overview(stamps),
             '<p class="small">MSE of the shader ball rendered for the same time with each sampler, against a '
             'converged reference; median rv (relative variance of the one-sample albedo estimator, 0 is perfect) '
             'over the incident angles. For the GGX fit and cosine: how many times the tables\' value (above 1: '
             'the tables do better).</p>']
    for entry, (name, render, report) in zip(entries, stamps):
        parts.append(f"<h2 id='{_e(name)}'>{_e(name)} <small>({_source(entry)})</small></h2>")
        if name in (failures or {}):
            stage, message = failures[name]
            parts.append(f'<p class="failed"><b>{_e(stage)} failed</b>: {_e(message)}<br>Its later stages did not '
                         f'run (what is shown below, if anything, is from an earlier run); a rerun tries again.</p>')
        if render:
            parts.append(render_section(name, render))
        if report:
            parts.append("<h3>Speed vs error of the samplers</h3>")
            parts.append(report_section(name, report))
        if not (render or report):
            parts.append("<p>Not reported yet.</p>")
        parts.append(f'<p class="files">Model: models/{_e(name)}.flow.npz; tables: tables/{_e(name)}.exr '
                     f'(and what the Blender node reads beside them).</p>')
    ran = [sec for _, _, sec, status in timings if status == "done"]
    parts.append(f'<p class="files">Written {time.strftime("%Y-%m-%d %H:%M")}; this run: {len(ran)} of '
                 f'{len(timings)} stages had work to do, {fmt_seconds(sum(ran))}.</p>')
    path = out / "index.html"
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(parts) + "\n", encoding="utf-8")
    return path
