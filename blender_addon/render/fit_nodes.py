"""The fit back end's nodes: the fit's parameters as a node group ("FlowBSDF fit: <hash>", each
piecewise linear in the view angle) and its closures (a Diffuse BSDF and GGX Glossy BSDFs, tilted
and view-aligned as the fit says); the SVM back end's control variate scales the same closures."""
import json

import bpy

from . import sockets

# The grey diffuse used when a material has neither a fit nor tables.
NEUTRAL = (0.5, 0.5, 0.5)
FIT_LOBES = 4           # at most (bake/export/closure_fit.LOBES); a vector socket holds lobes 1-3's r, a or tilt


def piecewise(tree, x_socket, xs, values, loc):
    """A vector socket whose value is the piecewise-linear interpolant of `values` (3-vectors)
    at knots `xs`, evaluated at x: v0 + sum_k (v_{k+1} - v_k) clamp((x - x_k)/(x_{k+1} - x_k)).
    Built from Map Range nodes (one per segment) and scalar Math Multiply Adds per channel (a
    channel's zero steps left out), combined once: exact, no curve tables. (Scalar: a vector Math
    node costs SVM ~5 scalar ones, and this runs on every shading point of the fit and the SVM
    back end: scripts/svm_cost_parts.py.)"""
    nodes, links = tree.nodes, tree.links
    channels = [float(values[0][c]) for c in range(3)]
    for k in range(len(xs) - 1):
        steps = [float(values[k + 1][c] - values[k][c]) for c in range(3)]
        if not any(steps):
            continue
        ramp = nodes.new("ShaderNodeMapRange")
        ramp.clamp = True
        ramp.inputs["From Min"].default_value = float(xs[k])
        ramp.inputs["From Max"].default_value = float(xs[k + 1])
        ramp.location = (loc[0] + 180 * (k + 1), loc[1] + 200)
        links.new(x_socket, ramp.inputs["Value"])
        for c, step in enumerate(steps):
            if step == 0.0:
                continue
            mad = nodes.new("ShaderNodeMath")
            mad.operation = 'MULTIPLY_ADD'
            mad.location = (loc[0] + 180 * (k + 1), loc[1] - 60 * c)
            links.new(ramp.outputs["Result"], mad.inputs[0])
            mad.inputs[1].default_value = step
            if isinstance(channels[c], float):
                mad.inputs[2].default_value = channels[c]
            else:
                links.new(channels[c], mad.inputs[2])
            channels[c] = mad.outputs[0]
    out = nodes.new("ShaderNodeCombineXYZ")
    out.location = (loc[0] + 180 * len(xs), loc[1])
    for c, value in enumerate(channels):
        if isinstance(value, float):
            out.inputs[c].default_value = value
        else:
            links.new(value, out.inputs[c])
    return out.outputs[0]


# The fit group's outputs (vectors, in this order where the fit has them): "Tilt" = (t_1, t_2,
# t_3), "Lobe 4" = (r_4, t_4, t_d) (the 4th lobe, isotropic: closure_fit.VIEW_ALIGNED 3, and the
# Diffuse's tilt; packed: every piecewise vector costs its segments' nodes).
FIT_PARAMS = ("Diffuse", "Specular 1", "Specular 2", "Specular 3", "Specular 4", "Roughness", "Anisotropy",
              "Tilt", "Lobe 4", "Control variate", "Matched share")


def fit_lobes(fit):
    """The fit's GGX lobes (3 or 4)."""
    lobes = len(fit["roughness"][0])
    if not 1 <= lobes <= FIT_LOBES:
        raise ValueError(f"closure fit of {lobes} lobes (at most {FIT_LOBES})")
    return lobes


def fit_tilts(fit):
    """(per knot the lobes' tilts (t = tan), per knot the Diffuse's), zeros for a fit without
    them (FIT_VERSION 6)."""
    lobes = fit_lobes(fit)
    tilt = fit.get("tilt") or [[0.0] * lobes for _ in fit["x"]]
    return [[float(v) for v in knot] for knot in tilt], [float(v) for v in fit.get("diffuse_tilt") or [0.0] * len(fit["x"])]


def _fit_columns(fit):
    """{output name: per knot its 3-vector} of the fit group (FIT_PARAMS)."""
    lobes = fit_lobes(fit)
    tilt, dtilt = fit_tilts(fit)
    pad = lambda v: (list(v) + [0.0, 0.0, 0.0])[:3]      # noqa: E731
    columns = {"Diffuse": fit["diffuse"]}
    columns.update({f"Specular {j + 1}": [knot[j] for knot in fit["specular"]] for j in range(lobes)})
    columns.update(Roughness=[pad(v[:3]) for v in fit["roughness"]], Anisotropy=[pad(v[:3]) for v in fit["anisotropy"]])
    if any(v for knot in tilt for v in knot[:3]):
        columns["Tilt"] = [pad(v[:3]) for v in tilt]
    if lobes > 3 or any(dtilt):
        columns["Lobe 4"] = [[r[3] if lobes > 3 else 0.0, t[3] if lobes > 3 else 0.0, d]
                             for r, t, d in zip(fit["roughness"], tilt, dtilt)]
    if "cv" in fit:
        columns["Control variate"] = fit["cv"]
        columns["Matched share"] = [[matched_share(e)] * 3 for e in fit["rel_error"]]
    return {name: columns[name] for name in FIT_PARAMS if name in columns}


def fit_params(tree, fit, loc, cv=False):
    """The fit's parameters at the view angle, from its node group (fit_group): {"kd": colour,
    "ks": [colour per lobe], "roughness": (r_1, r_2, r_3), "anisotropy": (a_1, a_2, a_3),
    "tilt": (t_1, t_2, t_3) or None, "lobe4": (r_4, t_4, t_d) or None, "tilted": per closure
    (Diffuse first) whether its tilt is anywhere not 0, "view_aligned": how many lobes take the
    view's tangent, "material_aligned": how many the material's (anisotropic tables), turned by
    "tangent_turn" (rad) about the normal}; `cv`: and "cv" (beta_d, beta_s, s), "matched" (s_m, s_m, s_m), the control
    variate's (svm.py)."""
    node = tree.nodes.new("ShaderNodeGroup")
    node.node_tree = fit_group(fit)
    node.location = loc
    out = node.outputs
    lobes = fit_lobes(fit)
    tilt, dtilt = fit_tilts(fit)
    params = {"kd": out["Diffuse"], "ks": [out[f"Specular {j + 1}"] for j in range(lobes)],
              "roughness": out["Roughness"], "anisotropy": out["Anisotropy"],
              "tilt": out.get("Tilt"), "lobe4": out.get("Lobe 4"),
              "tilted": [any(dtilt)] + [any(knot[j] for knot in tilt) for j in range(lobes)],
              "view_aligned": min(int(fit.get("view_aligned", 0)), 3),
              "material_aligned": min(int(fit.get("material_aligned", 0)), 3),
              "tangent_turn": float(fit.get("tangent_turn", 0.0))}
    if cv:
        params.update(cv=out["Control variate"], matched=out["Matched share"])
    return params


def fit_group(fit):
    """Node group "FlowBSDF fit: <hash>" of a fit's parameters at the view angle (Layer Weight
    "Facing" = 1 - |cos theta_i|), each piecewise linear in it (FIT_PARAMS, vectors, where the
    fit has them: _fit_columns). Named after its content: materials with the same fit share it.
    (A group of its own: every node added to a tree costs in proportion to the tree's size, and
    each back end takes the parameters.)"""
    import hashlib
    from .svm import MATCHED_SHARE_MIN
    payload = json.dumps([fit, MATCHED_ERROR_MAX, MATCHED_SHARE_MIN], sort_keys=True, default=str)
    name = "FlowBSDF fit: " + hashlib.sha256(payload.encode()).hexdigest()[:12]
    tree = bpy.data.node_groups.get(name)
    if tree is not None:
        return tree
    tree = bpy.data.node_groups.new(name, "ShaderNodeTree")
    columns = _fit_columns(fit)
    for param in columns:
        sockets.new_socket(tree, param, "OUTPUT", "NodeSocketVector")
    facing = tree.nodes.new("ShaderNodeLayerWeight")
    facing.inputs["Blend"].default_value = 0.5          # Facing = 1 - |cos theta_i|
    out = tree.nodes.new("NodeGroupOutput")
    out.location = (3400, 0)
    for k, values in enumerate(columns.values()):
        tree.links.new(piecewise(tree, facing.outputs["Facing"], fit["x"], values, (200, -500 * k)), out.inputs[k])
    return tree


def matched_share(rel_error):
    """The portal's share s where the control variate is matched to a small light (svm.py),
    0 where it is not to be (the fit's relative L2 error of f cos at the view angle above
    MATCHED_ERROR_MAX). The rest f - f_cv is about the fit's error, so is its needed share of
    the samples. Sky + sun sphere, 24 px, 64 spp, 12 seeds, per-pixel variance with s = 0.03 /
    0.1 / 0.3: paper_white (errors 0.03-0.3) 0.0125 / 0.018 / 0.062, cm_military_green
    (0.15-0.35) 0.0016 / 0.0011 / 0.0033 (the portal alone 0.101 and 0.0255). Where the fit is
    poor its f_cv exceeds f widely: in a sun's shadow (no light to match, the sky only) the rest
    then renders negative pixels (cm_military_green: 7-17 of 5000, at any s and with betas
    capped at 1; paper_white none)."""
    from .svm import MATCHED_SHARE_MIN
    e = float(rel_error)
    return min(max(0.5 * e, MATCHED_SHARE_MIN), 0.5) if e <= MATCHED_ERROR_MAX else 0.0


MATCHED_ERROR_MAX = 0.1


def closures(tree, params, loc, scale_d=None, scale_s=None, tilts=True, material_tangent=None, turned_tangent=None):
    """The fit's closures: a Diffuse BSDF (colour kd) plus a GGX Glossy BSDF per lobe (colour
    ks_j, roughness r_j, anisotropy a_j; the first params["view_aligned"] with the view's
    tangent: view_tangent; the first params["material_aligned"] with `material_tangent`, the
    socket of the tables' frame, which Cycles projects onto the surface as the exact back ends
    do), each tilted closure with its own Normal N + t normalize(T) (t its
    tilt, T the view tangent, N Geometry's Normal; a MULTIPLY_ADD: a zero tilt gives N exactly,
    Cycles normalises it; closures whose tilt is 0 at every knot take the shading normal
    unlinked, as before). `scale_d`, `scale_s`: colours multiplying kd and every ks_j (the SVM
    back end's control variate); `tilts` False: every closure untilted. `turned_tangent`: the
    material-aligned lobes' tangent already made (lobe_tangent), instead of turning `material_tangent`."""
    nodes, links = tree.nodes, tree.links
    x, y = loc[0] + 3000, loc[1]
    if params["material_aligned"]:
        material_tangent = turned_tangent or lobe_tangent(tree, params, material_tangent, (x - 600, y - 1300))

    def scaled(colour, scale, at):
        if scale is None:
            return colour
        mul = nodes.new("ShaderNodeVectorMath")
        mul.operation = 'MULTIPLY'
        mul.location = at
        links.new(colour, mul.inputs[0])
        links.new(scale, mul.inputs[1])
        return mul.outputs[0]
    tilted = params["tilted"] if tilts else [False] * (len(params["ks"]) + 1)
    tangent = normal = None
    if params["view_aligned"] or any(tilted):
        tangent, normal = view_tangent(tree, (x - 400, y - 700), with_normal=True)
    if any(tilted):
        unit = nodes.new("ShaderNodeVectorMath")
        unit.operation = 'NORMALIZE'
        unit.location = (x - 200, y - 900)
        links.new(tangent, unit.inputs[0])
    separated = {}

    def component(key, c, at):
        """Component c of params[key] (one Separate XYZ per vector)."""
        if key not in separated:
            sep = separated[key] = nodes.new("ShaderNodeSeparateXYZ")
            sep.location = at
            links.new(params[key], sep.inputs[0])
        return separated[key].outputs[c]

    def tilt_of(closure):       # 0: the Diffuse, j + 1: lobe j
        if closure == 0:
            return component("lobe4", 2, (x, y - 1100))
        return component("tilt", closure - 1, (x, y - 900)) if closure <= 3 else component("lobe4", 1, (x, y - 1100))

    def normal_of(closure, bsdf):
        if not tilted[closure]:
            return
        mad = nodes.new("ShaderNodeVectorMath")
        mad.operation = 'MULTIPLY_ADD'          # T t + N: N exactly where t = 0
        mad.location = (bsdf.location[0] - 200, bsdf.location[1] - 100)
        links.new(unit.outputs[0], mad.inputs[0])
        links.new(tilt_of(closure), mad.inputs[1])
        links.new(normal, mad.inputs[2])
        links.new(mad.outputs[0], bsdf.inputs["Normal"])
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.location = (x + 400, y)
    links.new(scaled(params["kd"], scale_d, (x + 200, y)), diffuse.inputs["Color"])
    normal_of(0, diffuse)
    out = diffuse.outputs[0]
    for j, ks in enumerate(params["ks"]):
        glossy = nodes.new("ShaderNodeBsdfAnisotropic")     # "Glossy BSDF" in Blender >= 4.0
        glossy.distribution = 'GGX'
        glossy.location = (x + 400, y - 300 * (j + 1))
        links.new(scaled(ks, scale_s, (x + 200, y - 300 * (j + 1))), glossy.inputs["Color"])
        links.new(component("roughness", j, (x, y - 300)) if j < 3 else component("lobe4", 0, (x, y - 1100)),
                  glossy.inputs["Roughness"])
        aligned_to = (tangent if j < params["view_aligned"] else
                      material_tangent if j < params["material_aligned"] else None)
        if aligned_to is not None and "Anisotropy" in glossy.inputs:
            links.new(component("anisotropy", j, (x, y - 500)), glossy.inputs["Anisotropy"])
            links.new(aligned_to, glossy.inputs["Tangent"])
        elif "Anisotropy" in glossy.inputs:
            glossy.inputs["Anisotropy"].default_value = 0.0
        normal_of(j + 1, glossy)
        add = nodes.new("ShaderNodeAddShader")
        add.location = (x + 600, y - 300 * j - 150)
        links.new(out, add.inputs[0])
        links.new(glossy.outputs[0], add.inputs[1])
        out = add.outputs[0]
    return out


def lobe_tangent(tree, params, material_tangent, loc):
    """The tangent a material-aligned fit's lobes take: `material_tangent` (the tables' frame,
    the group's Tangent input) turned about the normal by params["tangent_turn"] (right-handed:
    x toward y = N x x, as closure_fit.eval_fit turns it); Cycles projects it onto the surface
    after, as the exact back ends do."""
    if material_tangent is None:
        raise ValueError("a closure fit along the material's tangent needs that tangent")
    if not params["tangent_turn"]:
        return material_tangent
    geometry = tree.nodes.new("ShaderNodeNewGeometry")
    geometry.location = loc
    turned = tree.nodes.new("ShaderNodeVectorRotate")
    turned.rotation_type = 'AXIS_ANGLE'
    turned.location = (loc[0] + 200, loc[1])
    tree.links.new(material_tangent, turned.inputs["Vector"])
    tree.links.new(geometry.outputs["Normal"], turned.inputs["Axis"])
    turned.inputs["Angle"].default_value = params["tangent_turn"]
    return turned.outputs["Vector"]


def view_tangent(tree, loc, with_normal=False):
    """The view direction projected onto the shading surface, I - (I.N) N (Geometry's Incoming
    and Normal), nudged off zero as svm.VIEW_TANGENT_NUDGE says (the control variate's f_cv
    computes the same tangent): Cycles normalises cross(N, T), NaN for a zero tangent (a
    head-on view, where the fit's anisotropy is 0 anyway, and its tilts). `with_normal`: (the
    tangent, Geometry's Normal)."""
    from .svm import VIEW_TANGENT_EPS, VIEW_TANGENT_NUDGE
    nodes, links = tree.nodes, tree.links
    geometry = nodes.new("ShaderNodeNewGeometry")
    geometry.location = loc
    incoming, normal = geometry.outputs["Incoming"], geometry.outputs["Normal"]

    def vmath(op, at, *inputs):
        node = nodes.new("ShaderNodeVectorMath")
        node.operation = op
        node.location = (loc[0] + 200 * at, loc[1])
        for socket, value in zip(node.inputs, inputs):
            if isinstance(value, tuple):
                socket.default_value = value
            else:
                links.new(value, socket)
        return node.outputs["Value" if op == 'DOT_PRODUCT' else "Vector"]
    i_dot_n = vmath('DOT_PRODUCT', 1, incoming, normal)
    projected = vmath('SUBTRACT', 3, incoming, vmath('MULTIPLY', 2, normal, i_dot_n))
    nudge = vmath('CROSS_PRODUCT', 4, normal, VIEW_TANGENT_NUDGE)
    tangent = vmath('MULTIPLY_ADD', 5, nudge, (VIEW_TANGENT_EPS,) * 3, projected)
    return (tangent, normal) if with_normal else tangent


def build_fit(tree, fit, loc=(-1400, -400), material_tangent=None):
    """The fit back end's closures (a neutral grey diffuse without a fit); returns their
    shader output socket. `material_tangent`: the tables' frame (the group's Tangent input),
    which a material-aligned fit's lobes take."""
    if fit is None:
        diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
        diffuse.location = (loc[0] + 3400, loc[1])
        diffuse.inputs["Color"].default_value = (*NEUTRAL, 1.0)
        return diffuse.outputs[0]
    return closures(tree, fit_params(tree, fit, loc), loc, material_tangent=material_tangent)
