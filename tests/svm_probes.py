"""Test probes of the SVM graph (blender_addon/render/svm/): graphs on inputs read from a probe
image that show what the graph computes side by side, for tests against numpy, and the graph's
node and texture lookup counts. Not shipped: tests and scripts import it (tests/ on sys.path).

`build_svm_probe` builds the sampler (or its inverse, or the world mixture) on inputs read from
a probe image (per pixel u0, u1, cos theta_i, phi_i) and returns an Emission that encodes wo
(0.5 + 0.5 wo), the weight and the pdf side by side; `build_world_probe` the map's sampling and
pdf; `_probe_input` and `_probe_output` the probe's two ends for other graphs."""
from blender_addon.render.svm.graph import X, Y, Z, _Graph, _image, atan2, cos, floor, fract, sin, sqrt
from blender_addon.render.svm.mixture import _Mixture
from blender_addon.render.svm.shader import TANGENT, _frame
from blender_addon.render.svm.tables import _inverse, _Sampler, _tables_sample
from blender_addon.render.svm.world import _world_pdf_group, _world_sample_group, world_layout


def build_svm_probe(tree, texture_path, probe_path, inverse=False, location=(0.0, 0.0), world=None):
    """The sampler (or with `inverse`, tables_pdf_graph's inverse) on inputs from the probe image
    `probe_path` (w x h float32 RGBA texels: u0, u1, cos theta_i, phi_i; with `inverse`,
    cos theta_o, phi_o, cos theta_i, phi_i, in the frame whose x is the tangent: wi at phi_i)
    for a camera whose window spans 3 w x h pixels (orthographic, pixel centres): pixel
    column x shows texel x mod w of the probe, as 0.5 + 0.5 wo, the weight W and the pdf
    (thirds of the image; with `inverse`: the pdf, f·cos and 0), through an Emission of
    strength 1. Returns the Emission's output socket.
    With `world` (build_svm_sampler's), the mixture at a shading point of normal world z and
    wi = (sin theta_i cos phi_i, sin theta_i sin phi_i, cos theta_i) (the frame's x from wi, or
    for anisotropic tables world x): 0.5 + 0.5 the world direction, the weight, and (q, the
    technique (0 tables, 1 map, 2 sun), 1 if the direction counts else 0)."""
    g = _Graph(tree, location)
    sampler = _Sampler(g, texture_path)
    thirds, values, alpha = _probe_input(g, probe_path)
    first, second, cos_i = (g.dot(values, axis) for axis in (X, Y, Z))
    phi_i = alpha if sampler.lay["P"] > 1 else None
    if world is not None:
        sin_i = sqrt(1.0 - cos_i * cos_i)
        wi = g.combine(sin_i * cos(alpha), sin_i * sin(alpha), cos_i)
        tx, ty = _frame(g, Z, wi if phi_i is None else TANGENT)
        if phi_i is not None:
            phi_i = atan2(g.dot(wi, ty), g.dot(wi, tx))
        at = {"n": Z, "ng": Z, "cos_raw": cos_i, "cos_i": cos_i, "tx": tx, "ty": ty, "phi_i": phi_i,
              "u0": first, "u1": second, "p": (0.0, 0.0, 0.0)}
        return _Mixture(world).graph(g, sampler, at, lambda out: _probe_output(
            g, thirds, (g.vmath('MULTIPLY_ADD', out["direction"], (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)), out["weight"],
                        g.combine(out["q"], out["technique"], out["ok"]))))
    if inverse:
        sin_o = sqrt(1.0 - first * first)
        wo = (sin_o * cos(second), sin_o * sin(second), first)
        pdf, fcos = _inverse(g, sampler, cos_i, phi_i, wo)
        shown = (pdf, fcos, (0.0, 0.0, 0.0))
    else:
        wo, weight, pdf = _tables_sample(g, sampler, cos_i, phi_i, first, second)
        wo = g.vmath('MULTIPLY_ADD', g.combine(*wo), (0.5, 0.5, 0.5), (0.5, 0.5, 0.5))
        shown = (wo, weight, pdf)
    return _probe_output(g, thirds, shown)


def build_world_probe(tree, world_path, probe_path, location=(0.0, 0.0)):
    """The world map's sampling on u0, u1 from the probe image (build_svm_probe's layout): 0.5
    + 0.5 the direction, (its pdf, the pdf graph's density at it, 0), and 0."""
    g = _Graph(tree, location)
    wl, image = world_layout(str(world_path)), _image(world_path)
    thirds, values, _ = _probe_input(g, probe_path)
    out = g.group(_world_sample_group(wl, image), U0=g.dot(values, X), U1=g.dot(values, Y))
    again = g.group(_world_pdf_group(wl, image), Direction=out["Direction"])[0]
    return _probe_output(g, thirds, (g.vmath('MULTIPLY_ADD', out["Direction"], (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)),
                                     g.combine(out["Pdf"], again), (0.0, 0.0, 0.0)))


def _probe_input(g, probe_path):
    """(the thirds' flags: left, middle, right; the probe texel's colour, its alpha) of this pixel."""
    window = g.node("ShaderNodeTexCoord").outputs["Window"]
    wx = g.dot(window, X) * 3.0
    third = floor(wx)
    # one of the three by its third of the image: x 1 and x 0 (exact)
    left, right = third < 0.5, third > 1.5
    middle = 1.0 - left - right
    probe = g.node("ShaderNodeTexImage", image=_image(probe_path), interpolation='Closest', extension='EXTEND')
    g.set(probe.inputs["Vector"], g.combine(fract(wx), g.dot(window, Y)))
    return (left, middle, right), probe.outputs["Color"], g.outputs(probe)["Alpha"]


def _probe_output(g, thirds, shown):
    """An Emission of shown[k] in third k of the image."""
    color = g.vmath('ADD', g.vmath('ADD', g.scale(shown[0], thirds[0]), g.scale(shown[1], thirds[1])),
                    g.scale(shown[2], thirds[2]))
    emission = g.node("ShaderNodeEmission")
    g.set(emission.inputs["Color"], color)
    emission.inputs["Strength"].default_value = 1.0
    return emission.outputs["Emission"]


def graph_counts(tree):
    """(shader nodes, texture lookups per sample) of a tree, node groups expanded as Cycles
    compiles them (group inputs/outputs, frames and reroutes not counted; image lookups of
    the same image at the same coordinates counted once: Cycles merges identical nodes)."""
    nodes, lookups = _count(tree, (), {})
    return nodes, len(lookups)


def _count(tree, path, outer):
    """(nodes, {(image, coordinate source)}) in `tree`, a group instance at `path` whose
    inputs come from the sources `outer` (by socket identifier)."""
    def source(socket):
        if not socket.is_linked:
            value = socket.default_value
            return ("constant", tuple(value) if hasattr(value, "__len__") else value)
        link = socket.links[0]
        if link.from_node.bl_idname == "NodeGroupInput":
            return outer.get(link.from_socket.identifier)
        return (path, link.from_node.name, link.from_socket.identifier)
    nodes, lookups = 0, set()
    for node in tree.nodes:
        if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
            inner = {socket.identifier: source(socket) for socket in node.inputs}
            n, lk = _count(node.node_tree, path + (node.name,), inner)
            nodes, lookups = nodes + n, lookups | lk
        elif node.bl_idname not in ("NodeGroupInput", "NodeGroupOutput", "NodeFrame", "NodeReroute"):
            nodes += 1
            if node.bl_idname == "ShaderNodeTexImage":
                lookups.add((node.image.name if node.image else "", source(node.inputs["Vector"])))
    return nodes, lookups
