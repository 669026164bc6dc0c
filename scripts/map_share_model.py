"""How much of the portal's one-sample mixture should draw from the world map (blender_addon/
world.py SHARE, SMALL_SUN_SHARE): a numpy model of the Learned BSDF's portal estimator.

A sphere seen along -y (wi = +y at 52 normals over its visible disc), lit by an equirectangular
world image (no occlusion: the sphere is convex); per normal, 2^14 directions drawn from the
mixture (map with probability c, else the tables), weight lum(f cos) L / (c p_map + (1 - c)
p_tables), as the SVM graph and the OSL shader weigh them. Prints each material's mean per-normal
variance per sample at each c, over the variance at c = 0.5. A model, not the render: on the
lights acceptance's sky it put c = 0.8 at 0.31x (paper_white) and 0.42x (cm_military_green) of
c = 0.5's variance, Cycles' SVM renders measured 0.87x and 0.99x (blender_addon/render/world.py).

    .venv/bin/python scripts/map_share_model.py WORLD.exr TABLES.exr... [--shares 0.2,0.5,0.8]
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bake.maths.geometry import LUMINANCE  # noqa: E402
from bake.core.table_files import open_tables  # noqa: E402
from bake.export.world_map import WorldMap  # noqa: E402


def read_rgb(path):
    import OpenEXR
    with OpenEXR.File(str(path)) as exr:
        ch = exr.channels()
        px = ch["RGB"].pixels if "RGB" in ch else ch["RGBA"].pixels[..., :3]
    return np.asarray(px, np.float64)


def normals(k=8):
    g = np.linspace(-0.9, 0.9, k)
    return [np.array([x, np.sqrt(1.0 - x * x - z * z), z]) for x in g for z in g if x * x + z * z < 0.85]


def variance(tables, wm, radiance, n, c, rng, samples):
    """Variance per sample of the mixture's estimate at normal n (world space)."""
    wi_w = np.array([0.0, 1.0, 0.0])
    tx = wi_w - (wi_w @ n) * n
    tx /= np.linalg.norm(tx)
    to_local = np.stack([tx, np.cross(n, tx), n])
    wi = to_local @ wi_w
    u = rng.random((samples, 3))
    from_map = u[:, 2] < c
    dirs = np.empty((samples, 3))
    dirs[from_map] = wm.sample(u[from_map, :2])[0]
    dirs[~from_map] = tables.sample(wi, u[~from_map, :2])[0] @ to_local
    wo = dirs @ to_local.T
    up = wo[:, 2] > 0
    fcos, p_tables = np.zeros(samples), np.zeros(samples)
    fcos[up] = (tables.eval(wi, wo[up]) @ LUMINANCE) * wo[up, 2]
    p_tables[up] = tables.pdf(wi, wo[up])
    q = c * wm.pdf(dirs) + (1.0 - c) * p_tables
    row, col = wm._pixel(dirs)
    w = np.where(up & (q > 0), fcos * radiance[row, col] / np.where(q > 0, q, 1.0), 0.0)
    return w.var()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("world")
    ap.add_argument("tables", nargs="+")
    ap.add_argument("--shares", default="0.2,0.35,0.5,0.65,0.8,0.9")
    ap.add_argument("--samples", type=int, default=1 << 14)
    args = ap.parse_args(argv)
    img = read_rgb(args.world)
    wm, radiance = WorldMap(img), img @ LUMINANCE
    shares = [float(c) for c in args.shares.split(",")]
    print(f"{args.world}: {img.shape[1]} x {img.shape[0]}, peak {wm.peak:.3g}x a uniform sphere's pdf")
    for path in args.tables:
        tables = open_tables(path)
        rng = np.random.default_rng(1)
        var = {c: np.mean([variance(tables, wm, radiance, n, c, rng, args.samples) for n in normals()])
               for c in shares + [0.5]}
        print(f"{Path(path).stem}: " + "  ".join(f"c={c:g} {var[c] / var[0.5]:.3f}" for c in shares))


if __name__ == "__main__":
    main()
