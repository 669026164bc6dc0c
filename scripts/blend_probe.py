"""What blending two incident bins loses half-way, in which coordinates (issue 22, item 4).

    .venv/bin/python scripts/blend_probe.py MATERIAL LO_DEG HI_DEG [--cells N]

Tables blend their two nearest bins' densities at fixed cell coordinates (one layout for all
bins: the mixture). At the pair's cos-midpoint this prints the rv over the ideal tabulation's
there (metrics.ReferencePoints: 512² of the ideal's draws, seed 7) of the 50/50 mixture of the
two bins' exact targets (the 256² ideal tabulations at LO and HI) blended over:
  - wo (fixed directions),
  - halfpolar (a, b) (tables.py's isotropic coordinates: what the tables approach),
  - the half vector h,
and for RGL files over the file's own warped coordinates s (RGLMaterial eval's step 4, where its
`rgb` table is read: measured slices blend at fixed s), where the targets are N² histograms of
1536² draws (uniform cells over s hold the target to within a few times the ideal there: the
line says the histogram's own rv and the mixture's over it).
A loss in every coordinate is intrinsic to blending bins that far apart; a loss over halfpolar
that s does not have is a feature that moves with theta_i (measured: chm_mint at 84.64/85.17,
halfpolar 2.06x, s 1.06x its own; 83.59/84.64: 20.8x and 1.37x).
"""
import argparse

import numpy as np

from bake.maths.geometry import spherical_dir
from bake.core.halfvector import polar_from_ab, polar_to_ab
from bake.core.ideal import IdealSampler
from bake.materials import open_material
from bake.materials.rgl import RGLMaterial, WarpedCoords, shared_dir
from bake.core.metrics import ReferencePoints


def each(wi, n):
    return np.broadcast_to(wi, (n, 3))


class Blend:
    """pdf of the mixture of the bins' densities `pdfs` (functions of wo at their wi) with weights
    `ws`, blended over coordinates (to_coords at the midpoint, from_coords at each bin)."""

    def __init__(self, wm, wis, ws, pdf, coords):
        self.wm, self.wis, self.ws, self.pdf_at, self.coords = wm, wis, ws, pdf, coords

    def pdf(self, wi, wo):
        n = len(wo)
        if self.coords == "wo":
            return sum(w * self.pdf_at(each(d, n), wo) for w, d in zip(self.ws, self.wis))
        if self.coords == "halfpolar":
            a, b, jac_mid = polar_to_ab(each(self.wm, n), wo)
            out = 0.0
            for w, d in zip(self.ws, self.wis):
                wo_k, jac_k = polar_from_ab(each(d, n), a, b)
                out = out + w * self.pdf_at(each(d, n), wo_k) * jac_k
            return out / jac_mid
        h = self.wm[None, :] + wo          # the half vector: d omega = 4 (wi . h) d omega_h
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        out = 0.0
        for w, d in zip(self.ws, self.wis):
            c = h @ d
            wo_k = 2 * c[:, None] * h - d[None, :]
            ok = (wo_k[:, 2] > 0) & (c > 0)
            p = self.pdf_at(each(d, n), np.where(ok[:, None], wo_k, [0.0, 0.0, 1.0])) * c
            out = out + w * np.where(ok, p, 0.0)
        return out / (h @ self.wm)


class OverS:
    """The histogram densities over s (cells²) of f·cos at `parts` [(wi, weight)], as a pdf at wm."""

    def __init__(self, mat, ideal, wm, parts, cells):
        self.warp, self.wm, self.cells, self.hists = WarpedCoords(mat), wm, cells, []
        for wi, w in parts:
            d = ReferencePoints(mat, wi, ideal, 1536, 11)
            s, _ = self.warp.to_s(wi, d.wo)
            hist, _, _ = np.histogram2d(s[:, 0], s[:, 1], bins=cells, range=[[0, 1], [0, 1]], weights=d.g / d.h)
            hist = hist / hist.sum() * cells * cells
            self.hists.append((np.maximum(hist, 1e-3 * hist.mean()), w))   # every cell positive

    def pdf(self, wi, wo):
        s, jac = self.warp.to_s(self.wm, wo)
        i, j = (np.clip((s * self.cells).astype(int), 0, self.cells - 1)).T
        return sum(w * h[i, j] for h, w in self.hists) / jac


def main():
    p = argparse.ArgumentParser()
    p.add_argument("material", help="a shared RGL file's name (e.g. chm_mint_rgb) or a path")
    p.add_argument("lo", type=float)
    p.add_argument("hi", type=float)
    p.add_argument("--cells", type=int, default=96, help="the s histograms' cells per side")
    args = p.parse_args()
    path = shared_dir() / f"{args.material}.bsdf" if "/" not in args.material else args.material
    mat = open_material(path)
    ideal = IdealSampler(mat)
    lo, hi = np.radians(args.lo), np.radians(args.hi)
    mid = float(np.arccos(0.5 * (np.cos(lo) + np.cos(hi))))
    wm, wis = spherical_dir(mid, 0.0), [spherical_dir(lo, 0.0), spherical_dir(hi, 0.0)]
    draws = ReferencePoints(mat, wm, ideal, 512, 7)
    rv_ideal = draws.rv(ideal)[0]
    print(f"{mat.name}, bins {args.lo} and {args.hi} deg, at their cos-midpoint {np.degrees(mid):.3f}: "
          f"the ideal's rv {rv_ideal:.4g}")
    for coords in ("wo", "halfpolar", "h"):
        rv = draws.rv(Blend(wm, wis, (0.5, 0.5), ideal.pdf, coords))[0]
        print(f"  the bins' targets blended over {coords}: {rv / rv_ideal:.2f}x the ideal's rv", flush=True)
    if isinstance(mat, RGLMaterial) and mat.isotropic:
        own = draws.rv(OverS(mat, ideal, wm, [(wm, 1.0)], args.cells))[0]
        mix = draws.rv(OverS(mat, ideal, wm, [(wis[0], 0.5), (wis[1], 0.5)], args.cells))[0]
        print(f"  over the file's s ({args.cells}² histograms): the midpoint's own {own / rv_ideal:.2f}x, "
              f"the bins' blended {mix / rv_ideal:.2f}x: {mix / own:.2f}x its own")


if __name__ == "__main__":
    main()
