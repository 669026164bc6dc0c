"""A prototype for issue 22, item 4: tables over an RGL file's own coordinates s, beside halfpolar.

    .venv/bin/python scripts/warped_tables_probe.py MATERIAL LO_DEG HI_DEG [--cells 48]

Builds a pair of bins at LO and HI the way the planner's probes do (build_tables from the ideal,
one placement for both bins) over halfpolar and over s (rgl.WarpedCoords: cells in [0, 1]² of s,
b = 2 pi s_y), and prints the rv over the ideal tabulation's (metrics.ReferencePoints, 512², seed 7)
at the bins, their quarter points and cos-midpoint, and the share of samples lost at the midpoint
(s that reach no direction above the horizon). Not the product's path: the s coordinates reach
build_tables and Tables (numpy only) by patching their coordinate tables in this process.

Measured (48², this script, 2026-12-05): chm_mint 84.64/85.17 halfpolar 1.17 / 2.50 (mid) / 0.91,
over s 1.37 / 0.52 / 0.37; military 78.93/89.9 mid 3220 -> 12.4; but on the bin over s often worse
(chm 0 deg 1818x, paper_white 49.94 12.8x against 0.26x) and 0.02-2 % of samples lost.
"""
import argparse

import numpy as np

import bake.core.tables as tables
import bake.core.tabulate as tabulate
from bake.core.planner import lobe_width_of
from bake.maths.geometry import spherical_dir
from bake.core.ideal import IdealSampler
from bake.materials import open_material
from bake.materials.rgl import WarpedCoords, shared_dir
from bake.core.metrics import ReferencePoints

TWO_PI = 2.0 * np.pi


class Warps:
    """WarpedCoords per wi, and the (a, b) <-> wo maps Tables and the builder call."""

    def __init__(self, material):
        self.coords = WarpedCoords(material)

    def from_ab(self, wi, a, b, phi_ref=None):
        wo, jac = self.coords.from_s(wi, np.stack([np.ravel(a), np.ravel(b) / TWO_PI], axis=-1))
        wo[jac <= 0] = (0.0, 0.0, -1.0)          # lost: below the horizon
        return wo, np.where(jac > 0, jac / TWO_PI, np.inf)       # d omega / d(a, b)

    def to_ab(self, wi, wo, phi_ref=None):
        s, jac = self.coords.to_s(wi, wo)
        s = np.clip(np.nan_to_num(s), 0.0, 1.0)
        return s[:, 0], s[:, 1] * TWO_PI, jac / TWO_PI


def patch_in(warps, coords_used):
    """Let build_tables and Tables take the s coordinates under the name halfpolar while
    coords_used[0] == "s" (the builder's frames, row and column knots; Tables' maps)."""
    polar_frame, row_knots, polar_maps = tabulate._PolarFrame, tabulate._row_knots, tables.H_MAPS["halfpolar"]

    class SFrame:
        def __init__(self, wi, phi):
            self.wi = wi

        def nodes(self, a0, a1, b0, b1, s):
            q = len(s)
            a = np.repeat(a0[:, None] + s[None, :] * (a1 - a0)[:, None], q, axis=1)
            b = np.tile(b0[:, None] + s[None, :] * (b1 - b0)[:, None], (1, q))
            wo, jac = warps.from_ab(self.wi, a, b)
            return wo, np.where(np.isfinite(jac), jac, 0.0)

        def ab(self, wo):
            return warps.to_ab(self.wi, wo)[:2]

    tabulate._PolarFrame = lambda wi, phi: SFrame(wi, phi) if coords_used[0] == "s" else polar_frame(wi, phi)
    tabulate._row_knots = lambda wi, theta, coords, width: (
        np.array([0.0, 1.0]) if coords_used[0] == "s" else row_knots(wi, theta, coords, width))
    tables.H_MAPS["halfpolar"] = tuple(
        (lambda *x, f=f, g=g: g(*x) if coords_used[0] == "s" else f(*x))
        for f, g in zip(polar_maps, (warps.from_ab, warps.to_ab)))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("material")
    p.add_argument("lo", type=float)
    p.add_argument("hi", type=float)
    p.add_argument("--cells", type=int, default=48)
    args = p.parse_args()
    mat = open_material(shared_dir() / f"{args.material}.bsdf")
    ideal = IdealSampler(mat)
    coords_used = ["halfpolar"]
    patch_in(Warps(mat), coords_used)
    lo, hi = np.radians(args.lo), np.radians(args.hi)
    angles = [lo] + [float(np.arccos((1 - f) * np.cos(lo) + f * np.cos(hi))) for f in (0.25, 0.5, 0.75)] + [hi]
    draws = [ReferencePoints(mat, spherical_dir(t, 0.0), ideal, 512, 7) for t in angles]
    floors = [d.rv(ideal)[0] for d in draws]
    width = lobe_width_of(mat, ideal)
    for coords in ("halfpolar", "s"):
        coords_used[0] = coords
        tab = tabulate.build_tables(mat, ideal, [lo, hi], args.cells, args.cells, coords="halfpolar", window=None,
                                    lobe_width=None if coords == "s" else width)
        tab.backend = "numpy"
        ratios = [d.rv(tab)[0] / f for d, f in zip(draws, floors)]
        wo, pdf = tab.sample(spherical_dir(angles[2], 0.0), np.random.default_rng(3).random((1 << 16, 2)))
        lost = np.mean((wo[:, 2] <= 0) | ~(pdf > 0))
        print(f"{mat.name} {args.cells}² pair {args.lo}/{args.hi} over {coords}: rv / the ideal's at " + ", ".join(
            f"{np.degrees(t):.3f}: {r:.2f}" for t, r in zip(angles, ratios)) + f"; lost at the midpoint {lost:.4f}",
              flush=True)


if __name__ == "__main__":
    main()
