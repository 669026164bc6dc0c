"""The portal direction's mixture (`_Mixture`): the tables, the world's map, the sky's sun and the
lamps the portal reaches (blender_addon/render/osl/learned_bsdf.osl, lamps.h), a branch per technique;
`update_world` hands a built graph new world inputs. What it does and measured: docs/svm.md."""
import math

from .. import sockets
from .control_variate import CV, _cv_value, _matching
from .graph import X, Y, Z, _image, _mix_shader, compare, cos, drop_unused, fma, maximum, minimum, sin, sqrt, where
from .tables import _tables_call, _tables_sample
from .world import (_WORLD_GROUPS, _is_world_group, _world_group_name, _world_pdf_group, _world_sample_group,
                    world_layout)

WORLD = "FlowBSDF SVM world"    # a Combine XYZ node per mixture: (WorldShare, SunShare, SunCos)
SUN = "FlowBSDF SVM sun"        # a Combine XYZ node per mixture with a sun: SunDirection
LIGHT = "FlowBSDF SVM light"    # a Combine XYZ node per matched control variate: LightDirection
LAMP = "FlowBSDF SVM lamp"      # per lamp technique two Combine XYZ nodes lamps.bind_svm drives
LAMPS = "FlowBSDF SVM lamps"    # a Value node per mixture with lamps: their share (LampShare)


class _Mixture:
    """The portal direction's mixture (docs/svm.md) for the world inputs `world`
    (blender_addon/world.shader_inputs): which techniques the graph has, its value nodes, and
    its branches. False when it has none (then the graph is the tables' alone)."""

    def __init__(self, world):
        world = dict(world or {})
        self.inputs = world
        self.path = str(world.get("World") or "")
        self.map = world_layout(self.path) if world.get("WorldShare", 0.0) > 0.0 else None
        self.sun = bool(world.get("SunShare", 0.0) > 0.0 and world.get("SunCos", 1.0) < 1.0)
        self.lamps = int(world.get("Lamps", 0)) if world.get("LampShare", 0.0) > 0.0 else 0
        self.light = _light_direction(world)
        # no small light in the world: the control variate is matched to the lamp that lights
        # the shading point most
        self.match_lamp = self.light is None and self.lamps > 0
        self._lamp_nodes = self._lamp_data = None

    def light_axis(self, g, at):
        """The small light's direction at the shading point: the world's (LightDirection, from
        its named node: update_world) or the brightest lamp's there."""
        if self.match_lamp:
            return self.lamp_data(g, at)["axis"]
        node = g.node("ShaderNodeCombineXYZ", name=LIGHT, label=LIGHT)
        for socket, value in zip(node.inputs, self.light):
            socket.default_value = value
        return g.vmath('NORMALIZE', node.outputs[0])

    def __bool__(self):
        return self.map is not None or self.sun or self.lamps > 0

    def lamp_nodes(self, g):
        """Per lamp technique its two named nodes' outputs (lamps.bind_svm drives them): place (a
        sun's direction) and (radius or a sun's angle, power, 1 for a sun)."""
        if self._lamp_nodes is None:
            self._lamp_nodes = []
            for k in range(self.lamps):
                where = g.node("ShaderNodeCombineXYZ", name=f"{LAMP} {k}", label=f"{LAMP} {k}")
                size = g.node("ShaderNodeCombineXYZ", name=f"{LAMP} {k} size", label=f"{LAMP} {k} size")
                where["flowbsdf_lamp"], size["flowbsdf_lamp_size"] = k, k
                self._lamp_nodes.append((where.outputs[0], size.outputs[0]))
        return self._lamp_nodes

    def lamp_cone(self, g, p, place, size):
        """A lamp technique's cone at the shading point p (its axis unnormalised, "to"; 1 - cos of
        its half angle) about the lamp's bounding sphere (a sun lamp: about its direction, of its
        angle), and the weight that shares the lamps' draws (~ irradiance: power / distance^2, a
        sun's strength)."""
        radius, power, is_sun = (g.dot(size, axis) for axis in (X, Y, Z))
        to = g.vmath('SUBTRACT', place, g.scale(p, 1.0 - is_sun))
        d2 = maximum(g.dot(to, to), radius * radius)
        s2 = minimum(radius * radius / d2, 1.0)
        # 1 - cos without cancellation: sin^2 / (1 + cos) for a sphere, 2 sin^2(angle / 4) for a sun
        sphere = s2 / (1.0 + sqrt(1.0 - s2))
        half = sin(radius * 0.25)
        omc = where(is_sun, half * half * 2.0, sphere)
        return {"to": to, "omc": omc, "weight": where(is_sun, power, power / d2)}

    def lamp_data(self, g, at):
        """Before the branches: the lamps' total weight, the largest, the brightest lamp's axis
        (the matched control variate's) and (values) the lamps' share c_lamp."""
        if self._lamp_data is None:
            total = best = to = None
            for place, size in self.lamp_nodes(g):
                cone = self.lamp_cone(g, at["p"], place, size)
                if total is None:
                    total, best, to = cone["weight"], cone["weight"], cone["to"]
                    continue
                total = total + cone["weight"]
                better = cone["weight"] > best
                to = g.vmath('MULTIPLY_ADD', cone["to"], g.combine(better, better, better), g.scale(to, 1.0 - better))
                best = maximum(best, cone["weight"])
            # (normalised once, as picked: the same axis as the brightest lamp's own cone has)
            self._lamp_data = {"total": total, "best": best, "axis": g.vmath('NORMALIZE', to) if self.match_lamp else None}
        return self._lamp_data

    def lamp_stream(self, g, at, tag):
        """Each lamp's cone at the shading point with its share c_k ("c": LampShare x its weight /
        the total, the matched lamp's x scale) and "cone" (c_k p_k inside the cone), one lamp at
        a time (a generator: a caller that folds them in keeps one lamp's values alive, not all),
        from a position through a no-op of its own (`tag`): values the branches shared Cycles
        would compute before them and hold on its stack through all (measured: 4 lamps so took
        28 of its 255 floats)."""
        p = g.vmath('MAXIMUM', at["p"], (-1e30 * tag,) * 3)
        data = self._lamp_data
        share = self.lamp_share / data["total"]
        for place, size in self.lamp_nodes(g):
            cone = self.lamp_cone(g, p, place, size)
            cone["axis"] = g.vmath('NORMALIZE', cone["to"])
            c = cone["weight"] * share
            if self.match_lamp and self.scale is not None:   # the brightest lamp's draws scaled
                top = 1.0 - (cone["weight"] < data["best"])
                c = c * fma(top, self.scale - 1.0, 1.0)
            cone["c"] = c
            cone["cone"] = c / (cone["omc"] * (2.0 * math.pi))
            yield cone

    def values(self, g, at, scale=None):
        """The named nodes the add-on changes (update_world) and the shares, sun axis and cones
        from them (constants to Cycles: it folds them; a lamp's share varies over the surface).
        `scale`: a matched control variate's points (1 elsewhere): fewer draws of the matched
        light, whose part of the rest is ~0."""
        node = g.node("ShaderNodeCombineXYZ", name=WORLD, label=WORLD)
        node["flowbsdf_map"] = self.path if self.map else ""
        node["flowbsdf_sun"] = int(self.sun)
        node["flowbsdf_lamps"] = self.lamps
        for socket, value in zip(node.inputs, _world_values(self.inputs, self.map is not None, self.sun)):
            socket.default_value = value
        shares = node.outputs[0]
        self.scale = scale
        if scale is not None and not self.match_lamp:
            shares = g.vmath('MULTIPLY', shares, g.combine(scale, scale, 1.0))
        rest = 1.0
        if self.lamps:
            value = g.node("ShaderNodeValue", name=LAMPS, label=LAMPS)
            value.outputs[0].default_value = float(self.inputs.get("LampShare", 0.0))
            self.lamp_share = g.outputs(value)[0]
            data = self.lamp_data(g, at)
            self.c_lamp = self.lamp_share
            if self.match_lamp and scale is not None:       # LampShare (total - (1 - scale) best) / total
                self.c_lamp = self.lamp_share * (1.0 - (1.0 - scale) * data["best"] / data["total"])
            rest = 1.0 - self.c_lamp
        # the world's techniques share what the lamps leave (a technique the graph lacks: 0)
        self.c_world = (g.dot(shares, X) * rest if self.lamps else g.dot(shares, X)) if self.map else g.const(0.0)
        self.c_sun = g.const(0.0)
        if self.sun:
            sun = g.node("ShaderNodeCombineXYZ", name=SUN, label=SUN)
            for socket, value in zip(sun.inputs, self.inputs["SunDirection"]):
                socket.default_value = value
            self.sun_cos = g.dot(shares, Z)
            self.c_sun = g.dot(shares, Y) * (self.sun_cos < 1.0)
            if self.lamps:
                self.c_sun = self.c_sun * rest
            self.axis = g.vmath('NORMALIZE', sun.outputs[0])
            self.omc = 1.0 - self.sun_cos
            # c_sun p_cone inside the cone (0 for c_sun = 0: Cycles' divide by 0 gives 0)
            self.cone = self.c_sun / (self.omc * (2.0 * math.pi))
        self.c_light = self.c_sun + self.c_world
        if self.lamps:
            self.c_light = self.c_light + self.c_lamp
        self.c_tables = 1.0 - self.c_light

    @staticmethod
    def sample_cone(g, axis, omc, u0, u1):
        """lamps.h cone_direction: uniform in the cone about `axis` of 1 - cos its half angle
        `omc` (1 - cos computed as t (2 - t))."""
        near_x = 1.0 - (abs(g.dot(axis, X)) < 0.9)
        tx = g.vmath('NORMALIZE', g.vmath('CROSS_PRODUCT', axis, g.combine(1.0 - near_x, near_x)))
        ty = g.vmath('CROSS_PRODUCT', axis, tx)
        t = u0 * omc
        s = sqrt(t * (2.0 - t))
        phi = u1 * (2.0 * math.pi)
        d = g.vmath('ADD', g.vmath('ADD', g.scale(tx, s * cos(phi)), g.scale(ty, s * sin(phi))), g.scale(axis, 1.0 - t))
        return g.vmath('NORMALIZE', d)

    def light_pdf(self, g, d, own, at=None, tag=0, drawn=None, lamps=None):
        """c_world p_world(d) + c_sun p_cone(d) + the lamps' c_k p_k(d) (`lamps`, or lamp_stream
        with `tag` at `at`), the technique `own` left out (its caller adds its own sample's
        density); in the lamps' branch the lamp of index `drawn` counts as inside its cone."""
        total = None

        def add(term):
            nonlocal total
            total = term if total is None else total + term
        if self.map and own != "world":
            add(self.c_world * g.group(self.pdf_group(), Direction=d)[0])
        if self.sun and own != "sun":
            add(self.cone * (1.0 - (g.dot(d, self.axis) < self.sun_cos)))
        for k, lamp in enumerate(lamps if lamps is not None else self.lamp_stream(g, at, tag) if self.lamps else ()):
            # inside the cone: 1 - cos = |d - axis|^2 / 2 (no cancellation for small cones)
            gap = g.vmath('DISTANCE', d, lamp["axis"])
            inside = gap * gap * 0.5 < lamp["omc"]
            if drawn is not None:
                inside = maximum(inside, compare(drawn, float(k), 0.25))
            add(lamp["cone"] * inside)
        return 0.0 if total is None else total

    def pdf_group(self):
        return _world_pdf_group(self.map, _image(self.path))

    def graph(self, g, sampler, at, closure, scale=None):
        """The mixture's shader: a branch per technique ending in closure(dict of direction,
        weight, q (the mixture's pdf), technique (0 tables, 1 map, 2 sun, 3 + k lamp k), ok (1
        when the direction counts)), chosen by u1 through Mix Shaders whose factor is exactly 0
        or 1 (Cycles skips the nodes of the branch not taken: svm.cpp generate_multi_closure):
        u1 in [0, c_sun) the sun, then the map, then the lamps (one branch: a branch per lamp
        took 7 more of Cycles' 255 stack floats per lamp), the rest the tables."""
        self.values(g, at, scale)
        u1 = at["u1"]
        techniques = ([("sun", self.c_sun)] if self.sun else []) + ([("world", self.c_world)] if self.map else []) \
            + ([("lamps", self.c_lamp)] if self.lamps else [])
        branches, start = [], 0.0
        for kind, share in techniques:
            end = start + share if start != 0.0 else share
            branches.append((end, self.light_branch(g, sampler, at, kind, start, share, closure)))
            start = end
        out = self.tables_branch(g, sampler, at, closure)
        for end, branch in reversed(branches):
            out = _mix_shader(g, u1 < end, out, branch)
        return out

    def tables_branch(self, g, sampler, at, closure):
        t1 = minimum((at["u1"] - self.c_light) / self.c_tables, 1.0 - 2.0 ** -24)
        wo, weight, pdf = _tables_sample(g, sampler, at["cos_i"], at["phi_i"], at["u0"], t1)
        d = _to_world(g, at, wo)
        q = fma(self.c_tables, pdf, self.light_pdf(g, d, "tables", at, 1))
        ok = _valid(g, at, wo[2], d)
        return closure({"direction": d, "weight": g.scale(weight, pdf * ok / q), "q": q, "technique": 0.0, "ok": ok})

    def light_branch(self, g, sampler, at, kind, start, share, closure):
        u0 = at["u0"]
        u1 = (at["u1"] - start if start != 0.0 else at["u1"]) / share
        drawn = lamps = None
        if kind == "sun":
            d = self.sample_cone(g, self.axis, self.omc, u0, u1)
            own, technique, noop = self.cone, 2.0, -2.0
        elif kind == "world":
            out = g.group(_world_sample_group(self.map, _image(self.path)), U0=u0, U1=u1)
            d, own, technique, noop = out["Direction"], self.c_world * out["Pdf"], 1.0, -1.0
        else:
            d, drawn, lamps = self.sample_lamps(g, at, u0, u1)
            own, technique, noop = 0.0, drawn + 3.0, -3.0
        # the other techniques' density first: the lamps' values (here the drawn ones, not made
        # twice) are then no longer alive while the tables' inverse runs
        light = self.light_pdf(g, d, kind, at, {"sun": 2, "world": 3, "lamps": 4}[kind], drawn, lamps)
        wo = tuple(g.dot(d, axis) for axis in (at["tx"], at["ty"], at["n"]))
        # its own incident nodes (cos theta_i through a no-op unlike the other branches'): Cycles
        # would merge identical ones into nodes run before the branches, their results held
        # on the stack through every branch
        out = _tables_call(g, sampler, "pdf", maximum(at["cos_i"], noop), at["phi_i"], X=wo[0], Y=wo[1], Z=wo[2])
        pdf, fcos = out["Pdf"], out["F cos"]
        q = fma(self.c_tables, pdf, own + light if kind != "lamps" else light)
        ok = _valid(g, at, wo[2], d)
        return closure({"direction": d, "weight": g.scale(fcos, ok / q), "q": q, "technique": technique, "ok": ok})

    def sample_lamps(self, g, at, u0, u1):
        """(direction, index of the lamp drawn, the lamps' values: lamp_stream's): the lamp by u1
        in parts c_k / c_lamp, u1 rescaled within its part, uniform in its cone (picked by flags:
        exact, x 1 and x 0)."""
        lo, axis, omc, v, index = 0.0, (0.0, 0.0, 0.0), 0.0, 0.0, g.const(0.0)
        last = self.lamps - 1
        lamps = list(self.lamp_stream(g, at, 5))
        for k, lamp in enumerate(lamps):
            part = lamp["c"] / self.c_lamp
            hi = lo + part if k else part
            above = 1.0 - (u1 < lo) if k else 1.0
            flag = above if k == last else above * (u1 < hi) if k else u1 < hi
            within = (u1 - lo if k else u1) / part
            if not last:
                axis, omc, v = lamp["axis"], lamp["omc"], within
                break
            axis = g.vmath('MULTIPLY_ADD', lamp["axis"], g.combine(flag, flag, flag), axis)
            omc = fma(lamp["omc"], flag, omc)
            v = fma(within, flag, v)
            index = fma(flag, float(k), index)
            lo = hi
        return self.sample_cone(g, axis, omc, u0, minimum(v, 1.0 - 2.0 ** -24)), index, lamps


def _light_direction(world):
    """The world's small light (LightDirection: a sun, a small sun in the map) or None."""
    d = tuple(float(x) for x in (world or {}).get("LightDirection", (0.0, 0.0, 0.0)))
    return d if any(d) else None


def _world_values(world, has_map, has_sun):
    """(WorldShare, SunShare, SunCos) of the world node: 0 for a technique the graph lacks."""
    return (float(world.get("WorldShare", 0.0)) if has_map else 0.0,
            float(world.get("SunShare", 0.0)) if has_sun else 0.0,
            float(world.get("SunCos", 1.0)) if has_sun else 1.0)


def _to_world(g, at, wo):
    return g.vmath('ADD', g.vmath('ADD', g.scale(at["tx"], wo[0]), g.scale(at["ty"], wo[1])), g.scale(at["n"], wo[2]))


def _valid(g, at, cos_o, d):
    """1 when wi and wo are above the shading surface and d above the geometric one, else 0."""
    return (at["cos_raw"] > 0.0) * ((cos_o > 0.0) * (g.dot(d, at["ng"]) > 0.0))


def update_world(tree, world):
    """Hand new world inputs (blender_addon/world.shader_inputs) to the sampler graphs in `tree`
    built with a world: their shares and sun (the named value nodes) and, for a new map, its
    node groups. Returns False when a graph lacks a technique the new inputs use (the map or
    the sun; or `tree` has no world graph and the inputs have a technique): rebuild it then."""
    mix = _Mixture(world)
    for node in tree.nodes:
        if node.name.startswith(CV):
            matched = _matching(mix, bool(node.get("flowbsdf_matchable", 0)))
            if node.get("flowbsdf_light", 0) != int(matched) \
                    or node.get("flowbsdf_match_lamp", 0) != int(matched and mix.match_lamp):
                return False
            sockets.assign(node.outputs[0], _cv_value(world))
        if node.name.startswith(LIGHT) and mix.light is not None:
            for socket, value in zip(node.inputs, mix.light):
                sockets.assign(socket, value)
    nodes = [node for node in tree.nodes if node.name.startswith(WORLD)]
    if not nodes:
        return not mix
    for node in nodes:
        if (mix.map and not node.get("flowbsdf_map")) or (mix.sun and not node.get("flowbsdf_sun")) \
                or mix.lamps > node.get("flowbsdf_lamps", 0):       # (slots it has and the scene leaves empty: power 0)
            return False
    for node in tree.nodes:
        if node.name.startswith(LAMPS) and node.bl_idname == "ShaderNodeValue":
            sockets.assign(node.outputs[0], float(mix.inputs.get("LampShare", 0.0)))
    for node in nodes:
        has_map, has_sun = bool(node.get("flowbsdf_map")), bool(node.get("flowbsdf_sun"))
        for socket, value in zip(node.inputs, _world_values(mix.inputs, has_map and mix.map, has_sun)):
            sockets.assign(socket, value)
        if mix.map and node["flowbsdf_map"] != mix.path:
            node["flowbsdf_map"] = mix.path
    if mix.sun:
        for node in tree.nodes:
            if node.name.startswith(SUN):
                for socket, value in zip(node.inputs, mix.inputs["SunDirection"]):
                    sockets.assign(socket, value)
    if mix.map:
        image, swapped = _image(mix.path), False
        for node in tree.nodes:
            if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
                for kind, build in _WORLD_GROUPS.items():
                    name = node.node_tree.name
                    if _is_world_group(name, kind) and name != _world_group_name(kind, mix.map, image):
                        node.node_tree, swapped = build(mix.map, image), True
        if swapped:
            drop_unused()
    return True
