"""Issue 51: does the SVM graph beat the closure fit under lamps at Blender's DEFAULT render settings,
denoising included? backends.svm_pays was decided with denoising off (adaptive sampling made the fit
win at equal time); Blender's default denoises (OpenImageDenoise), which removes much of the SVM
graph's noise and none of the fit's bias.

Per material (lights_acceptance's studio scene: an area lamp, a point lamp with a radius, a dim
world; its sphere, camera and box pixel filter; Blender's factory render settings with adaptive
sampling at 4096 samples), with denoising on and off: the fit at 4096 samples, --seeds
renders each; the SVM graph at --svm-spp samples, its MSE interpolated at the fit's CPU time, of
whole renders and less each back end's 1-sample render (the cost that does not grow with the pixels,
which dominates at these sizes).
Per render: CPU seconds of this process (Cycles' threads) and the MSE over the sphere
against the tracer's converged image of the MEASURED FILE (lights_acceptance.Case.reference("file"),
net of its noise). Printed: each MSE with its SE, the time, and SVM / fit at equal time.

    .venv/bin/python scripts/denoise_pays.py --tables-dir DIR [names...] [--size 96] [--seeds 3] [--svm-spp 4096,1024,256,64]
        [--ref-spp 4096] [--work-dir out/denoise_pays]
"""
import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import lights_acceptance as la  # noqa: E402

SAMPLES = 4096      # Blender's default render samples


def equal_time_mse(points, cpu):
    """The MSE at CPU time `cpu`, interpolated log-log between the (cpu, mse) points that bracket it
    (None outside their range: no extrapolation)."""
    points = sorted(points)
    for (c0, m0), (c1, m1) in zip(points, points[1:]):
        if c0 <= cpu <= c1:
            t = 0.0 if c1 == c0 else np.log(cpu / c0) / np.log(c1 / c0)
            return float(np.exp((1 - t) * np.log(m0) + t * np.log(m1)))
    return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("names", nargs="*", default=["cm_military_green", "vch_golden_yellow"])
    ap.add_argument("--tables-dir", required=True, help="default bakes: <dir>/<name>.exr")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--work-dir", default=str(ROOT / "out" / "denoise_pays"))
    ap.add_argument("--svm-spp", type=lambda t: [int(x) for x in t.split(",")], default=[4096, 1024, 256, 64],
                    help="the SVM graph's sample counts (comma separated)")
    ap.add_argument("--reuse", action="store_true", help="reuse the saved references")
    a = ap.parse_args(argv)
    args = SimpleNamespace(size=a.size, work_dir=a.work_dir, reuse=a.reuse, ref_spp=a.ref_spp, file_ref_spp=0,
                           workers=a.workers)
    factory = la.blender_settings()
    studio = la.setups(None, None)["studio"]

    def setup(denoise):
        base = la._film_off(la._with_settings(studio, factory))

        def with_denoising(sc):
            base(sc)
            sc.cycles.use_denoising = denoise       # (after _with_settings, which turns it off)
        return with_denoising

    inner = la.inner_mask(a.size)
    results = {}
    for name in a.names:
        tables = Path(a.tables_dir) / f"{name}.exr"
        case = la.Case("studio", name, tables, setup(False), args)
        ref, ref_var, _ = case.reference("file")
        rows = {}

        def run(kind, spp, denoise):
            case.setup = setup(denoise)
            imgs, secs = case.cycles(kind, spp, a.seeds, first_seed=10)
            err = la.errors(imgs, ref, ref_var, inner)
            cpu = float(np.mean([s[1] for s in secs]))
            key = f"{kind} {spp} {'denoised' if denoise else 'noisy'}"
            rows[key] = {"mse": err["mse"], "mse_se": err["mse_se"], "bias2": err["bias2"], "cpu": cpu}
            la.log(f"{case.tag()} {key}: MSE {err['mse']:.3e} +- {err['mse_se']:.1e} (bias^2 {err['bias2']:.2e}), "
                   f"CPU {cpu:.1f} s per render")
            return rows[key]

        for denoise in (True, False):
            tag = "denoised" if denoise else "noisy"
            # What a render costs whatever its samples (sync, textures, the denoiser's start): at
            # 1 sample per pixel; taken off every render's CPU time, the rest is what grows with
            # the pixels (a full-size frame's cost is nearly all that).
            fixed = {kind: run(kind, 1, denoise)["cpu"] for kind in ("fit", "svm")}
            fit = run("fit", SAMPLES, denoise)
            svm = [run("svm", spp, denoise) for spp in a.svm_spp]
            for label, less in (("whole renders", {"fit": 0.0, "svm": 0.0}), ("less the 1-sample render", fixed)):
                fit_cpu = fit["cpu"] - less["fit"]
                mse = equal_time_mse([(r["cpu"] - less["svm"], r["mse"]) for r in svm], fit_cpu)
                said = (f"SVM's MSE at the fit's CPU time {mse / fit['mse']:.2f}x the fit's" if mse is not None else
                        "no equal-time point among the SVM graph's sample counts")
                la.log(f"{case.tag()} {tag}, CPU of {label}: " + ", ".join(
                    f"SVM@{spp} MSE {r['mse'] / fit['mse']:.2f}x at {(r['cpu'] - less['svm']) / fit_cpu:.2f}x CPU"
                    for spp, r in zip(a.svm_spp, svm)) + f"; {said}")
                rows[f"equal time {tag}, {label}"] = None if mse is None else mse / fit["mse"]
        results[name] = rows
        Path(a.work_dir, "denoise_pays.json").write_text(json.dumps(results, indent=1))
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    t0 = time.time()
    main()
    la.log(f"done in {(time.time() - t0) / 60:.1f} min")
