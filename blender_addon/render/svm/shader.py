"""The SVM back end's shader: the shading point and its frame, the tables' sample (or the mixture's,
with the control variate) ending in Ray Portal BSDFs (`build_svm_sampler`), the sampler alone
(`sample_graph`) and its inverse (`tables_pdf_graph`). What the graph does: docs/svm.md."""
from .control_variate import (MATCHED_LIGHT_SCALE, _cv_closures, _cv_matched, _cv_pick, _cv_rest, _cv_switched,
                              _matching)
from .film import _film_u, _random
from .graph import X, _Graph, _mix_shader, atan2, maximum, raw, saturate
from .mixture import _Mixture
from .tables import _inverse, _Sampler, _tables_sample

CUTOFF = 1e-5           # Cycles' CLOSURE_WEIGHT_CUTOFF
TANGENT = (1.0, 0.0, 0.0)


def _frame(g, n, reference):
    """Unit x and y of the local frame: `reference` projected onto the plane of n, or any
    perpendicular where that vanishes (as learned_bsdf.osl)."""
    along = g.vmath('SUBTRACT', reference, g.scale(n, g.dot(reference, n)))
    usable = g.vmath('LENGTH', along) > 1e-7
    # cross(n, x) unless n is near x, then cross(n, (1, 1, 0))
    near_x = abs(g.dot(n, X)) > 0.9
    other = g.vmath('CROSS_PRODUCT', n, g.combine(1.0, near_x))
    tx = g.vmath('NORMALIZE', g.vmath('ADD', g.scale(along, usable), g.scale(other, 1.0 - usable)))
    return tx, g.vmath('CROSS_PRODUCT', n, tx)


def _shading(g, sampler, tangent):
    """The shading point: (geometry node, n, wi, cos theta_i as is and clamped to >= 0, and
    for anisotropic tables the frame (tx, ty) and phi_i, else None, None, None: the
    isotropic frame follows wi, `_frame(g, n, wi)`, built where it is used)."""
    geometry = g.node("ShaderNodeNewGeometry")
    n, wi = geometry.outputs["Normal"], geometry.outputs["Incoming"]
    cos_raw = g.dot(wi, n)
    frame = (None, None, None)
    if sampler.lay["P"] > 1:
        tx, ty = _frame(g, n, TANGENT if tangent is None else tangent)
        frame = (tx, ty, atan2(g.dot(wi, ty), g.dot(wi, tx)))
    return geometry, n, wi, cos_raw, maximum(cos_raw, 0.0), frame


def sample_graph(tree, texture_path, group_input_tangent_socket=None, location=(0.0, 0.0)):
    """Add to `tree` the sampler of the SVM texture `texture_path` without the closure: a dict
    of sockets: "direction" (world, unit), "weight" (colour W = baked f·cos / pdf), "pdf"
    (per steradian), "valid" (1 when cos theta_i > 0 and the direction is above the geometric
    surface, else 0), "position" (the shading point) and "u2" (a third uniform number of
    this path vertex, unused by the sampler; film-stratified u0, u1 are used). For building
    on: build_svm_sampler, or a mixture with another strategy (one-sample MIS, with
    tables_pdf_graph at the other strategy's direction). Anisotropic tables take their frame's
    x from `group_input_tangent_socket` (world x when None)."""
    return {key: raw(value) for key, value in _sample(_Graph(tree, location), texture_path,
                                                      group_input_tangent_socket).items()}


def _sample(g, texture_path, group_input_tangent_socket, cv=None):
    sampler = _Sampler(g, texture_path)
    geometry, n, wi, cos_raw, cos_i, (tx, ty, phi_i) = _shading(g, sampler, group_input_tangent_socket)
    light_path = g.node("ShaderNodeLightPath")
    u0, u1, u2 = _random(g, geometry, light_path)
    u0, u1 = _film_u(g, light_path, (u0, u1))
    take = None
    if cv is not None:
        take, u0 = _cv_pick(g, cv, u0)
    wo, weight, pdf = _tables_sample(g, sampler, cos_i, phi_i, u0, u1)
    if phi_i is None:
        tx, ty = _frame(g, n, wi)
    direction = g.vmath('ADD', g.vmath('ADD', g.scale(tx, wo[0]), g.scale(ty, wo[1])), g.scale(n, wo[2]))
    valid = (cos_raw > 0.0) * (g.dot(direction, geometry.outputs["True Normal"]) > 0.0)
    return {"direction": direction, "weight": weight, "pdf": pdf, "valid": valid,
            "position": geometry.outputs["Position"], "u2": u2, "wi": wi, "n": n, "take": take}


def build_svm_sampler(tree, texture_path, group_input_tangent_socket=None, location=(0.0, 0.0), world=None,
                      cv=None):
    """Add to the shader node tree `tree` the sampler of the SVM texture `texture_path`
    (bake/export/svm_export.ensure_svm_export) ending in a Ray Portal BSDF; returns its shader output
    socket. Anisotropic tables take their frame's x from `group_input_tangent_socket` (a
    vector socket, e.g. the Learned BSDF group's Tangent input), world x when None. Camera
    rays stratify u by the film when the current scene allows it (set_film updates that).
    `world`: the world inputs (blender_addon/world.shader_inputs: World, WorldShare,
    SunDirection, SunCos, SunShare): the portal direction is then drawn from the mixture of
    the tables, the world map and the sun (docs/svm.md); update_world changes them.
    Without a world map or sun to draw from (None, shares 0, no readable map), the graph is
    the tables' alone.
    `cv`: a control variate f_cv, the fit's Cycles closures (node._svm_backend: "fit" its
    parameters' sockets (node._fit_params: kd, ks per lobe, roughness, anisotropy) of a Diffuse
    and GGX Glossy BSDFs; "betas" (beta_d, beta_s, s) and "matched_share" (s_m in x) sockets;
    "has_betas"; "match_image" (the fit's match image path or None); "closures" (scale_d,
    scale_s) -> the closures' shader, kd and each ks scaled by those colours): a shading point
    takes the closures (colours beta kd, beta ks, weight 1 / (1 - s)) with probability 1 - s,
    else the portal carrying f - f_cv with weight (f - f_cv) cos / (q s), as two portals (its
    positive and negative channels); matched to the world's light where it has one.
    """
    g = _Graph(tree, location)
    mix = _Mixture(world)
    if cv is not None:
        cv = _cv_switched(g, cv, world, _matching(mix, bool(cv.get("match_image"))), mix.match_lamp)
    if mix:
        return _mixture(g, texture_path, group_input_tangent_socket, mix, cv)
    out = _sample(g, texture_path, group_input_tangent_socket, cv)
    # zero (the path ends) for light from below the surface or a direction below the geometry
    weight = g.scale(out["weight"], out["valid"])
    if cv is None:
        return _portal(g, weight, out["position"], out["direction"], out["u2"])
    rest = _cv_rest(g, cv, out["wi"], out["n"], out["direction"], weight, out["valid"], out["pdf"])
    return _mix_shader(g, out["take"], _cv_closures(g, cv),
                       _signed_portals(g, rest, out["position"], out["direction"], out["u2"]))


def _signed_portals(g, weight, position, direction, u2):
    """Two portals along `direction`, the positive and the negative channels of `weight`:
    Cycles picks a closure by its mean weight's magnitude, which for a colour of mixed signs
    may be near 0 while its channels are not (the path's weight over the pick would explode)."""
    pos = _portal(g, g.vmath('MAXIMUM', weight, (0.0, 0.0, 0.0)), position, direction, u2)
    neg = _portal(g, g.vmath('MINIMUM', weight, (0.0, 0.0, 0.0)), position, direction, u2)
    node = g.node("ShaderNodeAddShader")
    g.set(node.inputs[0], pos)
    g.set(node.inputs[1], neg)
    return node.outputs[0]


def _portal(g, weight, position, direction, u2):
    """A Ray Portal BSDF continuing the path along `direction` with colour `weight`. Cycles
    drops a closure of mean weight (magnitude) < CUTOFF: those below 2 CUTOFF are rouletted up
    to it."""
    keep = saturate(abs(g.dot(weight, (1.0 / 3, 1.0 / 3, 1.0 / 3))) * (0.5 / CUTOFF))
    survive = u2 * (1.0 - 2.0 ** -24) < keep
    weight = g.scale(weight, survive / keep)
    portal = g.node("ShaderNodeBsdfRayPortal")
    g.set(portal.inputs["Color"], weight)
    g.set(portal.inputs["Position"], position)
    g.set(portal.inputs["Direction"], direction)
    return portal.outputs["BSDF"]


def _mixture(g, texture_path, group_input_tangent_socket, mix, cv=None):
    """The shading point and its u (as _sample), then the mixture's branches, each ending in a
    portal (two with a control variate `cv`: build_svm_sampler)."""
    sampler = _Sampler(g, texture_path)
    geometry, n, wi, cos_raw, cos_i, (tx, ty, phi_i) = _shading(g, sampler, group_input_tangent_socket)
    light_path = g.node("ShaderNodeLightPath")
    u0, u1, u2 = _random(g, geometry, light_path)
    u0, u1 = _film_u(g, light_path, (u0, u1))
    if phi_i is None:
        tx, ty = _frame(g, n, wi)
    at = {"n": n, "wi": wi, "ng": geometry.outputs["True Normal"], "cos_raw": cos_raw, "cos_i": cos_i, "tx": tx, "ty": ty,
          "phi_i": phi_i, "u0": u0, "u1": u1, "p": geometry.outputs["Position"]}
    position = geometry.outputs["Position"]
    if cv is None:
        return mix.graph(g, sampler, at, lambda out: _portal(g, out["weight"], position, out["direction"], u2))

    scale = None
    if cv["matching"]:
        unmatched = None
        if mix.match_lamp:      # (the brightest lamp's share of the lamps' weight: equal time, 4096
            # Principled spp, studio: MSE x0.83 / 0.75 / 1.10 on satin / military / vch, 6 seeds)
            data = mix.lamp_data(g, at)
            unmatched = 1.0 - data["best"] / data["total"]
        cv = _cv_matched(g, cv, at, mix.light_axis(g, at), unmatched)
        scale = 1.0 - cv["matched"] * (1.0 - MATCHED_LIGHT_SCALE)
    take, at["u0"] = _cv_pick(g, cv, u0)

    def closure(out):
        rest = _cv_rest(g, cv, wi, n, out["direction"], out["weight"], out["ok"], out["q"])
        return _signed_portals(g, rest, position, out["direction"], u2)
    return _mix_shader(g, take, _cv_closures(g, cv), mix.graph(g, sampler, at, closure, scale))


def tables_pdf_graph(tree, texture_path, wo_socket, group_input_tangent_socket=None, location=(0.0, 0.0)):
    """Add to `tree` the inverse of the sampler: at the world direction `wo_socket` (a unit
    vector socket), the tables' pdf (per steradian, 0 below the shading surface) and baked
    f·cos (colour: W x pdf, 0 when wi or wo is below the surface), as Tables.pdf and
    Tables.eval x cos theta_o do. Returns (pdf socket, f·cos socket)."""
    g = _Graph(tree, location)
    sampler = _Sampler(g, texture_path)
    _, n, wi, cos_raw, cos_i, (tx, ty, phi_i) = _shading(g, sampler, group_input_tangent_socket)
    if phi_i is None:
        tx, ty = _frame(g, n, wi)
    local = tuple(g.dot(wo_socket, axis) for axis in (tx, ty, n))
    pdf, fcos = _inverse(g, sampler, cos_i, phi_i, local)
    fcos = g.scale(fcos, cos_raw > 0.0)
    return raw(pdf), fcos
