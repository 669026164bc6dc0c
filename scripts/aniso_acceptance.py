"""Issue-22 acceptance for anisotropic tables: planned tables (plan_tables' defaults, from the
ideal tabulation) of the anisotropic hard cases, their rv at 12 phi_i between phi bins and at
theta_i between theta bins, against the ideal tabulation's (IdealSampler at 256^2 per wi), with
size, bake time and sampling speed; optionally beside tables over (a, b) of wo (the coordinates
anisotropic tables had before the half vector).

    .venv/bin/python scripts/aniso_acceptance.py [--cases a,b] [--coords halfvector,wo]
        [--thetas 30,57.3,80] [--k 256] [--phi-count auto|N] [--resolution N]

rv is metrics.relative_variance_ref (wo drawn from the ideal sampler on a jittered k x k grid;
sees the tails a direct estimate misses). Prints Markdown; asserts nothing.
"""
import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bake.maths.geometry import incident  # noqa: E402
from bake.core.ideal import IdealSampler  # noqa: E402
from bake.core.settings import BakeSettings  # noqa: E402
from bake.core.planner import plan_tables  # noqa: E402
from bake.core.tabulate import build_tables  # noqa: E402
from bake.materials import open_material  # noqa: E402
from bake.core.metrics import relative_variance_ref  # noqa: E402
from bake.quality.stress import hard_cases  # noqa: E402

EXTRA = {"ggx_1to25_seam": {"kind": "analytic", "model": "ggx", "alpha_x": 0.02, "alpha_y": 0.5}}


def open_case(name, folder):
    if name in EXTRA:
        return open_material(EXTRA[name])
    return {c.name: c for c in hard_cases()}[name].open(folder)


def speed(tab, n=1 << 16, repeat=3):
    """sample + pdf with a new wi per sample: samples per second (best of `repeat`)."""
    rng = np.random.default_rng(0)
    theta, phi = np.arccos(rng.random(n)), rng.uniform(-math.pi, math.pi, n)
    wi = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    u = rng.random((n, 2))
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        wo, _ = tab.sample(wi, u)
        tab.pdf(wi, wo)
        best = min(best, time.perf_counter() - t0)
    return n / best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default="aniso_1to50,aniso_1to50_rotated,ggx_1to25_seam")
    ap.add_argument("--coords", default="halfvector")
    ap.add_argument("--thetas", default="30,57.3,80")
    ap.add_argument("--k", type=int, default=256)
    ap.add_argument("--phi-count", default="auto", help="plan_tables' phi_count: auto or a number")
    ap.add_argument("--resolution", type=int, default=None, help="fix the tables' resolution (skip the probe)")
    args = ap.parse_args()
    thetas = [float(t) for t in args.thetas.split(",")]
    folder = Path(tempfile.mkdtemp())
    print("| case | coords | plan | MB | bake s | samples/s | theta_i | rv / ideal rv at 12 phi_i between bins | worst |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.cases.split(","):
        mat = open_case(name, folder)
        ideal = IdealSampler(mat, resolution=256)
        for coords in args.coords.split(","):
            t0 = time.time()
            count = args.phi_count if args.phi_count == "auto" else int(args.phi_count)
            tab = plan_tables(mat, ideal, BakeSettings(phi_count=count, resolution=args.resolution), coords=coords)
            seconds = time.time() - t0
            plan = f"{tab.rows}x{tab.cols}, {len(tab.theta_bins)} x {len(tab.phi_bins)} bins"
            rate = speed(tab)
            P = len(tab.phi_bins) - (tab.coords == "halfvector")      # the azimuths (halfvector: + the closing bin)
            step = mat.phi_period / P
            # 12 azimuths spread over the period, each 0.3 or 0.7 of the way between two bins
            phis = [tab.phi_bins[(j * P) // 12] + (0.3 + 0.4 * (j % 2)) * step for j in range(12)]
            for theta in thetas:
                ratios = []
                for phi in phis:
                    wi = incident(theta, phi)
                    rv = relative_variance_ref(mat, tab, wi, ideal, k=args.k)[0]
                    ref = relative_variance_ref(mat, ideal, wi, ideal, k=args.k)[0]
                    ratios.append(rv / ref)
                print(f"| {name} | {coords} | {plan} | {tab.nbytes / 1e6:.2f} | {seconds:.0f} | {rate / 1e6:.2f} M | "
                      f"{theta:g} | {' '.join(f'{r:.2f}' for r in ratios)} | {max(ratios):.2f} |", flush=True)


if __name__ == "__main__":
    main()
