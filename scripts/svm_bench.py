"""Cost of the SVM back end (blender_addon/svm.py) per sample on the CPU, against the OSL back
end (blender_addon/osl/learned_bsdf.osl), a Diffuse BSDF and a Principled BSDF.

Scene: a smooth unit sphere filling an orthographic view, size x size pixels, under a constant
white world (a furnace: every path shades the sphere once, then leaves). One Cycles thread.
Each back end renders at 32 spp and at --spp, interleaved over --repeats rounds; the cost per
sample is the CPU time difference over the extra samples (sync, BVH and shader compilation
cancel out), per shaded sample (sphere pixels x extra spp); CPU time of the process, not wall
time, and the fastest run, as other jobs may share the cores. SVM, Diffuse and Principled render with
OSL off; the OSL back end (and a Diffuse with OSL on, for scale) with OSL on. Also reports the
SVM graph's node and lookup counts (node groups expanded, as Cycles compiles them) and the
time to build it in Python and to compile it (an 8 x 8 px, 1 spp render).

    .venv/bin/python scripts/svm_bench.py TABLES.exr [--spp 512] [--size 48] [--repeats 3]
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
from bake.osl_export import ensure_osl_export  # noqa: E402
from bake.svm_export import ensure_svm_export  # noqa: E402


def _materials(tables):
    """{back end: (OSL on?, nodes(tree) -> shader socket)}."""
    from blender_addon import node as lb
    from blender_addon import svm
    svm_texture, osl_texture = ensure_svm_export(tables), ensure_osl_export(tables)

    def bsdf(kind):
        def nodes(tree):
            return tree.nodes.new(kind).outputs[0]
        return nodes

    def osl(tree):
        script = lb.make_script_node(tree)
        script.inputs["Tables"].default_value = str(osl_texture)
        return script.outputs["BSDF"]
    return {"diffuse": (False, bsdf("ShaderNodeBsdfDiffuse")), "principled": (False, bsdf("ShaderNodeBsdfPrincipled")),
            "svm": (False, lambda tree: svm.build_svm_sampler(tree, svm_texture)), "osl": (True, osl),
            "diffuse (OSL on)": (True, bsdf("ShaderNodeBsdfDiffuse"))}


def _render_time(osl, nodes, size, spp):
    """(CPU seconds of the render call, sphere pixels) for one back end: the process's CPU
    time, all threads (the machine is shared: wall time would count other jobs)."""
    sc = cs.reset(size, size, spp=spp, osl=osl, threads=1)
    cs.ortho_camera(sc, scale=2.2)
    cs.set_world(sc, (1.0, 1.0, 1.0))
    cs.add_sphere(sc, cs.material_with(nodes))
    start = time.process_time()
    img = cs.render(sc)
    seconds = time.process_time() - start
    _, hit = cs.sphere_view(size, size, scale=2.2)
    assert np.all(np.isfinite(img)) and img[hit].mean() > 0.05, "the sphere rendered black"
    return seconds, int(hit.sum())


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", type=Path)
    parser.add_argument("--spp", type=int, default=512)
    parser.add_argument("--size", type=int, default=48)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", default="diffuse,principled,svm,osl,diffuse (OSL on)",
                        help="comma-separated subset of: diffuse, principled, svm, osl, diffuse (OSL on)")
    args = parser.parse_args()
    import bpy
    from blender_addon import svm
    materials = {name: m for name, m in _materials(args.tables).items() if name in args.backends.split(",")}

    tree = bpy.data.node_groups.new("count", "ShaderNodeTree")
    start = time.perf_counter()
    svm.build_svm_sampler(tree, ensure_svm_export(args.tables))
    built = time.perf_counter() - start
    nodes, lookups = svm.graph_counts(tree)
    compile_s = {}
    for name in ("diffuse", "svm"):
        osl, fn = _materials(args.tables)[name]
        compile_s[name] = _render_time(osl, fn, 8, 1)[0]
    print(f"SVM graph: {nodes} nodes, {lookups} texture lookups per sample, built in {built:.2f} s; "
          f"8x8 1-spp render {compile_s['svm']:.2f} CPU s (Diffuse {compile_s['diffuse']:.2f} s)")

    times = {name: {32: [], args.spp: []} for name in materials}
    pixels = 0
    for _ in range(args.repeats):
        for name, (osl, fn) in materials.items():
            for spp in (32, args.spp):
                seconds, pixels = _render_time(osl, fn, args.size, spp)
                times[name][spp].append(seconds)
    print(f"{args.size}x{args.size} sphere ({pixels} px), one thread, CPU seconds, fastest of {args.repeats} "
          f"(other jobs on the machine only ever slow a run down):")
    per_sample = {}
    for name, t in times.items():
        high, low = min(t[args.spp]), min(t[32])
        per_sample[name] = (high - low) / (pixels * (args.spp - 32)) * 1e9
        print(f"  {name:18s} {args.spp} spp {high:6.2f} s  ({' '.join(f'{x:.2f}' for x in t[args.spp])})   "
              f"{per_sample[name]:6.0f} ns per shaded sample")
    ratios = [(a, b) for a, b in (("svm", "osl"), ("svm", "principled"), ("osl", "principled"))
              if a in per_sample and b in per_sample]
    print("  " + ", ".join(f"{a} / {b} {per_sample[a] / per_sample[b]:.2f}" for a, b in ratios) + " (per sample)")


if __name__ == "__main__":
    main()
