"""What the EEVEE-target Material Output saves EEVEE: render time of a small sphere whose
Learned BSDF group holds all its back ends (tables bound: OSL Script node, SVM graph, fit),
EEVEE rendering the group's BSDF output (before: one Material Output for every engine; EEVEE
compiles the whole group) or its EEVEE output (now: only the EEVEE fit's closures feed it).
Each render a new material (its own shader compilation), the two wirings interleaved, best of
--repeat; and the mean relative difference of their images (the same closures where the fit
has no EEVEE fit: the BSDF side's Mix Shaders pick the fit in EEVEE).

    .venv/bin/python scripts/eevee_compile_cost.py TABLES_DIR NAME [--repeat 2] [--px 32]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
import cycles_scenes as cs  # noqa: E402
from eevee_acceptance import engine_id, rel_mad, scene  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("tables_dir", type=Path)
    ap.add_argument("name")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--px", type=int, default=32)
    args = ap.parse_args()
    import bpy
    from blender_addon.render import node as lb
    lb.register()
    sc = scene(args.px, 16, 16)
    sc.render.engine = engine_id()
    sphere = cs.add_sphere(sc, None, segments=64, rings=32)
    lb.set_backend(sc, "fit")
    times, imgs = {"before": [], "now": []}, {}
    for i in range(args.repeat):
        for wiring in ("before", "now"):
            mat = bpy.data.materials.new(f"{wiring}{i}")
            node = lb.assign_learned_bsdf(mat, args.name, args.tables_dir / f"{args.name}.exr")
            if wiring == "before":      # one output for every engine, fed by the BSDF
                for n in [n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]:
                    if n.target == 'EEVEE':
                        mat.node_tree.nodes.remove(n)
                    else:
                        n.target = 'ALL'
            assert len(node.node_tree.nodes) > 50, "tables not bound: no SVM graph"
            sphere.data.materials.clear()
            sphere.data.materials.append(mat)
            t0 = time.perf_counter()
            imgs[wiring] = cs.render(sc)
            times[wiring].append(time.perf_counter() - t0)
            print(wiring, i, round(times[wiring][-1], 1), flush=True)
    n, hit = cs.sphere_view(args.px, args.px, 2.2)
    print({"best_seconds": {k: round(min(v), 1) for k, v in times.items()},
           "ratio_before_over_now": round(min(times["before"]) / min(times["now"]), 2),
           "image_difference": round(rel_mad(imgs["now"], imgs["before"], hit & (n[..., 2] > 0.1)), 4),
           "group_nodes": len(node.node_tree.nodes)})


if __name__ == "__main__":
    main()
