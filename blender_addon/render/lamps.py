"""The scene's lamps, passed to the Learned BSDF's OSL shader (blender_addon/render/osl/lamps.h).

The shader has LAMP slots of sockets (`L<k>Kind`, `Flags`, `P`, `X`, `Y`, `Z`, `Color`,
`Strength`, `Size`). `bind(script, scene)` fills one slot per lamp that renders: the kind,
the flags and the shape are set as values (a change of lamp type, visibility or shape binds
again on the next scene update), everything that animates is a driver on the socket reading
the lamp: its world matrix (location and axes, scale included; an RNA path indexes
matrix_world by [column][row]), colour (times the blackbody
colour when Temperature is on), energy x 2^exposure, and sizes. Drivers evaluate without
Python (simple expressions), so keyframed lamps render right at every frame, in the
viewport and on farms, with auto-run off.

What the shader does not model is said by `limits(scene)`, which the node's status shows:
lamps past the slots, light linking, node-based lamp shaders (their Emission strength and
colour are not read), and zero-spread area lamps. What the SVM back end's portal cannot reach
is said by `unreachable(scene)`; `reach(lamp)` makes a lamp reachable (the status's button).
"""
import bpy

SLOTS = 8
KIND = {"POINT": 1, "SPOT": 2, "SUN": 3, "AREA": 4}
ELLIPSE = 5                                     # AREA with shape DISK or ELLIPSE
SHADOW, MIS, CAMERA, DIFFUSE, GLOSSY, SPHERE, NORMALIZE = 1, 2, 4, 8, 16, 32, 64
KEY = "flowbsdf_lamps"                          # on the group tree: the bound lamp set
SVM_SLOTS = 4                                   # lamps the SVM graph's portal draws toward
SVM_KEY = "flowbsdf_svm_lamps"                  # on the group tree: the lamp set its SVM graph is bound to


def renders(ob):
    return not ob.hide_render and any(not c.hide_render for c in ob.users_collection)


def scene_lamps(scene):
    """The light objects that render in `scene` (light portals are not lights), by name."""
    return sorted((ob for ob in scene.objects if ob.type == 'LIGHT' and renders(ob)
                   and not getattr(ob.data.cycles, "is_portal", False)), key=lambda ob: ob.name)


def unreachable(scene):
    """{lamp name: why} for the lamps the SVM back end's portal cannot hit, which so light only
    the fit's closures there (backends.resolve): a portal continuing a camera ray is a camera ray
    (lamps hidden from the camera are not hit), a point of radius 0 or a sun of angle 0 has no
    area to hit, and past a bounce Cycles hits only lamps with Multiple Importance on."""
    out = {}
    for ob in scene_lamps(scene):
        light = ob.data
        if not getattr(ob, "visible_camera", True):
            out[ob.name] = "hidden from the camera"
        elif light.type in ("POINT", "SPOT") and getattr(light, "shadow_soft_size", 0.0) <= 0.0:
            out[ob.name] = "radius 0"
        elif light.type == "SUN" and getattr(light, "angle", 0.0) <= 0.0:
            out[ob.name] = "angle 0"
        elif not getattr(light.cycles, "use_multiple_importance_sampling", True):
            out[ob.name] = "Multiple Importance off"
    return out


def svm_lamps(scene):
    """The lamps whose cones the SVM back end's portal draws directions in (svm._Mixture): the
    first SVM_SLOTS that render and that it can reach (`unreachable`)."""
    hidden = unreachable(scene)
    return [ob for ob in scene_lamps(scene) if ob.name not in hidden][:SVM_SLOTS]


def bind_svm(tree, scene):
    """Drive the SVM graph's lamp nodes (svm.LAMP: per lamp technique k its place, and its size,
    power and kind) in the group tree `tree` from svm_lamps(scene): a point, spot or area lamp's
    bounding sphere (centre, radius) and power / distance^2 share weight (power / 4 pi, an area's
    / pi: the radiant intensity of its axis), a sun lamp's direction (its +Z), angle and
    strength; each times its colour's mean. Does nothing when already bound to the same set."""
    obs = svm_lamps(scene)
    sig = signature(scene) + repr([ob.name for ob in obs])
    nodes = {("where", node["flowbsdf_lamp"]): node for node in tree.nodes if "flowbsdf_lamp" in node.keys()}
    nodes.update({("size", node["flowbsdf_lamp_size"]): node for node in tree.nodes
                  if "flowbsdf_lamp_size" in node.keys()})
    key = sig + repr(sorted(n.name for n in nodes.values()))
    if tree.get(SVM_KEY) == key:
        return
    for (part, k), node in nodes.items():
        for i in range(3):
            path = f'nodes["{node.name}"].inputs[{i}].default_value'
            try:
                tree.driver_remove(path)
            except TypeError:
                pass
            if k >= len(obs):
                node.inputs[i].default_value = 0.0
                continue
            ob, light = obs[k], obs[k].data
            sun = light.type == "SUN"
            if part == "where":
                _drive(tree, path, -1, ob, "m", {"m": (ob, f"matrix_world[{2 if sun else 3}][{i}]")})
                continue
            if i == 2:
                node.inputs[i].default_value = 1.0 if sun else 0.0
            elif i == 1:
                e, energy = _energy(light)
                per = "1" if sun else "0.3183" if light.type == "AREA" else "0.07958"
                mean = {f"c{c}": (light, f"color[{c}]") for c in range(3)}
                _drive(tree, path, -1, light, f"{e}*{per}*(c0+c1+c2)/3", {**energy, **mean})
            elif light.type == "AREA":
                a, b = _size_paths(light)[:2]
                cols = {f"m{c}{r}": (ob, f"matrix_world[{c}][{r}]") for c in (0, 1) for r in range(3)}
                _drive(tree, path, -1, light,
                       "0.5*sqrt(a*a*(m00*m00+m01*m01+m02*m02)+b*b*(m10*m10+m11*m11+m12*m12))",
                       {"a": (light, a), "b": (light, b or a), **cols})
            else:
                _drive(tree, path, -1, light, "s", {"s": (light, "angle" if sun else "shadow_soft_size")})
    tree[SVM_KEY] = key


def kind_of(light):
    if light.type == "AREA" and light.shape in ("DISK", "ELLIPSE"):
        return ELLIPSE
    return KIND.get(light.type, 0)


def flags_of(ob):
    light = ob.data
    flags = 0
    flags |= SHADOW if getattr(light, "use_shadow", True) else 0
    flags |= MIS if getattr(light.cycles, "use_multiple_importance_sampling", True) else 0
    flags |= CAMERA if getattr(ob, "visible_camera", True) else 0
    flags |= DIFFUSE if getattr(ob, "visible_diffuse", True) else 0
    flags |= GLOSSY if getattr(ob, "visible_glossy", True) else 0
    flags |= SPHERE if not getattr(light, "use_soft_falloff", True) else 0
    flags |= NORMALIZE if getattr(light, "normalize", True) else 0
    return flags


def _size_paths(light):
    """The data paths (on the light) of the Size socket's three components."""
    if light.type in ("POINT", "SPOT"):
        return ["shadow_soft_size"] + (["spot_size", "spot_blend"] if light.type == "SPOT" else [None, None])
    if light.type == "SUN":
        return ["angle", None, None]
    size_y = "size_y" if light.shape in ("RECTANGLE", "ELLIPSE") else "size"
    return ["size", size_y, "spread"]


def _drive(tree, path, index, id_, expression, variables):
    """A driver on tree[path][index]: `expression` over variables {name: (id, data path)}."""
    fc = tree.driver_add(path, index)
    drv = fc.driver
    drv.type = 'SCRIPTED'
    while drv.variables:
        drv.variables.remove(drv.variables[0])
    for name, (target, data_path) in variables.items():
        var = drv.variables.new()
        var.name = name
        var.type = 'SINGLE_PROP'
        var.targets[0].id_type = 'OBJECT' if isinstance(target, bpy.types.Object) else 'LIGHT'
        var.targets[0].id = target
        var.targets[0].data_path = data_path
    drv.expression = expression
    for mod in list(fc.modifiers):       # driver_add may add a generator: the driver alone decides
        fc.modifiers.remove(mod)


def _energy(light):
    """(driver expression, variables) of a lamp's energy x 2^exposure (Blender 4.2+'s exposure)."""
    if hasattr(light, "exposure"):
        return "e*pow(2, x)", {"e": (light, "energy"), "x": (light, "exposure")}
    return "e", {"e": (light, "energy")}


def _socket_path(script, name):
    return f'nodes["{script.name}"].inputs["{name}"].default_value'


def signature(scene):
    """What a binding depends on beyond animation: lamp names, kinds, flags and shapes."""
    return repr([(ob.name, ob.data.name, kind_of(ob.data), flags_of(ob), getattr(ob.data, "shape", ""),
                  getattr(ob.data, "use_temperature", False)) for ob in scene_lamps(scene)[:SLOTS]])


def bind(script, scene):
    """Fill the shader's lamp slots with `scene`'s lamps (drivers for what animates), the first
    `LampSlots` of them (a constant to Cycles' compile: where no lamp renders, it leaves the
    shader's lamp code out; scripts/osl_first_pixel.py measures the compile).
    Does nothing when the group is already bound to the same lamp set."""
    tree = script.id_data
    sig = signature(scene)
    if tree.get(KEY) == sig:
        return
    lamps = scene_lamps(scene)[:SLOTS]
    used = script.inputs.get("LampSlots")     # (a script of an older shader: none)
    if used is not None:
        used.default_value = len(lamps)
    for k in range(SLOTS):
        prefix = f"L{k}"
        for name in ("P", "X", "Y", "Z", "Color", "Strength", "Size"):
            path = _socket_path(script, prefix + name)
            try:
                tree.driver_remove(path)
            except TypeError:
                pass
        if k >= len(lamps):
            script.inputs[prefix + "Kind"].default_value = 0
            script.inputs[prefix + "Strength"].default_value = 0.0
            continue
        ob, light = lamps[k], lamps[k].data
        script.inputs[prefix + "Kind"].default_value = kind_of(light)
        script.inputs[prefix + "Flags"].default_value = flags_of(ob)
        for i in range(3):
            _drive(tree, _socket_path(script, prefix + "P"), i, ob, "m", {"m": (ob, f"matrix_world[3][{i}]")})
            for axis, col in (("X", 0), ("Y", 1), ("Z", 2)):
                _drive(tree, _socket_path(script, prefix + axis), i, ob, "m",
                       {"m": (ob, f"matrix_world[{col}][{i}]")})
            if getattr(light, "use_temperature", False):
                _drive(tree, _socket_path(script, prefix + "Color"), i, light, "c*t",
                       {"c": (light, f"color[{i}]"), "t": (light, f"temperature_color[{i}]")})
            else:
                _drive(tree, _socket_path(script, prefix + "Color"), i, light, "c", {"c": (light, f"color[{i}]")})
            path = _size_paths(light)[i]
            if path is None:
                script.inputs[prefix + "Size"].default_value[i] = 0.0
            else:
                _drive(tree, _socket_path(script, prefix + "Size"), i, light, "s", {"s": (light, path)})
        _drive(tree, _socket_path(script, prefix + "Strength"), -1, light, *_energy(light))
    tree[KEY] = sig


def _names(obs):
    names = [ob.name for ob in obs]
    return ", ".join(names[:2]) + (", ..." if len(names) > 2 else "")


def limits(scene):
    """What the shader does not light as Cycles would: [(what, the artist's step to fix it)]
    in the UI's words (empty when all is modelled)."""
    lamps = scene_lamps(scene)
    notes = []
    if len(lamps) > SLOTS:
        notes.append((f"{len(lamps) - SLOTS} lamps past the first {SLOTS} are not lit ({_names(lamps[SLOTS:])})",
                      f"Use at most {SLOTS} lamps"))
    linked = [ob for ob in lamps if getattr(getattr(ob, "light_linking", None), "receiver_collection", None)]
    if linked:
        notes.append((f"Light Linking is ignored ({_names(linked)})", "Clear Light Linking"))
    noded = [ob for ob in lamps[:SLOTS] if getattr(ob.data, "use_nodes", False)]
    if noded:
        notes.append((f"lamp nodes are not evaluated ({_names(noded)})", "Turn Off Lamp Nodes"))
    flat = [ob for ob in lamps[:SLOTS] if ob.data.type == "AREA" and getattr(ob.data, "spread", 1.0) <= 0.0]
    if flat:
        notes.append((f"area lamps of Spread 0 are not lit ({_names(flat)})", "Give Lamp a Spread"))
    return notes


# Why the SVM back end's portal cannot reach a lamp (`unreachable`), in the status's words, and
# the button that makes it reachable (`reach`): short enough for a button in the default sidebar.
REACH = {"hidden from the camera": ("{} is hidden from the camera", "Show Lamp to Camera"),
         "radius 0": ("{} has radius 0", "Give Lamp a Radius"),
         "angle 0": ("{} has angle 0", "Give Sun an Angle"),
         "Multiple Importance off": ("{} has Multiple Importance off", "Use Multiple Importance")}
RADIUS, ANGLE = 0.1, 0.00918            # what `reach` gives a lamp of none: Blender's defaults (m, rad)


def reach(ob):
    """Make lamp `ob` one the SVM back end's portal reaches (what `unreachable` asks for)."""
    light = ob.data
    ob.visible_camera = True
    if light.type in ("POINT", "SPOT") and light.shadow_soft_size <= 0.0:
        light.shadow_soft_size = RADIUS
    if light.type == "SUN" and light.angle <= 0.0:
        light.angle = ANGLE
    light.cycles.use_multiple_importance_sampling = True
    light.update_tag()
