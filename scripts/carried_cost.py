"""What the carried blend costs in Cycles' OSL back end, against the same tables at fixed cells.

A table file baked from an isotropic RGL file with its carried intervals (tables.meta["carried"]:
`flowbsdf bake`, or tables_acceptance.py --out), its carry texture written beside it; a sphere
(64 x 64, box filter) in two scenes: a constant world (the tables' sample and the portal only)
and the same with a point lamp (+ next-event estimation: the tables' eval for MIS). Per scene,
with the Carried texture and without (moved aside: the node reads it by name at every render): CPU time of this process
(Cycles' threads) per spp from two sample counts (each render's fixed cost cancels), the best of
--repeat interleaved rounds (the machine is shared), and the ratio carried / fixed.

    .venv/bin/python scripts/carried_cost.py TABLES.exr RGL_FILE.bsdf [--repeat 2]
"""
import argparse
import contextlib
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import cycles_scenes as cs  # noqa: E402
from bake.export.derived import ensure_carry_export, ensure_osl_export  # noqa: E402
from bake.materials import open_material  # noqa: E402

SPP = (16, 48)


def render_seconds(tables, carried, lamp, spp):
    import bpy
    from blender_addon.render import node as lb
    sc = cs.reset(64, 64, spp=spp)
    cs.ortho_camera(sc, scale=2.2)
    cs.set_world(sc, (0.2, 0.2, 0.2) if lamp else (1.0, 1.0, 1.0))
    mat = bpy.data.materials.new("m")
    node = lb.assign_learned_bsdf(mat, tables.stem, tables)
    lb.set_backend(sc, "osl")
    cs.add_sphere(sc, mat)
    if lamp:
        light = bpy.data.lights.new("lamp", type='POINT')
        light.energy = 500.0
        ob = bpy.data.objects.new("lamp", light)
        ob.location = (2.0, -1.0, 3.0)
        sc.collection.objects.link(ob)
    assert lb.node_state(node, sc).text == "OSL" + (", carried blend" if carried else "") + ", exact", lb.node_status(node, sc)
    t0 = time.process_time()
    cs.render(sc)
    return time.process_time() - t0


def without(texture):
    """The carry texture moved aside while a render runs (the node reads it by name at each render)."""
    @contextlib.contextmanager
    def aside():
        hidden = texture.with_name("." + texture.name)
        texture.rename(hidden)
        try:
            yield
        finally:
            hidden.rename(texture)
    return aside()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("tables", type=Path)
    p.add_argument("material", type=Path)
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args()
    from blender_addon.render import node as lb
    lb.register()
    ensure_osl_export(args.tables)
    texture = ensure_carry_export(args.tables, open_material(args.material))
    if texture is None:
        sys.exit(f"{args.tables} has no carried intervals (tables.meta['carried'])")
    print(f"{args.tables.name}: carry texture {texture.name} ({texture.stat().st_size / 1e6:.2f} MB on disk)")
    print("| scene | fixed cells, CPU s / spp | carried, CPU s / spp | carried / fixed |")
    print("|---|---|---|---|")
    for lamp in (False, True):
        best = {}
        for _ in range(args.repeat):
            for carried in (False, True):
                with (contextlib.nullcontext() if carried else without(texture)):
                    lo, hi = (render_seconds(args.tables, carried, lamp, spp) for spp in SPP)
                per = (hi - lo) / (SPP[1] - SPP[0])
                best[carried] = min(best.get(carried, per), per)
        print(f"| {'point lamp + dim world' if lamp else 'constant world'} | {best[False]:.3f} | {best[True]:.3f} | "
              f"{best[True] / best[False]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
