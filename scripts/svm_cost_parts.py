"""Issue 52: where the SVM back end's time per sample goes. The add-on's SVM graph (blender_addon/render/svm/)
built with parts switched off, side by side with Principled and the fit (OSL off), per scene.

Variants (the graph patched while the node builds it; some render a different, even biased, image:
they measure cost, not a look):
  svm        the node's SVM back end as is
  -match     the control variate unmatched (svm._matching False: the baked betas, no match lookups)
  fcv0       f_cv in the portal's rest a constant 0 (the in-graph f_cv's cost; biased)
  untilted   the fit's closures and f_cv untilted (svm.CV_TILTS False)
  -cv        no control variate (the portal mixture alone)
  -mix       no mixture (world None: the tables' sample; the control variate then off)
  sampler    the tables' sampler and a portal alone (world None, no control variate)
  before     the graph as --before's package (another checkout's blender_addon/render/svm/, or an svm.py
             of before issue 53) builds it (a cut's saving, side by side; its node groups named apart)
  portal     a Ray Portal of constant colour toward the mirror direction: a portal bounce's rays
             and a trivial graph (the floor of any portal back end)
One Cycles thread (with two, a worker waiting for the other counted as CPU time). Per scene (constant
world, the acceptance's HDRI, studio lamps) and variant: CPU time of this process per spp from the
fastest of --inner renders at --lo and at --hi spp (each render's fixed cost cancels), the best of
--repeat interleaved rounds (the machine is shared); and the graph's node and texture lookup counts
(groups expanded, every branch: the SVM interpreter runs only the branch taken). A graph without the
node named svm.FILM is not taken for the SVM back end (binding.has_svm: the node renders the fit instead).

    .venv/bin/python scripts/svm_cost_parts.py [--tables T.exr] [--variants svm,before] [--repeat 3]
"""
import argparse
import contextlib
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import backend_cost  # noqa: E402
import cycles_acceptance as ca  # noqa: E402
import cycles_scenes as cs  # noqa: E402
from bake.export.closure_fit import load_fit  # noqa: E402
from bake.export.derived import ensure_fit  # noqa: E402

BUILT = []      # the SVM back end's output socket, as built
VARIANTS = ("principled", "fit", "svm", "-match", "fcv0", "untilted", "-cv", "-mix", "sampler", "portal")


@contextlib.contextmanager
def patched(variant):
    """The svm package with the variant's part switched off while the graph is built and rendered
    (a name is patched in the modules that look it up: the face for node.py's, the package's
    modules for their own)."""
    from blender_addon.render import svm
    from blender_addon.render.svm import control_variate, graph, mixture, shader
    modules = (svm, control_variate, mixture, shader)
    saved = [(m, dict(vars(m))) for m in modules]
    build = svm.build_svm_sampler
    BUILT.clear()

    def without_world(tree, texture, tangent=None, location=(0.0, 0.0), world=None, cv=None):
        return build(tree, texture, tangent, location=location, cv=None if variant == "sampler" else cv)

    def portal_only(tree, texture, tangent=None, location=(0.0, 0.0), world=None, cv=None):
        g = graph._Graph(tree, location)
        g.node("ShaderNodeCombineXYZ", name=svm.FILM)      # (the node's mark of an SVM graph: binding.has_svm)
        geometry = g.node("ShaderNodeNewGeometry")
        d = g.vmath('REFLECT', g.scale(geometry.outputs["Incoming"], -1.0), geometry.outputs["Normal"])
        portal = g.node("ShaderNodeBsdfRayPortal")
        g.set(portal.inputs["Color"], (0.5, 0.5, 0.5, 1.0))
        g.set(portal.inputs["Position"], geometry.outputs["Position"])
        g.set(portal.inputs["Direction"], d)
        return portal.outputs["BSDF"]
    try:
        if variant == "-match":
            shader._matching = mixture._matching = lambda mix, matchable: False
        elif variant == "fcv0":
            control_variate._cv_fcos = lambda g, cv, wi, n, d: (0.0, 0.0, 0.0)
        elif variant == "untilted":
            svm.CV_TILTS = control_variate.CV_TILTS = False
        elif variant == "-cv":
            shader._cv_switched = lambda *args, **kw: None
        elif variant in ("-mix", "sampler"):
            svm.build_svm_sampler = without_world
        elif variant == "portal":
            svm.build_svm_sampler = portal_only
        elif variant == "before":
            svm.build_svm_sampler = _before().build_svm_sampler
        inner = svm.build_svm_sampler

        def recorded(*args, **kw):
            BUILT.append(inner(*args, **kw))
            return BUILT[-1]
        svm.build_svm_sampler = recorded
        yield
    finally:
        for module, values in saved:
            for key, value in values.items():
                setattr(module, key, value)


def _before(path=None):
    """The SVM graph builder of another checkout (--before: a package folder, or before issue
    53 the module blender_addon/svm.py), as blender_addon.render.svm_before; its node groups get
    names of their own (a graph of the same GRAPH_VERSION would reuse this checkout's)."""
    import importlib.util
    name = "blender_addon.render.svm_before"
    if name not in sys.modules:
        if path is None:
            raise SystemExit("the variant `before` needs --before (another checkout's blender_addon/render/svm)")
        path = Path(path)
        if path.is_dir():
            spec = importlib.util.spec_from_file_location(name, path / "__init__.py",
                                                          submodule_search_locations=[str(path)])
        else:       # (the module's `from . import sockets` then finds blender_addon.render.sockets)
            spec = importlib.util.spec_from_file_location(name, path)
        sys.modules[name] = module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        for key, sub in list(sys.modules.items()):
            if (key == name or key.startswith(name + ".")) and hasattr(sub, "GROUP_PREFIX"):
                sub.GROUP_PREFIX = sub.GROUP_PREFIX.rstrip() + " before "
    return sys.modules[name]


def graph_nodes(socket):
    """(nodes, texture lookups) upstream of the SVM back end's output socket, itself included:
    groups expanded, image nodes of one image at one place counted as one lookup (Cycles merges
    them: tests/test_svm.py test_cycles_merges_the_lookups_of_one_texel)."""

    def source(socket, path, outer):
        # what feeds a node input: a constant, or a node's output (a group input's: the group node's)
        if not socket.is_linked:
            value = socket.default_value
            return ("constant", tuple(value) if hasattr(value, "__len__") else value)
        link = socket.links[0]
        if link.from_node.bl_idname == "NodeGroupInput":
            return outer.get(link.from_socket.identifier)
        return (path, link.from_node.name, link.from_socket.identifier)

    def upstream(socket, seen, path=(), outer=None):
        # nodes feeding `socket` (a node input), group internals expanded
        for link in socket.links:
            node = link.from_node
            key = (path, node.name)
            if key in seen:
                continue
            seen.add(key)
            if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
                groups.add(key)
                inner_outer = {s.identifier: source(s, path, outer or {}) for s in node.inputs}
                out = next(n for n in node.node_tree.nodes if n.bl_idname == "NodeGroupOutput")
                inner = set()
                for s in out.inputs:
                    upstream(s, inner, path + (node.name,), inner_outer)
                seen |= inner
                for s in node.inputs:
                    upstream(s, seen, path, outer)
            elif node.bl_idname == "NodeGroupInput":
                pass
            else:
                if node.bl_idname == "ShaderNodeTexImage":
                    place = source(node.inputs["Vector"], path, outer or {})
                    lookups.add((node.image.name if node.image else "", place))
                for s in node.inputs:
                    upstream(s, seen, path, outer)
        return seen

    seen, groups, lookups = {((), socket.node.name)}, set(), set()
    for s in socket.node.inputs:
        upstream(s, seen)
    nodes = len({k for k in seen - groups if not k[1].startswith(("Group Input", "Group Output", "Reroute"))})
    return nodes, len(lookups)


def per_spp(kind, variant, tables, fit, setup, size, lo, hi, inner):
    with patched(variant):
        sc, mat = ca.cycles_scene(kind, tables.stem, tables, None, size, lo, fit=fit, setup=setup, native=True)
        sc.render.threads = 1           # one Cycles thread: no worker waiting for another counted as CPU
        cs.render(sc)                           # warm: compilation, world map, textures
        nodes = graph_nodes(BUILT[-1]) if kind == "svm" and BUILT else (0, 0)
        secs = {lo: [], hi: []}
        for _ in range(inner):
            for spp in (lo, hi):
                sc.cycles.samples = spp
                t0 = time.process_time()
                cs.render(sc)
                secs[spp].append(time.process_time() - t0)
        return (min(secs[hi]) - min(secs[lo])) / (hi - lo), nodes


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tables", type=Path, required=True,
                    help="a default bake's table file (e.g. cm_military_green's: `flowbsdf bake`)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--before", type=Path, default=None,
                    help="the svm package (or svm.py) the variant `before` builds with")
    ap.add_argument("--scenes", default="constant,hdri,studio")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--inner", type=int, default=3, help="renders at each spp per round (the fastest counts)")
    ap.add_argument("--lo", type=int, default=16)
    ap.add_argument("--hi", type=int, default=400)
    args = ap.parse_args(argv)
    if "before" in args.variants.split(","):
        _before(args.before)
    fit = load_fit(ensure_fit(args.tables))
    scenes = {k: v for k, v in backend_cost.setups().items() if k in args.scenes.split(",")}
    variants = args.variants.split(",")
    best, nodes = {}, {}
    for r in range(args.repeat):
        for scene, setup in scenes.items():
            for v in variants:
                kind = v if v in ("principled", "fit") else "svm"
                t, n = per_spp(kind, v, args.tables, fit, setup, args.size, args.lo, args.hi, args.inner)
                best[scene, v] = min(best.get((scene, v), float("inf")), t)
                nodes[scene, v] = n
                print(f"round {r} {scene} {v}: {1e3 * t:.2f} ms/spp ({n[0]} nodes, {n[1]} lookups)", flush=True)
    print(f"{args.tables.stem}, {args.size} px sphere, CPU ms per spp (this process, all threads) from "
          f"{args.lo} and {args.hi} spp, best of {args.repeat} interleaved rounds; ratio to Principled; "
          f"graph nodes (n) and texture lookups (lk) upstream of the output (groups expanded, every branch)")
    print("| variant | " + " | ".join(scenes) + " |")
    print("|---" * (len(scenes) + 1) + "|")
    for v in variants:
        cells = []
        for scene in scenes:
            t, p = best[scene, v], best[scene, "principled"] if (scene, "principled") in best else float("nan")
            n, lk = nodes[scene, v]
            cells.append(f"{1e3 * t:.2f} ({t / p:.2f}x{f', {n} n, {lk} lk' if n else ''})")
        print(f"| {v} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
