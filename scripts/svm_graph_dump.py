"""Issue 53 item 3: the SVM graphs as canonical text, to show that a rewrite of the graph builder
(blender_addon/render/svm/, before: blender_addon/svm.py) builds the same graphs: the same nodes in
the same order with the same settings, inputs and links. Run it with one checkout's code and
then another's on the same prepared tables and `diff` the two dumps.

    .venv/bin/python scripts/svm_graph_dump.py --prepare DIR [--baked DIR_OF_DEFAULT_BAKES]   (tables, once)
    .venv/bin/python scripts/svm_graph_dump.py --dump DIR --out dump.txt [--checkout PATH]

--prepare writes the test fixtures' tables (tests/cycles_scenes.py: plastic over its default
coordinates, over wo and halfpolar; brushed, anisotropic; lambert; grouped; mixed; odd synthetic
K x P), their SVM exports and fits, a small world map and an equirectangular image with a sun, and
copies the default Final bakes found under --baked (<name>/tables/<name>.exr and what is beside).
--dump builds, with the code of --checkout (default: this script's), per texture the tables'
graph (build_svm_sampler), with a tangent, the world mixture (map, sun, map and sun, lamps, all),
the control variate (node._svm_backend with the fit: constant, sun-matched, lamp-matched,
unmatched), sample_graph + tables_pdf_graph, update_world's swap of a new map, the test probes
(build_svm_probe: sample, inverse, mixture; build_world_probe; f_cv; the match lookup), and the
Learned BSDF node's own group in four scenes (constant world, image world, sky, studio lamps:
node.sync bakes the world's map, CPU); then writes every material tree and node group: per node
in creation order its name, type, settings (every RNA property but the editor's), inputs
(linked: the source node and socket; else the value), custom properties; the links in order;
the images' names and settings; graph_counts.

The OSL script node's compiled bytecode names its temporary files (and so its bytecode_hash
differs from run to run): normalise both dumps before the diff, e.g.
    sed -E "s#/tmp/flowbsdf_osl_[A-Za-z0-9_]+/tmp[A-Za-z0-9_]+[.]#TMP.#g; s/bytecode_hash='[0-9a-f]+'/bytecode_hash=H/"
"""
import argparse
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PLASTIC = {"kind": "analytic", "model": "plastic", "albedo": [0.7, 0.1, 0.08], "alpha": 0.12}
LAMPS = [((2.0, -1.0, 3.0), (0.3, 40.0, 0.0)), ((-3.0, 0.5, 1.0), (0.1, 20.0, 0.0)),
         ((0.3, 0.2, 0.9), (0.05, 3.0, 1.0)), ((0.0, 4.0, 0.5), (1.0, 80.0, 0.0))]
# RNA properties of a node that are the editor's, not the graph's
SKIP = {"rna_type", "type", "location_absolute", "dimensions", "width", "height", "inputs", "outputs",
        "internal_links", "parent", "select", "show_options", "show_preview", "show_texture", "use_custom_color",
        "color", "color_tag", "bl_idname", "bl_label", "bl_description", "bl_icon", "bl_static_type",
        "bl_width_default", "bl_width_min", "bl_width_max", "bl_height_default", "bl_height_min",
        "bl_height_max", "warning_propagation", "texture_mapping", "color_mapping", "image_user",
        "interface", "is_active_output"}


def prepare(folder, baked):
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "tests"))
    import numpy as np
    import cycles_scenes as cs
    from bake.core.profiles import K_MAX, NSEG
    from bake.core.tables import Tables
    from bake.export.derived import ensure_fit, ensure_svm_export
    from bake.export.world_map import WorldMap, write_world_texture
    from bake.io.exrio import write_rgba_exr
    folder.mkdir(parents=True, exist_ok=True)
    made = {}
    for name, make in (("plastic", lambda d: cs.small_tables(PLASTIC, "plastic", d)),
                       ("plastic_wo", lambda d: cs.small_tables(PLASTIC, "plastic", d, coords="wo")),
                       ("plastic_halfpolar", lambda d: cs.small_tables(PLASTIC, "plastic", d, coords="halfpolar")),
                       ("brushed", lambda d: cs.aniso_small_tables(d)),
                       ("brushed_wo", lambda d: cs.aniso_small_tables(d, coords="wo")),
                       ("lambert", lambda d: cs.lambert_tables(d)),
                       ("grouped", lambda d: cs.grouped_tables(PLASTIC, "grouped", d)),
                       ("mixed", lambda d: cs.mixed_tables(PLASTIC, "mixed", d))):
        sub = folder / name
        sub.mkdir(exist_ok=True)
        made[name] = make(sub)
    for K, P in ((1, None), (2, 3)):        # tests/test_svm.py _synthetic's odd shapes
        rng = np.random.default_rng(K)
        R, C = 8, 12
        lead = (K,) if P is None else (K, P)
        a = np.sort(rng.random(lead + (R + 1,)), -1)
        b = np.sort(rng.random(lead + (R, C + 1)), -1) * 2 * np.pi
        mass = rng.random(lead + (R, C)) ** 4 + 1e-3
        slopes = [np.cumsum(rng.uniform(-K_MAX / NSEG, K_MAX / NSEG, lead + (R, C, NSEG)), -1) for _ in range(2)]
        tab = Tables(np.radians(np.linspace(0.0, 89.5, K)), a, b, mass, *slopes, rng.random(lead + (R, C, 3)),
                     phi_bins=None if P is None else np.arange(P) * np.pi / P, phi_period=np.pi if P else 2 * np.pi)
        sub = folder / f"synthetic{K}x{P or 1}"
        sub.mkdir(exist_ok=True)
        tab.save(sub / "synthetic.exr")
        made[sub.name] = sub / "synthetic.exr"
    for path in made.values():
        ensure_svm_export(path)
    for name in ("plastic", "lambert", "mixed"):
        ensure_fit(made[name])
    for src in sorted(Path(baked).glob("*/tables/*.exr")) if baked else ():
        name = src.parent.parent.name
        if src.name == f"{name}.exr" and (src.parent.parent / "done").exists():
            shutil.copytree(src.parent, folder / "baked" / name, dirs_exist_ok=True)
    rng = np.random.default_rng(3)             # tests/test_svm.py _world_map
    img = rng.random((24, 48, 3)) ** 4
    img[3, 40] = 300.0
    img[20:, :] = 0.0
    write_world_texture(folder / "world.exr", WorldMap(img))
    img2 = img.copy()
    img2[5, 10] = 500.0
    write_world_texture(folder / "world2.exr", WorldMap(img2))
    env = np.full((64, 128, 4), 0.3, np.float32)        # an image world with a small sun
    env[..., 3] = 1.0
    env[20:22, 90:92, :3] = 4000.0
    write_rgba_exr(folder / "env.exr", env, "flowbsdf", {})


# ------------------------------------------------------------------------------ the dump

def _val(v):
    if isinstance(v, float):
        return repr(v)
    if hasattr(v, "__len__") and not isinstance(v, str):
        return "(" + ", ".join(_val(x) for x in v) + ")"
    if hasattr(v, "name") and hasattr(v, "bl_rna"):
        return f"<{type(v).__name__} {v.name!r}>"
    return repr(v)


def _custom(owner):
    out = []
    for key in owner.keys():
        value = owner[key]
        out.append(f"{key}={_val(value.to_dict() if hasattr(value, 'to_dict') else value)}")
    return " ".join(out)


def dump_tree(tree, lines, groups, images):
    lines.append(f"tree {tree.name!r} {tree.bl_idname}")
    if getattr(tree, "interface", None) is not None:
        for item in tree.interface.items_tree:
            lines.append(f"  socket {getattr(item, 'in_out', '')} {item.name!r} {getattr(item, 'socket_type', '')}")
    for node in tree.nodes:
        props = []
        for prop in node.bl_rna.properties:
            key = prop.identifier
            if key in SKIP or prop.type == "COLLECTION":
                continue
            try:
                props.append(f"{key}={_val(getattr(node, key))}")
            except (AttributeError, TypeError, ValueError) as e:
                props.append(f"{key}=<{type(e).__name__}>")
        lines.append(f"  node {node.bl_idname} " + " ".join(props))
        for i, socket in enumerate(node.inputs):
            if socket.is_linked:
                link = socket.links[0]
                lines.append(f"    in {i} {socket.identifier} <- {link.from_node.name!r}.{link.from_socket.identifier}")
            elif hasattr(socket, "default_value"):
                lines.append(f"    in {i} {socket.identifier} = {_val(socket.default_value)}"
                             f"{'' if socket.enabled else ' (disabled)'}")
        if node.keys():
            lines.append(f"    custom {_custom(node)}")
        if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
            groups.append(node.node_tree)
        image = getattr(node, "image", None)
        if image is not None and image.name not in images:
            images[image.name] = (f"image {image.name!r} {image.colorspace_settings.name} {image.alpha_mode} "
                                  f"half={image.use_half_precision} packed={image.packed_file is not None} "
                                  f"{_custom(image)}")
    for link in tree.links:
        lines.append(f"  link {link.from_node.name!r}.{link.from_socket.identifier} -> "
                     f"{link.to_node.name!r}.{link.to_socket.identifier}")


def _api(checkout):
    """(svm package or module, probes module, node module) of the checkout."""
    sys.path.insert(0, str(checkout))
    sys.path.insert(0, str(checkout / "tests"))
    try:
        from blender_addon.render import svm
    except ImportError:
        from blender_addon import svm
    try:
        from blender_addon.render import node
    except ImportError:
        from blender_addon import node
    try:
        import svm_probes as probes
    except ImportError:
        probes = svm
    return svm, probes, node


def dump(folder, out, checkout, quick=False):
    import bpy
    svm, probes, lb = _api(checkout)
    import cycles_scenes as cs
    from bake.export import closure_fit
    from bake.export.derived import ensure_fit, ensure_svm_export
    lines, built, done, images = [], [], set(), {}
    textures = {p.parent.name: ensure_svm_export(p)
                for p in sorted(folder.glob("*/*.exr")) if "." not in p.stem and not p.stem.startswith("world")}
    baked = {p.parent.name: p for p in sorted((folder / "baked").glob("*/*.exr")) if p.stem == p.parent.name}
    for name, path in baked.items():
        textures[f"baked/{name}"] = ensure_svm_export(path)
    world_map = str(folder / "world.exr")
    worlds = {
        "none": None,
        "map": {"World": world_map, "WorldShare": 0.2},
        "sun": {"SunDirection": (0.3, 0.4, 0.8), "SunCos": 0.999, "SunShare": 0.3},
        "map and sun": {"World": world_map, "WorldShare": 0.2, "SunDirection": (0.3, 0.4, 0.8), "SunCos": 0.999,
                        "SunShare": 0.3, "ControlVariate": 1.0, "LightDirection": (0.3, 0.4, 0.8)},
        "lamps": {"Lamps": 4, "LampShare": 0.5, "ControlVariate": 1.0},
        "lamp": {"Lamps": 1, "LampShare": 0.5, "ControlVariate": 1.0},
        "all": {"World": world_map, "WorldShare": 0.2, "SunDirection": (0.3, 0.4, 0.8), "SunCos": 0.999,
                "SunShare": 0.3, "ControlVariate": 1.0, "Lamps": 4, "LampShare": 0.5},
        "cv on": {"ControlVariate": 1.0},
    }
    cs.reset(8, 8, spp=1, osl=False, threads=1)

    def record(label, build=None, tree=None):
        """Build a graph and write it, and the node groups it uses not written yet, at once (a
        scene reset removes them)."""
        if tree is None:
            tree = bpy.data.node_groups.new(f"dump {len(built)}", "ShaderNodeTree")
            build(tree)
        built.append(label)
        lines.append(f"=== {label}")
        lines.append(f"counts {counts(tree)}")
        groups = []
        dump_tree(tree, lines, groups, images)
        while groups:
            group = groups.pop(0)
            if group.name not in done:
                done.add(group.name)
                lines.append(f"=== group {group.name}")
                dump_tree(group, lines, groups, images)
    counts = getattr(probes, "graph_counts", None) or svm.graph_counts

    def tangent(tree, value=(0.6, 0.8, 0.0)):
        node = tree.nodes.new("ShaderNodeCombineXYZ")
        for socket, v in zip(node.inputs, value):
            socket.default_value = v
        return node.outputs[0]

    few = (lambda names, n: list(names)[:n]) if quick else (lambda names, n: list(names))
    for name, tex in textures.items():
        record(f"{name}: tables", lambda t, tex=tex: svm.build_svm_sampler(t, tex))
        if name.startswith("brushed") or "x3" in name:
            record(f"{name}: tables, tangent", lambda t, tex=tex: svm.build_svm_sampler(t, tex, tangent(t)))
    for name in few(("plastic", "brushed", "synthetic1x1", "plastic_wo", "mixed", "synthetic2x3") + tuple(
            f"baked/{n}" for n in list(baked)[:1]), 3):
        tex = textures[name]
        for w, world in worlds.items():
            if world is not None and (not quick or w in ("map and sun", "lamps", "all")):
                record(f"{name}: world {w}", lambda t, tex=tex, world=world: svm.build_svm_sampler(t, tex, world=world))
        if not quick or name != "synthetic1x1":
            record(f"{name}: sample_graph + tables_pdf_graph",
                   lambda t, tex=tex: _inverse_pair(svm, t, tex, tangent(t)))
    fits = {name: closure_fit.load_fit(ensure_fit(folder / name / f"{stem}.exr"))
            for name, stem in (("plastic", "plastic"), ("mixed", "mixed"))}
    for name, path in list(baked.items())[:1]:
        fits[f"baked/{name}"] = closure_fit.load_fit(ensure_fit(path))
    for name, fit in few(fits.items(), 1):
        tex = textures[name]
        variants = {"baked": fit}
        matched = dict(fit)
        matched["cv"] = [[0.5, 0.5, 0.3]] * len(fit["x"])
        matched["rel_error"] = [0.05] * len(fit["x"])
        variants["matched"] = matched
        poor = dict(fit)
        poor["rel_error"] = [1.0] * len(fit["x"])
        variants["poor"] = poor
        for v, f in few(variants.items(), 2):
            for w in few(("none", "map and sun", "lamps", "cv on", "lamp"), 3):
                world = worlds[w]
                if world is not None and "sun" in w:
                    world = dict(world, ControlVariate=1.0, LightDirection=(0.3, 0.4, 0.8))
                record(f"{name}: cv {v}, world {w}",
                       lambda t, tex=tex, f=f, world=world: lb._svm_backend(t, tex, f, None, world))
    # update_world: a new map swaps the groups
    tex = textures["plastic"]
    before = worlds["map and sun"]
    after = dict(before, World=str(folder / "world2.exr"), WorldShare=0.3, SunShare=0.2)

    def swapped(t):
        shader = svm.build_svm_sampler(t, tex, world=before)
        assert svm.update_world(t, after)
        return shader
    record("plastic: update_world to a new map", swapped)
    # the test probes
    probe = str(folder / "world.exr")          # (any RGBA float image serves as the probe's input)
    for name in few(("plastic", "brushed", "mixed", "synthetic2x3"), 2):
        tex = textures[name]
        record(f"{name}: probe sample", lambda t, tex=tex: probes.build_svm_probe(t, tex, probe))
        record(f"{name}: probe inverse", lambda t, tex=tex: probes.build_svm_probe(t, tex, probe, inverse=True))
        for w in few(("all", "map and sun", "lamps"), 1):
            record(f"{name}: probe world {w}",
                   lambda t, tex=tex, w=w: probes.build_svm_probe(t, tex, probe, world=worlds[w]))
    record("world probe", lambda t: probes.build_world_probe(t, world_map, probe))
    for tilts in few(("tilted", "none"), 1):
        record(f"f_cv probe, tilts {tilts}", lambda t, tilts=tilts: _fcos_probe(svm, probes, t, probe, tilts))
    record("match lookup probe", lambda t: _match_probe(svm, probes, t, probe, fits["plastic"]["match_path"]))
    # the Learned BSDF node's own group, in scenes
    for name in few(("plastic",) + tuple(f"baked/{n}" for n in list(baked)[:1]), 1):
        path = folder / name / (f"{name.split('/')[-1]}.exr")
        for scene in few(("studio", "constant", "image", "sky"), 2):
            record(f"{name}: node, {scene}", tree=_node_group(lb, cs, path, scene, folder, len(built)))
    lines += [images[name] for name in sorted(images)]
    Path(out).write_text("\n".join(lines) + "\n")
    print(f"{len(built)} graphs, {len(done)} groups, {len(lines)} lines -> {out}")


CV_FIT = {"kd": (0.10, 0.08, 0.06),           # tests/test_svm.py's
          "ks": [(0.30, 0.20, 0.10), (0.10, 0.20, 0.30), (0.05, 0.04, 0.03), (0.04, 0.03, 0.05)],
          "roughness": (0.35, 0.50, 0.25), "anisotropy": (0.40, -0.30, 0.20), "r4": 0.65}


def _internals(svm):
    """(_Graph, _cv_fcos, _match_lookup) of either layout."""
    if hasattr(svm, "_Graph"):
        return svm._Graph, svm._cv_fcos, svm._match_lookup
    from blender_addon.render.svm import control_variate, graph
    return graph._Graph, control_variate._cv_fcos, control_variate._match_lookup


def _fcos_probe(svm, probes, tree, path, tilts):
    """tests/test_svm.py test_svm_control_variate_fcos_is_closure_fit's graph."""
    import math
    Graph, cv_fcos, _ = _internals(svm)
    deg = [2.0, -3.0, 4.0, -1.0, 15.0] if tilts == "tilted" else [0.0] * 5
    t = [math.tan(math.radians(d)) for d in deg]
    cv_fit = {"kd": CV_FIT["kd"], "ks": CV_FIT["ks"], "roughness": CV_FIT["roughness"],
              "anisotropy": CV_FIT["anisotropy"], "tilt": tuple(t[:3]), "lobe4": (CV_FIT["r4"], t[3], t[4]),
              "tilted": [bool(t[4])] + [bool(v) for v in t[:4]]}
    cv = {"fit": cv_fit, "diffuse": (1.0, 1.0, 1.0), "specular": (1.0, 1.0, 1.0)}
    g = Graph(tree)
    thirds, values, _ = probes._probe_input(g, path)
    co, po, ci = (g.dot(values, axis) for axis in (svm.X, svm.Y, svm.Z))
    so = g.math('SQRT', g.math('MAXIMUM', g.math('SUBTRACT', 1.0, g.math('MULTIPLY', co, co)), 0.0))
    si = g.math('SQRT', g.math('MAXIMUM', g.math('SUBTRACT', 1.0, g.math('MULTIPLY', ci, ci)), 0.0))
    d = g.combine(g.math('MULTIPLY', so, g.math('COSINE', po)), g.math('MULTIPLY', so, g.math('SINE', po)), co)
    fcos = cv_fcos(g, cv, g.combine(si, 0.0, ci), svm.Z, d)
    return probes._probe_output(g, thirds, (fcos, fcos, fcos))


def _match_probe(svm, probes, tree, probe, path):
    """tests/test_svm.py test_svm_match_lookup_is_trilinear_in_the_match_image's graph."""
    Graph, _, match_lookup = _internals(svm)
    g = Graph(tree)
    thirds, values, phi = probes._probe_input(g, probe)
    cos_v, cos_l = g.dot(values, svm.X), g.dot(values, svm.Y)
    sin_l = g.math('SQRT', g.math('SUBTRACT', 1.0, g.math('MULTIPLY', cos_l, cos_l)))
    wo = (g.math('MULTIPLY', sin_l, g.math('COSINE', phi)), g.math('MULTIPLY', sin_l, g.math('SINE', phi)), cos_l)
    beta = match_lookup(g, path, cos_v, wo)
    return probes._probe_output(g, thirds, (beta, beta, beta))


def _inverse_pair(svm, tree, texture, tangent):
    out = svm.sample_graph(tree, texture, tangent)
    pdf, fcos = svm.tables_pdf_graph(tree, texture, out["direction"], tangent)
    node = tree.nodes.new("ShaderNodeCombineXYZ")
    tree.links.new(pdf, node.inputs[0])
    tree.links.new(out["pdf"], node.inputs[1])
    tree.links.new(fcos, tree.nodes.new("ShaderNodeEmission").inputs[0])
    return node.outputs[0]


def _node_group(lb, cs, tables, scene_kind, folder, k):
    """The Learned BSDF group of a material on `tables` with the SVM back end in a scene."""
    import bpy
    sc = cs.reset(8, 8, spp=1, osl=False, threads=1)
    if scene_kind == "constant":
        cs.set_world(sc, (0.5, 0.5, 0.5))
    elif scene_kind == "image":
        w = cs.set_world(sc, image=str(folder / "env.exr"))
        w.cycles.sampling_method = 'AUTOMATIC'
    elif scene_kind == "sky":
        cs.set_sky_world(sc, sun_elevation=0.5, sun_rotation=1.0, strength=0.2)
    else:
        cs.set_world(sc, (0.05, 0.05, 0.05))
        cs.add_lamp(sc, "AREA", (2.0, -1.0, 3.0), energy=200.0, size=0.5)
        cs.add_lamp(sc, "POINT", (-3.0, 0.5, 1.0), energy=300.0, shadow_soft_size=0.25)
    lb.register()
    mat = bpy.data.materials.new(f"m{k}")
    node = lb.assign_learned_bsdf(mat, f"m{k}", tables)
    lb.set_backend(sc, "svm")
    cs.add_sphere(sc, mat, segments=16, rings=8)
    lb.sync(sc, bake_world=True)
    return node.node_tree


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--prepare", type=Path)
    ap.add_argument("--baked", default=None, help="a folder of default Final bakes, <name>/tables/<name>.exr")
    ap.add_argument("--dump", type=Path, help="the prepared folder")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--checkout", type=Path, default=ROOT)
    ap.add_argument("--quick", action="store_true", help="a subset (~40 graphs) for a loaded machine")
    args = ap.parse_args(argv)
    if args.prepare:
        prepare(args.prepare, args.baked)
    if args.dump:
        dump(args.dump, args.out, args.checkout.resolve(), args.quick)


if __name__ == "__main__":
    main()
