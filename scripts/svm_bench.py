"""Cost per sample of the SVM back end (blender_addon/svm.py) on the CPU, against the OSL back
end (blender_addon/render/osl/learned_bsdf.osl), a Diffuse BSDF and a Principled BSDF; with --mse,
the equal-time image error of the SVM world mixture on a sphere under a sky with its sun.

Scene: a smooth unit sphere filling an orthographic view, size x size pixels, under a constant
white world (a furnace: every path shades the sphere once, then leaves; with --sky, the sky
below instead). One Cycles thread. Each back end renders at 32 spp and at --spp, interleaved
over --repeats rounds; the cost per sample is the CPU time difference over the extra samples
(sync, BVH and shader compilation cancel out), per shaded sample (sphere pixels x extra spp);
CPU time of the process, not wall time, and the fastest run, as other jobs may share the
cores. SVM, Diffuse and Principled render with OSL off; the OSL back end (and a Diffuse with
OSL on, for scale) with OSL on. "svm world" is the SVM graph with the world mixture of a
Sky Texture with its sun (strength 0.2, sun elevation 0.5, rotation 1.0; its world inputs
from blender_addon/render/world.bake_world_map: map 0.2, sun 0.3, tables 0.5). Also reports the
SVM graphs' node and lookup counts (node groups expanded, as Cycles compiles them; for the
mixture per technique, as only the chosen branch runs) and the time to build them in
Python and to compile them (an 8 x 8 px, 1 spp render).

--mse: the sphere under that sky (Cycles' world importance sampling on, Blender's default),
box pixel filter (the SVM's film-stratified u), 24 x 24 px; the reference a Diffuse BSDF 0.8
render at --ref-spp; each method ("svm world", "svm" the tables alone, "diffuse") at the
spp that costs what the Diffuse's --spp costs (from per-sample CPU costs measured at 64 and
512 spp, the fastest of 3), over --seeds seeds: the MSE over the sphere's pixels against
the reference (and its standard error), and the per-pixel variance over the seeds. The
tables are a learned Lambertian (albedo 0.8) when TABLES is "lambert".

    .venv/bin/python scripts/svm_bench.py TABLES.exr [--spp 512] [--size 48] [--repeats 3] [--sky]
    .venv/bin/python scripts/svm_bench.py lambert --mse [--spp 256] [--ref-spp 8192] [--seeds 8]
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import cycles_scenes as cs  # noqa: E402
from bake.export.derived import ensure_osl_export, ensure_svm_export  # noqa: E402


SKY = {"strength": 0.2, "sun_elevation": 0.5, "sun_rotation": 1.0}


def _set_sky(scene):
    """The scene's world: a Sky Texture with its sun (SKY), Cycles' world importance sampling on."""
    world = cs.set_world(scene)
    world.cycles.sampling_method = 'AUTOMATIC'
    tree = world.node_tree
    sky = tree.nodes.new("ShaderNodeTexSky")
    sky.sun_elevation, sky.sun_rotation = SKY["sun_elevation"], SKY["sun_rotation"]
    background = next(node for node in tree.nodes if node.type == 'BACKGROUND')
    tree.links.new(sky.outputs[0], background.inputs["Color"])
    background.inputs["Strength"].default_value = SKY["strength"]


def _sky_inputs(folder):
    """The world inputs of the sky (blender_addon/render/world.bake_world_map, its map in `folder`)."""
    from blender_addon.render import world
    scene = cs.reset(8, 8, spp=1, osl=False, threads=1)
    _set_sky(scene)
    return world.bake_world_map(scene, folder)


def _lambert(folder):
    """Tables of a Lambertian of albedo 0.8 (as tests/test_svm.py's)."""
    from bake.core.ideal import IdealSampler
    from bake.materials import open_material
    from bake.core.tabulate import build_tables
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.8})
    tab = build_tables(mat, IdealSampler(mat, resolution=64), np.radians([0.0, 30.0, 60.0, 80.0, 89.5]),
                       rows=24, cols=24, grid=96)
    tab.meta["material"] = "lambert"
    tab.save(folder / "lambert.exr")
    return folder / "lambert.exr"


def _materials(tables, world):
    """{back end: (OSL on?, nodes(tree) -> shader socket)}."""
    from blender_addon.render import osl_script
    from blender_addon import svm
    svm_texture, osl_texture = ensure_svm_export(tables), ensure_osl_export(tables)

    def bsdf(kind):
        def nodes(tree):
            node = tree.nodes.new(kind)
            if kind == "ShaderNodeBsdfDiffuse":
                node.inputs["Color"].default_value = (0.8, 0.8, 0.8, 1.0)
            return node.outputs[0]
        return nodes

    def osl(tree):
        script = osl_script.make_script_node(tree)
        script.inputs["Tables"].default_value = str(osl_texture)
        return script.outputs["BSDF"]
    return {"diffuse": (False, bsdf("ShaderNodeBsdfDiffuse")), "principled": (False, bsdf("ShaderNodeBsdfPrincipled")),
            "svm": (False, lambda tree: svm.build_svm_sampler(tree, svm_texture)),
            "svm world": (False, lambda tree: svm.build_svm_sampler(tree, svm_texture, world=world)),
            "osl": (True, osl), "diffuse (OSL on)": (True, bsdf("ShaderNodeBsdfDiffuse"))}


def _render(osl, nodes, size, spp, sky=False, seed=0, box=False):
    """(CPU seconds of the render call, image, sphere mask) for one back end: the process's
    CPU time, all threads (the machine is shared: wall time would count other jobs)."""
    sc = cs.reset(size, size, spp=spp, osl=osl, threads=1, seed=seed)
    if box:
        sc.cycles.pixel_filter_type = 'BOX'
    cs.ortho_camera(sc, scale=2.2)
    if sky:
        _set_sky(sc)
    else:
        cs.set_world(sc, (1.0, 1.0, 1.0))
    cs.add_sphere(sc, cs.material_with(nodes))
    start = time.process_time()
    img = cs.render(sc)
    seconds = time.process_time() - start
    _, hit = cs.sphere_view(size, size, scale=2.2)
    assert np.all(np.isfinite(img)) and img[hit].mean() > 0.05, "the sphere rendered black"
    return seconds, img, hit


def _render_time(osl, nodes, size, spp, sky=False):
    seconds, _, hit = _render(osl, nodes, size, spp, sky)
    return seconds, int(hit.sum())


def _counts(tables, world):
    """Lines on the SVM graphs: nodes, lookups (per technique for the mixture), build time."""
    import bpy
    from blender_addon import svm
    texture = ensure_svm_export(tables)
    lines, lookups = [], {}
    for name, kind in (("svm", None), ("svm world", world), ("tables pdf", "pdf")):
        tree = bpy.data.node_groups.new("count", "ShaderNodeTree")
        start = time.perf_counter()
        if kind == "pdf":
            svm.tables_pdf_graph(tree, texture, tree.nodes.new("ShaderNodeCombineXYZ").outputs[0])
        else:
            svm.build_svm_sampler(tree, texture, world=kind)
        built = time.perf_counter() - start
        nodes, lookups[name] = svm.graph_counts(tree)
        lines.append(f"{name}: {nodes} nodes, {lookups[name]} texture lookups, built in {built:.2f} s")
    steps = svm.world_layout(world["World"])["steps"]
    c_world, c_sun = world["WorldShare"], world["SunShare"]
    per = {"tables": lookups["svm"] + 1, "map": lookups["tables pdf"] + steps + 4, "sun": lookups["tables pdf"] + 1}
    mean = (1 - c_world - c_sun) * per["tables"] + c_world * per["map"] + c_sun * per["sun"]
    lines.append(f"svm world lookups per sample by technique (only its branch runs): tables {per['tables']}, "
                 f"map {per['map']} ({steps} search steps), sun {per['sun']}; mean {mean:.1f} at shares "
                 f"tables {1 - c_world - c_sun:.2f}, map {c_world:.2f}, sun {c_sun:.2f}")
    return lines


def _mse(args, tables, world):
    """The equal-time error of each method on the sky+sun sphere (module docstring)."""
    size = 24
    materials = _materials(tables, world)
    methods = ("svm world", "svm", "diffuse")
    start = time.process_time()
    _, reference, hit = _render(*materials["diffuse"], size, args.ref_spp, sky=True, seed=12345, box=True)
    print(f"reference: Diffuse BSDF at {args.ref_spp} spp ({time.process_time() - start:.0f} CPU s); "
          f"sphere mean (red, as below) {reference[hit][:, 0].mean():.4f}")
    cost = {}
    for name in methods:
        t = {spp: min(_render(*materials[name], size, spp, sky=True, box=True)[0] for _ in range(3))
             for spp in (64, 512)}
        cost[name] = (t[512] - t[64]) / 448
    print("CPU s per spp (24 x 24 px): " + ", ".join(f"{name} {cost[name] * 1e3:.2f} ms" for name in methods))
    for name in methods:
        spp = max(1, round(args.spp * cost["diffuse"] / cost[name]))
        imgs = np.array([_render(*materials[name], size, spp, sky=True, seed=seed, box=True)[1][..., 0]
                         for seed in range(args.seeds)])
        errors = ((imgs - reference[..., 0]) ** 2)[:, hit].mean(1)
        variance = imgs.var(0, ddof=1)[hit].mean()
        print(f"  {name:10s} {spp:5d} spp: MSE {errors.mean():.3g} +- {errors.std(ddof=1) / np.sqrt(len(errors)):.2g}"
              f"  per-pixel variance over seeds {variance:.3g}  sphere mean {imgs[:, hit].mean():.4f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tables", help='a table file, or "lambert" (a learned Lambertian, made here)')
    parser.add_argument("--spp", type=int, default=512)
    parser.add_argument("--size", type=int, default=48)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", default="diffuse,principled,svm,svm world,osl,diffuse (OSL on)",
                        help="comma-separated subset of: diffuse, principled, svm, svm world, osl, diffuse (OSL on)")
    parser.add_argument("--sky", action="store_true", help="render under the sky with its sun, not the furnace")
    parser.add_argument("--mse", action="store_true", help="the equal-time error on the sky+sun sphere instead")
    parser.add_argument("--ref-spp", type=int, default=8192)
    parser.add_argument("--seeds", type=int, default=8)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="svm_bench_"))
    tables = _lambert(folder) if args.tables == "lambert" else Path(args.tables)
    world = _sky_inputs(folder)
    print(f"world inputs: {world}")
    if args.mse:
        _mse(args, tables, world)
        return
    for line in _counts(tables, world):
        print(line)
    compile_s = {name: _render_time(*_materials(tables, world)[name], 8, 1)[0]
                 for name in ("diffuse", "svm", "svm world")}
    print("8x8 1-spp render (compilation): " + ", ".join(f"{k} {v:.2f} CPU s" for k, v in compile_s.items()))
    materials = {name: m for name, m in _materials(tables, world).items() if name in args.backends.split(",")}
    times = {name: {32: [], args.spp: []} for name in materials}
    pixels = 0
    for _ in range(args.repeats):
        for name, (osl, fn) in materials.items():
            for spp in (32, args.spp):
                seconds, pixels = _render_time(osl, fn, args.size, spp, args.sky)
                times[name][spp].append(seconds)
    print(f"{args.size}x{args.size} sphere ({pixels} px) under {'the sky' if args.sky else 'a white furnace'}, "
          f"one thread, CPU seconds, fastest of {args.repeats} (other jobs on the machine only ever slow a run down):")
    per_sample = {}
    for name, t in times.items():
        high, low = min(t[args.spp]), min(t[32])
        per_sample[name] = (high - low) / (pixels * (args.spp - 32)) * 1e9
        print(f"  {name:18s} {args.spp} spp {high:6.2f} s  ({' '.join(f'{x:.2f}' for x in t[args.spp])})   "
              f"{per_sample[name]:6.0f} ns per shaded sample")
    ratios = [(a, b) for a, b in (("svm world", "svm"), ("svm", "osl"), ("svm world", "osl"), ("svm", "principled"),
                                  ("osl", "principled")) if a in per_sample and b in per_sample]
    print("  " + ", ".join(f"{a} / {b} {per_sample[a] / per_sample[b]:.2f}" for a, b in ratios) + " (per sample)")


if __name__ == "__main__":
    main()
