"""What each lamp costs the OSL back end: render time per sample with 0..8 lamps.

A learned plastic sphere under a constant world with N area lamps (N = 0, 1, 2, 4, 8),
rendered with the OSL back end and, side by side, with a Principled BSDF (Cycles' own light
sampling); renders interleaved, the fastest of --repeat kept (the machine is shared). Prints
the time per sample (from two sample counts: each render's fixed cost cancels) and the ratio
to Principled, and the added cost per lamp.

    .venv/bin/python scripts/lamp_cost.py [--size 48] [--spp 128] [--repeat 3]
"""
import argparse
import math
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import cycles_scenes as cs  # noqa: E402


def scene(tables, lamps, principled, size, spp):
    import bpy
    from blender_addon.render import node as lb
    sc = cs.reset(size, size, spp=spp, threads=1)
    sc.cycles.pixel_filter_type = 'BOX'
    cs.ortho_camera(sc, scale=2.4)
    cs.set_world(sc, (0.2, 0.2, 0.2))
    if principled:
        mat = cs.material_with(lambda t: t.nodes.new("ShaderNodeBsdfPrincipled").outputs[0], "principled")
    else:
        mat = bpy.data.materials.new("learned")
        lb.assign_learned_bsdf(mat, tables.stem, tables)
    cs.add_sphere(sc, mat, segments=64, rings=32)
    for k in range(lamps):
        light = bpy.data.lights.new(f"lamp{k}", 'AREA')
        light.energy, light.size = 30.0, 0.5
        ob = bpy.data.objects.new(f"lamp{k}", light)
        a = 2 * math.pi * k / max(lamps, 1)
        ob.location = (3 * math.cos(a), 3 * math.sin(a), 2.0)
        ob.rotation_euler = (math.radians(50), 0.0, a + math.pi / 2)
        sc.collection.objects.link(ob)
    if not principled:
        lb.sync(sc)
    return sc


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    import bpy
    from blender_addon.render import node as lb
    lb.register()
    folder = Path(tempfile.mkdtemp(prefix="flowbsdf_lampcost_"))
    tables = folder / "plastic.exr"
    cs.small_tables({"kind": "analytic", "model": "plastic", "albedo": [0.7, 0.1, 0.08], "alpha": 0.12},
                    "plastic", folder)
    best = {}
    lo, hi = args.spp // 4, args.spp
    for _ in range(args.repeat):
        for lamps in (0, 1, 2, 4, 8):
            for principled in (False, True):
                sc = scene(tables, lamps, principled, args.size, lo)
                cs.render(sc)                        # warm: compile, world map, textures
                # net of each render's fixed cost (scene sync, OSL setup: ~1.5 s a frame here)
                key = (lamps, principled)
                best[key] = min(best.get(key, float("inf")), cs.seconds_per_spp(sc, lo, hi))
                bpy.ops.wm.read_factory_settings(use_empty=True)
    print(f"{args.size}x{args.size}, ms per sample per frame from {lo} and {hi} spp, 1 thread, best of {args.repeat}")
    print("| lamps | OSL ms/spp | Principled ms/spp | OSL / Principled |")
    print("|---|---|---|---|")
    for lamps in (0, 1, 2, 4, 8):
        o, p = best[(lamps, False)], best[(lamps, True)]
        print(f"| {lamps} | {1e3 * o:.2f} | {1e3 * p:.2f} | {o / p:.2f} |")
    per = (best[(8, False)] - best[(1, False)]) / 7
    print(f"added per lamp past the first (OSL): {1e3 * per:.3f} ms/spp = "
          f"{per / best[(1, False)]:.1%} of a one-lamp sample")

if __name__ == "__main__":
    main()
