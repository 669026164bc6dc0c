"""Render a scene with several samplers and compare them with a converged reference.

The reference is rendered once (many spp, `reference_sampler`, MIS) with its own seed;
each sampler then renders at equal spp and at equal time (the wall-clock time the first
sampler took for its spp; the others render whole passes until that time has passed). Sampler set-up (tables
loading, GGX fit, ideal tabulation) is not counted. Outputs in `out_dir`:
reference.exr, <sampler>_spp.exr, <sampler>_time.exr, compare.png (images and
false-colour error maps |lum(img - ref)|, all on one scale: see error_maps), the same pictures one per file
(reference.png, <sampler>_<mode>.png, <sampler>_<mode>_error.png), metrics.md and metrics.csv
(MSE, MAE, SSIM, and `error_scale`: the error maps' full-scale value).
The reference's own noise (mean variance of its pixel means) is reported with it:
an MSE cannot be resolved below it.
"""
import csv
import time
from pathlib import Path

import numpy as np

from ..core.ideal import FineIdeal
from ..errors import FlowBSDFError
from ..maths.geometry import LUMINANCE
from .images import false_colour, mae, mse, ssim, tonemap, write_exr, write_png
from .integrator import render


def _prepare(samplers):
    for s in samplers:
        if isinstance(s, FineIdeal):
            s.prepare()


def metrics(img, ref):
    return {"mse": mse(img, ref), "mae": mae(img, ref), "ssim": ssim(img, ref)}


def compare(scene, names, spp, reference_spp, out_dir, samplers_of, reference_sampler="ideal", mis=True,
            equal_time=True, seed=1, log=print, reference=None, workers=1, progress=None):
    """Returns (rows, reference image). samplers_of(name): the sampler `name` for each of the scene's
    materials (bake/plumbing/scene_samplers.py opens them from an output folder; FlowBSDFError when
    one is not available); reference: a precomputed (image, variance) to reuse;
    progress(what, passes, fraction, seconds): after every pass of every render (once per render
    when workers > 1), `what` = "reference" or "<sampler> (equal spp|time)", `fraction` = the
    share of that render done (of its spp, or of its time budget)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    built = {}      # samplers by name, built (and tabulated) once

    def samplers_for(name):
        if name not in built:
            built[name] = samplers_of(name)
            _prepare(built[name])
        return built[name]

    if reference is None:
        log(f"[compare] reference: {reference_sampler}, {reference_spp} spp")
        t0 = time.perf_counter()
        ref, ref_var, st = render(scene, samplers_for(reference_sampler), spp=reference_spp, mis=True,
                                  seed=10_000 + seed, workers=workers,
                                  progress=_reporter("reference", reference_spp, None, progress))
        log(f"[compare] reference done in {time.perf_counter() - t0:.1f}s")
    else:
        ref, ref_var = reference
    write_exr(out / "reference.exr", ref)
    ref_noise = float(np.mean(ref_var))
    rows, images = [], {}
    budget = None
    for name in names:
        try:
            samplers = samplers_for(name)
        except FlowBSDFError as e:      # report the sampler as unavailable, go on
            log(f"[compare] {name}: not available: {e}")
            rows.append({"sampler": name, "mode": "unavailable", "note": str(e)})
            continue
        runs = [("spp", dict(spp=spp))]
        if equal_time:
            runs.append(("time", None))
        for mode, kw in runs:
            if mode == "time":
                kw = dict(seconds=budget)
            img, var, stats = render(scene, samplers, mis=mis, seed=seed, workers=workers,
                                     progress=_reporter(f"{name} (equal {mode})", kw.get("spp"), kw.get("seconds"),
                                                        progress), **kw)
            if budget is None:
                budget = stats.seconds      # the first sampler's time at equal spp
            write_exr(out / f"{name}_{mode}.exr", img)
            images[(name, mode)] = img
            row = {"sampler": name, "mode": f"equal {mode}", "spp": stats.extra["spp"],
                   "seconds": round(stats.seconds, 2), **metrics(img, ref),
                   "paths_per_s": round(stats.paths / stats.seconds),
                   "sampling_share": round(stats.sampling_share, 3),
                   "lost": stats.lost, "reference_noise": ref_noise}
            rows.append(row)
            log(f"[compare] {name} ({row['mode']}): {row['spp']} spp in {row['seconds']}s, "
                f"MSE {row['mse']:.4g}, MAE {row['mae']:.4g}, SSIM {row['ssim']:.4f}")
    scale = write_side_by_side(out / "compare.png", ref, images)
    write_pictures(out, ref, images, scale)
    for row in rows:
        row.setdefault("error_scale", scale)
    (out / "metrics.md").write_text(markdown(rows, ref_noise, reference_sampler, reference_spp) + "\n")
    write_csv(out / "metrics.csv", rows)
    return rows, (ref, ref_var)


def _reporter(what, spp, seconds, progress):
    """The integrator's progress callback for one render (of `spp` passes or `seconds`), reporting
    to compare's `progress`."""
    if progress is None:
        return None
    return lambda k, elapsed, stats: progress(what, k, min(1.0, k / spp if spp else elapsed / seconds), elapsed)


def error_maps(ref, images):
    """|lum(image - ref)| per image, and their common full-scale value: the median over the
    images of their 99th percentiles (the worse images saturate rather than the better ones
    going black)."""
    errs = {k: np.abs((v - ref) @ LUMINANCE) for k, v in images.items()}
    return errs, (float(np.median([np.percentile(e, 99) for e in errs.values()])) or 1.0) if errs else 1.0


def write_pictures(out, ref, images, scale):
    """reference.png, and per (sampler, mode) <sampler>_<mode>.png and its error map
    <sampler>_<mode>_error.png (false colour, 0 to `scale`)."""
    out = Path(out)
    write_png(out / "reference.png", tonemap(ref))
    for (name, mode), err in error_maps(ref, images)[0].items():
        write_png(out / f"{name}_{mode}.png", tonemap(images[(name, mode)]))
        write_png(out / f"{name}_{mode}_error.png", false_colour(err, scale))


def write_side_by_side(path, ref, images):
    """Row pairs per mode: images (reference first), then their error maps on one scale;
    returns that scale (see error_maps)."""
    H, W = ref.shape[:2]
    modes = sorted({m for _, m in images}, key=lambda m: m != "spp")
    names = list(dict.fromkeys(n for n, _ in images))
    errs, vmax = error_maps(ref, images)
    if not names:
        return vmax
    gap = 2
    canvas = np.full((2 * len(modes) * (H + gap), (len(names) + 1) * (W + gap), 3), 255, np.uint8)
    for r, mode in enumerate(modes):
        y0 = 2 * r * (H + gap)
        canvas[y0:y0 + H, :W] = tonemap(ref)
        for c, name in enumerate(names, 1):
            if (name, mode) not in images:
                continue
            x0 = c * (W + gap)
            canvas[y0:y0 + H, x0:x0 + W] = tonemap(images[(name, mode)])
            canvas[y0 + H + gap:y0 + 2 * H + gap, x0:x0 + W] = false_colour(errs[(name, mode)], vmax)
    write_png(path, canvas)
    return vmax


COLUMNS = ["sampler", "mode", "spp", "seconds", "mse", "mae", "ssim", "paths_per_s", "sampling_share", "lost",
           "reference_noise", "error_scale", "note"]


def write_csv(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def markdown(rows, ref_noise, reference_sampler, reference_spp):
    lines = [f"Reference: {reference_sampler}, {reference_spp} spp, MIS (its noise: mean variance of "
             f"the pixel means {ref_noise:.3g}).", "",
             "| sampler | mode | spp | seconds | MSE | MAE | SSIM | paths/s | BSDF sampling share |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if r["mode"] == "unavailable":
            lines.append(f"| {r['sampler']} | unavailable: {r['note']} | | | | | | | |")
            continue
        lines.append(f"| {r['sampler']} | {r['mode']} | {r['spp']} | {r['seconds']} | {r['mse']:.4g} | "
                     f"{r['mae']:.4g} | {r['ssim']:.4f} | {r['paths_per_s']} | {r['sampling_share']:.1%} |")
    return "\n".join(lines)
