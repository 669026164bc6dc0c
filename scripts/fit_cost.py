"""What the closure fit costs Cycles per sample: the Learned BSDF's fit back end (FIT_VERSION 5:
a Diffuse BSDF + three GGX Glossy BSDFs, two with the view's tangent and anisotropy) against
the previous fit's graph (FIT_VERSION 4: Diffuse + one isotropic GGX, its parameters piecewise
linear in Facing as fit_nodes.piecewise builds them: rebuilt here from an old fit file) and a
Principled BSDF (closure_fit.principled_params), rendered with Blender's default SVM.

A sphere (64 x 64, box filter, the acceptance's perspective camera) in two scenes: "constant"
(a grey world) and "studio" (scripts/lights_acceptance.py: an area lamp + a point lamp with a
radius + a dim world). CPU time of this process (Cycles' threads) per spp from two sample
counts (each render's fixed cost cancels), the best of --repeat interleaved rounds.

    .venv/bin/python scripts/fit_cost.py TABLES.exr OLD_FIT.json [--repeat 2]
"""
import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import cycles_acceptance as ca  # noqa: E402
import cycles_scenes as cs  # noqa: E402
import lights_acceptance as la  # noqa: E402
from bake.export.closure_fit import load_fit  # noqa: E402
from bake.export.derived import ensure_fit  # noqa: E402

KINDS = ("principled", "fit v4", "fit")


def old_fit_material(fit):
    """A material rendering a FIT_VERSION 4 fit as that version's node did."""
    from blender_addon.render import fit_nodes
    def nodes(tree):
        facing = tree.nodes.new("ShaderNodeLayerWeight")
        facing.inputs["Blend"].default_value = 0.5
        x = facing.outputs["Facing"]
        kd = fit_nodes.piecewise(tree, x, fit["x"], fit["diffuse"], (0, 0))
        ks = fit_nodes.piecewise(tree, x, fit["x"], fit["specular"], (0, -500))
        r = fit_nodes.piecewise(tree, x, fit["x"], [[v] * 3 for v in fit["roughness"]], (0, -1000))
        diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
        tree.links.new(kd, diffuse.inputs["Color"])
        glossy = tree.nodes.new("ShaderNodeBsdfAnisotropic")
        glossy.distribution = 'GGX'
        sep = tree.nodes.new("ShaderNodeSeparateXYZ")
        tree.links.new(r, sep.inputs[0])
        tree.links.new(sep.outputs[0], glossy.inputs["Roughness"])
        tree.links.new(ks, glossy.inputs["Color"])
        add = tree.nodes.new("ShaderNodeAddShader")
        tree.links.new(diffuse.outputs[0], add.inputs[0])
        tree.links.new(glossy.outputs[0], add.inputs[1])
        return add.outputs[0]
    return cs.material_with(nodes, "fit v4")


def per_spp(kind, tables, fit, old, setup, lo, hi):
    if kind == "fit v4":
        sc, _ = ca.cycles_scene("principled", tables.stem, tables, None, 64, lo, fit=fit, setup=setup, native=True)
        sphere = next(ob for ob in sc.objects if ob.type == 'MESH')
        sphere.data.materials.clear()
        sphere.data.materials.append(old_fit_material(old))
    else:
        sc, _ = ca.cycles_scene(kind, tables.stem, tables, None, 64, lo, fit=fit, setup=setup, native=True)
    cs.render(sc)                               # warm: compilation, textures
    return cs.seconds_per_spp(sc, lo, hi, clock=time.process_time)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tables", type=Path)
    ap.add_argument("old_fit", type=Path)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--lo", type=int, default=16)
    ap.add_argument("--hi", type=int, default=96)
    args = ap.parse_args(argv)
    fit = load_fit(ensure_fit(args.tables))
    old = json.loads(args.old_fit.read_text())
    assert old.get("version") == 4, "OLD_FIT must be a FIT_VERSION 4 fit file"
    scenes = {"constant": lambda sc: cs.set_world(sc, color=(0.5, 0.5, 0.5)),
              "studio": la.setups(None, None)["studio"]}
    best = {}
    for _ in range(args.repeat):
        for scene, setup in scenes.items():
            for kind in KINDS:
                t = per_spp(kind, args.tables, fit, old, setup, args.lo, args.hi)
                best[scene, kind] = min(best.get((scene, kind), float("inf")), t)
    print(f"{args.tables.stem}, 64 x 64, CPU ms per spp (all threads) from {args.lo} and {args.hi} spp, "
          f"best of {args.repeat}")
    print("| scene | " + " | ".join(KINDS) + " | fit / fit v4 | fit / Principled |")
    print("|---" * (len(KINDS) + 3) + "|")
    for scene in scenes:
        b = {k: best[scene, k] for k in KINDS}
        print(f"| {scene} | " + " | ".join(f"{1e3 * b[k]:.2f}" for k in KINDS)
              + f" | {b['fit'] / b['fit v4']:.2f} | {b['fit'] / b['principled']:.2f} |")


if __name__ == "__main__":
    main()
