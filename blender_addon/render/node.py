"""The "Learned BSDF" node: a shader node group bound to one baked material.

A plain group node (ShaderNodeGroup), so a .blend renders with or without the add-on
installed, and materials append and link like any other. Its node tree, "Learned BSDF:
<material>", holds three back ends:

- OSL (Cycles on the CPU with Open Shading Language on): a Script node running
  osl/learned_bsdf.osl (stored in the .blend as a text block and compiled bytecode:
  osl_script.py). It samples the baked tables exactly, lights the material with the scene's
  lamps (next-event estimation with MIS: lamps.py passes them in by drivers) and draws
  the portal direction from a mixture of the tables, the world's importance map and a Sky
  Texture's sun (world.py renders the map), continuing the path with ray_portal_bsdf. Its
  input "Fallback" is the fit: with the OSL texture missing at render time it renders the
  fit instead of black. The scene's pixel filter and seed feed it (`film_settings`): on
  camera rays it stratifies its samples by their place in the pixel.
- SVM (every Cycles device, GPU included; Blender 5.0+): the same table sampler as plain
  shader nodes ending in a Ray Portal BSDF (svm.py, texture bake/export/svm_export.py): exact for
  the world and emissive surfaces; lamps are not light-sampled. Where the fit has a control
  variate (its `cv`), the fit's closures scaled by it render beside the portal, which then
  carries only the rest: Cycles' own light sampling of the world for most of the BSDF.
- fit: Cycles closures (Diffuse BSDF + GGX Glossy BSDF) whose colours and roughness are
  piecewise-linear functions of the view angle (Layer Weight "Facing" = 1 - cos theta_i),
  fitted at bake time (bake/export/closure_fit.py). Its parameters live in a node group of the
  .blend ("FlowBSDF fit: <hash>", shared by materials with the same fit: fit_nodes.py), so it renders
  everywhere (Eevee, previews) even when the table files are gone; approximate.

EEVEE renders none of the three as Cycles does (no OSL, no Ray Portal BSDF, no anisotropy): the
group's second output, "EEVEE", holds the fit's EEVEE fit (closure_fit: isotropic lobes of its
own, fit to the tables; a fit before FIT_VERSION 8: the fit's closures), and the material gets
two Material Outputs, target Cycles fed by "BSDF", target EEVEE by "EEVEE" (`_wire_outputs`):
each engine takes its own, and EEVEE compiles only the EEVEE fit's closures.

Two Mix Shaders pick one: "FlowBSDF SVM backend" (fit or SVM), then "FlowBSDF backend"
(that or OSL); with constant factors Cycles compiles only the chosen branch. The factors
follow the scene's back end ("auto", "osl", "svm", "fit"; `set_backend`, `backends.resolve`): auto
renders OSL where Cycles runs it, else the SVM graph, else (lamps would go unlit, or not
Cycles) the fit; the node's status says which and why (`node_status`). They are set before
every render (render_pre), on every scene and frame change (depsgraph_update_post,
frame_change_post: the viewport follows) and after loading a file (load_post), with the
lamps, film settings and world inputs; before saving (save_pre) they are set to what
renders without the add-on anywhere (SVM, or the fit where lamps render).
Binding data sits in the tree's custom property "flowbsdf" (binding.py).

Blenders without numpy or OSL (Debian's 3.4 for the batch path): nothing here imports
numpy at module load. The fit is read from its JSON file (<name>.fit.json, written by the
bake) with the json module, and the OSL texture is found by its content-hashed name
(derived.py); only missing or stale fits/textures need `bake` (numpy), imported on first use. Where Cycles
cannot run the OSL shader (`osl_script.osl_compiler_available`: Debian's 3.4, Blender < 4.4) there is no Script node
(an uncompiled one has no sockets and points at an add-on path that differs per machine),
and without the SVM graph's nodes (before 5.0) no SVM graph: the group holds the fit alone.
Opening such a file with the add-on where more back ends build rebuilds the group
(load_post, `upgrade`), as it does a group whose shader an older add-on compiled or whose
fit an older add-on made (refits.py: in a thread in the UI). The
group's socket is made with `tree.interface` (4.0+) or the legacy `tree.outputs` (3.x).

API (used by the add-on's UI and operators): register, unregister, assign_learned_bsdf,
set_backend, node_state, node_status, sync, update_world, film_settings; the back-end choice
and its words are backends.py's (backend_of, resolve, Status).
"""
from pathlib import Path

import bpy
from bpy.app.handlers import persistent

from .. import deps
from . import backends, binding, derived, fit_nodes, lamps, osl_script, refits, sockets, world

NODE_LABEL = "Learned BSDF"
SWITCH = "FlowBSDF backend"           # 1: OSL, else the SVM / fit switch below
SWITCH_SVM = "FlowBSDF SVM backend"     # 1: the SVM graph, 0: the fit
EEVEE_OUTPUT = "EEVEE"      # the group's output that the material's EEVEE-target Material Output takes


def svm_available():
    """Whether this Blender runs the SVM back end: the Ray Portal BSDF (4.2+) with Cycles' MIS of
    a lamp hit past a portal as 5.0 has it (4.5+: path_state_next), and a `bake` that imports
    (numpy). 4.2 LTS (past its support) renders the fit."""
    return (hasattr(bpy.types, "ShaderNodeBsdfRayPortal") and bpy.app.version >= (4, 5, 0)
            and deps.bake_module("export.svm_export") is not None)


# ------------------------------------------------------------------------------ the group

def _ensure_interface(tree):
    """The group's sockets: the BSDF output, the EEVEE output (the EEVEE fit's closures, which
    the material's EEVEE-target Material Output takes: _wire_outputs) and the Tangent input
    (anisotropic tables' frame: world x when unlinked, projected onto the tangent plane by the
    shader)."""
    if not sockets.has_socket(tree, "BSDF", "OUTPUT"):
        sockets.new_socket(tree, "BSDF", "OUTPUT", "NodeSocketShader")
    if not sockets.has_socket(tree, EEVEE_OUTPUT, "OUTPUT"):
        sockets.new_socket(tree, EEVEE_OUTPUT, "OUTPUT", "NodeSocketShader")
    if not sockets.has_socket(tree, "Tangent", "INPUT"):
        sockets.new_socket(tree, "Tangent", "INPUT", "NodeSocketVector").default_value = TANGENT


def _svm_backend(tree, svm_texture, fit, tangent, world_inputs, loc=(-1400, -3000)):
    """The SVM back end's shader: the sampler's portal mixture (svm.build_svm_sampler), with a
    fit its control variate: the fit's closures scaled by its `cv` betas (or matched to the
    world's small light: svm.py), which Cycles lights with its lamp and world sampling, taken
    with probability 1 - s; else the portal carrying the rest (bake/export/closure_fit.py)."""
    from . import svm
    has_betas = fit is not None and any(b[0] > 0.0 or b[1] > 0.0 for b in fit["cv"])
    # (a match image only where some view angle is matched: else no lookups)
    match = fit.get("match_path") if fit and any(fit_nodes.matched_share(e) > 0.0 for e in fit["rel_error"]) else None
    if not (has_betas or match) or not svm.control_variate_wanted(svm_texture, fit):
        return svm.build_svm_sampler(tree, svm_texture, tangent, location=loc, world=world_inputs)
    params = fit_nodes.fit_params(tree, fit, (loc[0], loc[1] + 1600), cv=True)
    # (a material-aligned fit's turned tangent made once: the closures and the graph's f_cv take it)
    turned = fit_nodes.lobe_tangent(tree, params, tangent, (loc[0] + 2400, loc[1] + 300)) if params["material_aligned"] else None
    cv = {"fit": params, "betas": params["cv"], "matched_share": params["matched"],
          "has_betas": has_betas, "match_image": match, "tangent": turned,
          "closures": lambda sd, ss: fit_nodes.closures(tree, params, (loc[0], loc[1] + 1600), sd, ss, tilts=svm.CV_TILTS,
                                                        turned_tangent=turned)}
    return svm.build_svm_sampler(tree, svm_texture, tangent, location=loc, world=world_inputs, cv=cv)


def _build_tree(tree, name, tables_path, fit_path):
    """(Re)build the group's nodes for a material; records the binding in tree["flowbsdf"]."""
    problems = []
    fit = None
    osl_texture = svm_texture = ""
    with_osl, with_svm = osl_script.osl_compiler_available(), svm_available()
    if tables_path.is_file():
        # The OSL texture is recorded even where OSL cannot compile: a Blender that can rebuilds
        # the group from it (`upgrade`).
        try:
            osl_texture = derived.osl_texture(tables_path)
        except Exception as e:      # noqa: BLE001  (a broken table file must not break the material)
            problems.append(f"no OSL texture: {e}")
        if with_svm:
            try:
                svm_texture = derived.svm_texture(tables_path)
            except Exception as e:      # noqa: BLE001
                problems.append(f"no SVM texture: {e}")
    else:
        problems.append(f"tables missing: {tables_path}")
    try:
        if fit_path is None and tables_path.is_file():
            fit_path = derived.fit_file(tables_path)
        if fit_path is not None:
            fit = derived.load_fit(fit_path)
    except Exception as e:          # noqa: BLE001
        problems.append(f"fit unavailable: {e}")

    tree.nodes.clear()
    if tree.animation_data:
        tree.animation_data_clear()         # the lamps' drivers pointed at the old nodes
    if lamps.KEY in tree.keys():
        del tree[lamps.KEY]
    _ensure_interface(tree)
    nodes, links = tree.nodes, tree.links
    out = nodes.new("NodeGroupOutput")
    out.location = (2600, 0)
    group_in = nodes.new("NodeGroupInput")
    group_in.location = (1900, 600)
    fit_out = fit_nodes.build_fit(tree, fit, material_tangent=group_in.outputs["Tangent"])
    # EEVEE's closures: the fit's own EEVEE fit (isotropic lobes: EEVEE renders no anisotropy),
    # else (a fit before FIT_VERSION 8, or none) the fit's closures
    eevee = fit.get("eevee") if fit else None
    links.new(fit_nodes.build_fit(tree, eevee, loc=(-1400, 1400)) if eevee else fit_out, out.inputs[EEVEE_OUTPUT])
    info = {"material": name, "tables": str(tables_path), "fit": str(fit_path or ""),
            "osl_texture": osl_texture, "svm_texture": svm_texture, "has_fit": fit is not None,
            "has_osl": with_osl, "fit_error": float(fit.get("error", -1.0)) if fit else -1.0,
            "fit_error_of": fit.get("l1_of", "") if fit else "", "fit_version": int(fit["version"]) if fit else 0,
            # what EEVEE shows: the EEVEE fit's error (else the fit's closures without their anisotropy: unknown)
            "eevee_error": float(eevee.get("error", -1.0)) if eevee else -1.0,
            # (fits before the key: view_aligned 0 was the anisotropic tables' mark)
            "anisotropic": bool(fit.get("anisotropic", fit.get("view_aligned", 1) == 0)) if fit else False,
            "matte": world.matte_fraction(fit),
            "problems": "; ".join(problems)}
    shader = fit_out
    if svm_texture:
        world_inputs = world.material_share(_world_inputs(bpy.context.scene, tables_path.parent, bake=False),
                                            info["matte"])
        svm_out = _svm_backend(tree, svm_texture, fit, group_in.outputs["Tangent"],
                               caustics_gate(bpy.context.scene, world_inputs))
        for image in bpy.data.images:       # the texture's image, relative to the .blend as the tables are
            if image.filepath and bpy.path.abspath(image.filepath) == svm_texture:
                image.filepath = binding.relative(svm_texture)
        shader = _switched(tree, SWITCH_SVM, shader, svm_out, (2200, -300))
    if with_osl:                # else no Script node at all (see the module docstring); `upgrade` adds it
        script = osl_script.make_script_node(tree)
        script.name = script.label = osl_script.SCRIPT
        script.location = (2200, 300)
        script.inputs["Tables"].default_value = osl_texture
        script.inputs["Carried"].default_value = info["carry_texture"] = derived.carry_texture(tables_path)
        links.new(fit_out, script.inputs["Fallback"])
        links.new(group_in.outputs["Tangent"], script.inputs["Tangent"])
        script["flowbsdf_src"] = osl_script.source_hash()
        shader = _switched(tree, SWITCH, shader, script.outputs["BSDF"], (2400, 0))
    links.new(shader, out.inputs["BSDF"])
    binding.write(tree, info)


def _switched(tree, name, off, on, location):
    """A Mix Shader between two shaders whose factor is a Value node named `name` (0: off,
    1: on). With a constant factor Cycles compiles only the chosen side."""
    switch = tree.nodes.new("ShaderNodeValue")
    switch.name = switch.label = name
    switch.outputs[0].default_value = 0.0
    switch.location = (location[0], location[1] + 200)
    mix = tree.nodes.new("ShaderNodeMixShader")
    mix.location = location
    tree.links.new(switch.outputs[0], mix.inputs["Fac"])
    tree.links.new(off, mix.inputs[1])
    tree.links.new(on, mix.inputs[2])
    return mix.outputs[0]


def upgrade(tree):
    """Rebuild a group made where a back end could not be built and can be here (OSL where
    Cycles compiles it, the SVM graph where Blender has the Ray Portal BSDF), or by an add-on
    whose OSL shader differs (its bytecode would not read the current texture layout and
    would render the fallback) or whose fit is of another version (refit from the tables, the
    SVM back end's match image with it). Returns True when it rebuilt the group."""
    if tree.library is not None:
        return False
    info = binding.read(tree)
    if not info.get("material") or not info.get("tables"):
        return False
    script = tree.nodes.get(osl_script.SCRIPT)
    stale_osl = osl_script.osl_compiler_available() and (script is None
                                                          or script.get("flowbsdf_src") != osl_script.source_hash())
    missing_svm = svm_available() and not binding.has_svm(tree) and Path(info["tables"]).is_file()
    stale_fit = refits.stale_fit(tree)
    if not (stale_osl or missing_svm or stale_fit):
        return False
    fit = Path(info["fit"]) if info.get("fit") and not stale_fit else None
    _build_tree(tree, info["material"], Path(info["tables"]), fit)
    for material in bpy.data.materials:     # (a group from before the EEVEE output: the materials' outputs too)
        if material.node_tree is not None and material.library is None:
            for n in material.node_tree.nodes:
                if n.bl_idname == "ShaderNodeGroup" and n.node_tree == tree:
                    _wire_outputs(material.node_tree, n)
    return True


def assign_learned_bsdf(material, name, tables_path, fit_path=None):
    """Bind `material` (a bpy Material) to the baked material `name`.

    Creates or rebuilds the node group "Learned BSDF: <name>" from `tables_path` (the
    baked .exr; its OSL texture and closure fit are made next to it when missing or stale,
    unless `fit_path` names a fit file), puts one "Learned BSDF" group node in the
    material's tree (reusing one bound to the same group) and connects it to the material
    output's Surface. Missing tables are not an error: the node then renders the fit (or a
    neutral grey when there is no fit either) and `node_status` says why. Returns the node.
    """
    tables_path = Path(bpy.path.abspath(str(tables_path)))
    fit_path = None if fit_path is None else Path(bpy.path.abspath(str(fit_path)))
    tree = binding.tree_for(name)
    scene = bpy.context.scene
    if scene is not None and scene.render.engine == 'CYCLES' and tables_path.is_file():
        _world_inputs(scene, tables_path.parent, bake=True)     # the world's map first: one graph, with it
    _build_tree(tree, name, tables_path, fit_path)
    if material.node_tree is None:
        material.use_nodes = True
    mtree = material.node_tree
    node = None
    for n in mtree.nodes:
        if n.bl_idname == "ShaderNodeGroup" and n.node_tree is not None and binding.TREE_KEY in n.node_tree.keys():
            node = n
            break
    output = _output(mtree, ("ALL", "CYCLES"))
    if output is None:
        output = mtree.nodes.new("ShaderNodeOutputMaterial")
        output.location = (200, 300)
    if node is None:
        node = mtree.nodes.new("ShaderNodeGroup")
        node.location = _beside(output)
    node.node_tree = tree
    node.label = NODE_LABEL
    node.name = NODE_LABEL
    node.width = 220
    # The Tangent input orients anisotropic tables only (isotropic ones render the same for any).
    node.inputs["Tangent"].hide = not binding.read(tree).get("anisotropic", False)
    mtree.links.new(node.outputs["BSDF"], output.inputs["Surface"])
    _wire_outputs(mtree, node, output)
    if hasattr(material.cycles, "emission_sampling"):
        # The shader's emission is the lamps' reflected light, not a light source: Cycles must
        # not sample it as one (measured: same image with AUTO, 2-4x slower).
        material.cycles.emission_sampling = 'NONE'
    for scene in bpy.data.scenes:
        sync(scene, bake_world=scene.render.engine == 'CYCLES')
    return node


def _output(mtree, targets):
    """The material's Material Output of one of `targets` ("ALL", "CYCLES", "EEVEE"), the
    active one first; None where it has none."""
    outputs = [n for n in mtree.nodes if n.bl_idname == "ShaderNodeOutputMaterial" and n.target in targets]
    return next((n for n in outputs if n.is_active_output), None) or next(iter(outputs), None)


def _wire_outputs(mtree, node, output=None):
    """Cycles and EEVEE each their own Material Output: `output` (the one the node's BSDF feeds,
    found when None) set to target Cycles, and one of target EEVEE (made beside it when the
    material has none) taking the node's EEVEE output. Each engine renders its own target's
    output whichever is active (Blender prefers the exact target), and compiles only what
    feeds it: EEVEE no OSL or SVM graph."""
    if EEVEE_OUTPUT not in node.outputs:
        return
    if output is None:
        output = next((l.to_node for l in node.outputs["BSDF"].links
                       if l.to_node.bl_idname == "ShaderNodeOutputMaterial"), None)
        if output is None:
            return
    output.target = 'CYCLES'
    eevee = _output(mtree, ("EEVEE",))
    if eevee is None:
        eevee = mtree.nodes.new("ShaderNodeOutputMaterial")
        eevee.location = (output.location.x, output.location.y - 160)
        eevee.target = 'EEVEE'
    mtree.links.new(node.outputs[EEVEE_OUTPUT], eevee.inputs["Surface"])


def _beside(output):
    """Where a new Learned BSDF node goes: above the node it replaces at the output's Surface
    (which keeps its place, unlinked, not hidden under the new one), else left of the output."""
    surface = output.inputs["Surface"]
    if surface.is_linked:
        old = surface.links[0].from_node
        return old.location.x, old.location.y + 260
    return output.location.x - 300, output.location.y


# ------------------------------------------------------------------------------ back ends, film, world

def set_backend(scene, backend):
    """Choose the back end for `scene`: "osl", "fit" or "auto" (OSL when the scene renders
    with Cycles on the CPU with Open Shading Language on, else the fit); applies it now."""
    if backend not in backends.BACKENDS:
        raise ValueError(f"FlowBSDF back end must be one of {backends.BACKENDS}, not {backend!r}")
    if hasattr(bpy.types.Scene, backends.SCENE_PROP):
        setattr(scene, backends.SCENE_PROP, backend)
    else:
        scene[backends.SCENE_PROP] = backend
    sync(scene)


def _refresh_export(tree):
    """Re-export the textures when the tables exist but a texture is missing or stale: the
    OSL shader takes the new file's name; the SVM graph, whose constants come from its
    texture's layout, is rebuilt (with the whole group)."""
    info = binding.read(tree)
    tables = Path(info.get("tables", ""))
    if not tables.is_file():
        return
    if binding.has_svm(tree):
        try:
            current = derived.svm_texture(tables)
        except Exception as e:      # noqa: BLE001
            current = info.get("svm_texture")
            print(f"FlowBSDF: no SVM texture for {tables}: {e}")
        if current != info.get("svm_texture"):
            _build_tree(tree, info["material"], tables, Path(info["fit"]) if info.get("fit") else None)
            return
    script = tree.nodes.get(osl_script.SCRIPT)
    if script is None:
        return
    try:
        texture = derived.osl_texture(tables)
    except Exception as e:      # noqa: BLE001
        info["problems"] = f"no OSL texture: {e}"
        binding.write(tree, info)
        return
    carried, socket = derived.carry_texture(tables), script.inputs.get("Carried")     # (a script of an older shader: none)
    if texture != script.inputs["Tables"].default_value or (socket is not None and carried != socket.default_value):
        script.inputs["Tables"].default_value = texture     # OSL reads absolute paths only
        if socket is not None:
            socket.default_value = info["carry_texture"] = carried
        info["osl_texture"] = texture
        binding.write(tree, info)


TANGENT = (1.0, 0.0, 0.0)       # the group's Tangent input when unlinked: world x (the tracer's default)
FILM_FILTERS = {'BOX': 1, 'BLACKMAN_HARRIS': 2, 'GAUSSIAN': 3}
FILM_PROP = "flowbsdf_film_u"


def film_u_wanted(scene):
    """Whether camera rays take u from their place in the pixel (the scene's setting, on by
    default; its stored value where the add-on has not registered the property)."""
    return bool(getattr(scene, FILM_PROP, scene.get(FILM_PROP, True)))


def film_settings(scene):
    """What the OSL shader needs to stratify camera-ray samples: {input name: value}
    (the pixel filter as the shader's code, 0 = hash u instead; its width; the render's seed).
    Cycles' box filter is one pixel wide whatever the width setting (which its UI hides for
    the box). The scene can turn it off (`flowbsdf_film_u`): u taken from a sample's place in
    its pixel is tied to where in the pixel the shading point lies, so where the light changes
    across a pixel its estimate keeps an error that more samples shrink slower than noise
    (measured, sky + sun on a sphere, MSE against a converged image, film / hashed u: 24 px
    wide, 64 spp 0.092 / 0.367, 512 spp 0.032 / 0.043; 96 px wide, 128 spp 0.031 / 0.182,
    1024 spp 0.0068 / 0.024): far less error at the sample counts renders use, hashed u for
    a render that must converge to the last digit."""
    cy = scene.cycles
    seed = cy.seed + (scene.frame_current if getattr(cy, "use_animated_seed", False) else 0)
    width = 1.0 if cy.pixel_filter_type == 'BOX' else float(cy.filter_width)
    use = film_u_wanted(scene)
    return {"FilmFilter": FILM_FILTERS.get(cy.pixel_filter_type, 0) if use else 0, "FilmWidth": width,
            "Seed": int(seed) & 0x7FFFFFFF}


def _set_inputs(node, values):
    for name, value in values.items():
        sock = node.inputs.get(name)
        if sock is not None:
            sockets.assign(sock, value)


def sync(scene, refresh=False, bake_world=False):
    """Set every Learned BSDF group's switch, film settings, lamps and world map for `scene`;
    with refresh, re-export stale textures; with bake_world, render the world's importance
    map when it is missing (never during a render: see world.py)."""
    film = film_settings(scene) if scene.render.engine == 'CYCLES' else None
    limits = None
    worlds = {}
    for tree in binding.trees():
        if tree.library is not None:
            continue
        if refresh:
            _refresh_export(tree)
        if limits is None:
            limits = lamps.limits(scene)        # once per sync: it runs on every scene change
        backend = backends.resolve(scene, tree, limits).backend
        _set_switches(tree, backend)
        if film is None:
            continue
        folder = Path(binding.read(tree).get("tables", "")).parent
        if folder not in worlds:
            worlds[folder] = _world_inputs(scene, folder, bake_world)
        inputs = world.material_share(worlds[folder], binding.read(tree).get("matte"))
        if binding.has_svm(tree):
            from . import svm
            if not svm.update_world(tree, caustics_gate(scene, inputs)):  # a technique the graph lacks: rebuild it
                info = binding.read(tree)
                _build_tree(tree, info["material"], Path(info["tables"]),
                            Path(info["fit"]) if info.get("fit") else None)
                _set_switches(tree, backend)
            svm.set_film(tree, scene)
            lamps.bind_svm(tree, scene)
        script = tree.nodes.get(osl_script.SCRIPT)         # (after a rebuild: a new node)
        if script is not None:
            _set_inputs(script, film)
            lamps.bind(script, scene)
            _set_inputs(script, inputs)


def _set_switches(tree, backend):
    for name, on in ((SWITCH, backend == "osl"), (SWITCH_SVM, backend == "svm")):
        switch = tree.nodes.get(name)
        if switch is not None:
            sockets.assign(switch.outputs[0], float(on))


# The SVM graph's share of portal directions drawn toward the lamps (svm._Mixture), the rest the
# world's techniques and the tables
LAMP_SHARE = 0.5


def caustics_gate(scene, inputs):
    """The SVM graph's world inputs for `scene`: its control variate off where Caustics are off.
    The control variate's Diffuse closure takes a diffuse bounce, after which Cycles drops the
    glossy (reflective caustics off) or refractive (refractive off) closures of the surfaces the
    ray finds; the portal's continued ray keeps the camera flag: neither is dropped there. So the
    closures' share of the light the node reflects from such surfaces would be lost: measured,
    paper_white over a rough Glossy floor under the studio lamps, SVM - OSL -8.9 % (z -22) with
    Caustics off (after: +0.27 % +- 0.37). Filter Glossy 1.0 (Blender's default) blurs those
    surfaces after the closures' bounce: +2.1 % (z 5) there, stated, not gated (at the default it
    would turn the control variate off under every lamp; that noise cost is not measured)."""
    if not backends.caustics_off(scene) or not inputs.get("ControlVariate"):
        return inputs
    return {**inputs, "ControlVariate": 0.0}


def _world_inputs(scene, folder, bake):
    """The shader's world inputs (world.shader_inputs): the world's map when it exists (made
    when `bake`), else none — then the portal samples the tables alone (still unbiased). The
    SVM graph's control variate is on where the world has a small sun or the scene has lamps
    (Cycles' light sampling of the fit's closures lights them; the portal does not)."""
    try:
        inputs = world.bake_world_map(scene, folder) if bake else world.current_inputs(scene, folder)
    except Exception as e:      # noqa: BLE001  (no world map: noisier, not wrong)
        print(f"FlowBSDF: no world importance map: {e}")
        inputs = world.shader_inputs(None, None, None)
    if not lamps.scene_lamps(scene):
        return inputs
    # every lamp slot once there is a lamp to reach: adding, hiding or removing one then rebinds
    # the slots' drivers without rebuilding the graph (a rebuild per material: ~1-2 s each)
    reached = bool(lamps.svm_lamps(scene))
    return {**inputs, "ControlVariate": 1.0, "Lamps": lamps.SVM_SLOTS if reached else 0,
            "LampShare": LAMP_SHARE if reached else 0.0}


def update_world(scene):
    """Render the scene's world map when it is missing and hand it to every group (the add-on
    calls it after binding, on load and shortly after world edits)."""
    sync(scene, bake_world=True)


def node_state(node, scene=None):
    """The node's Status in `scene` (the current one when None), or None for a node that is not
    a Learned BSDF's."""
    tree = getattr(node, "node_tree", None)
    if tree is None or binding.TREE_KEY not in tree.keys():
        return None
    status = backends.resolve(scene or bpy.context.scene, tree)
    problems = binding.read(tree).get("problems")
    if problems and status.backend != "fit":
        status = status._replace(detail="; ".join(p for p in (status.detail, problems) if p))
    waiting = refits.refitting(tree)
    if waiting:
        status = status._replace(detail="; ".join(p for p in (
            status.detail, f"new closure fit being made ({waiting[0]} of {waiting[1]} done): "
                           "an older add-on's fit renders until then") if p))
    return status


def node_status(node, scene=None):
    """What the node renders and why, as one line (Status.line), e.g. "OSL, exact", "Fit, ~12 %
    off the measured material (tables missing). Bake the Material (tables missing: /x/y.exr)"."""
    status = node_state(node, scene)
    return "not a Learned BSDF node" if status is None else status.line()


# ------------------------------------------------------------------------------ handlers

@persistent
def _on_render_pre(scene, *_):
    refits.finish_refits()
    sync(scene, refresh=True)


@persistent
def _on_scene_change(scene, *_):
    sync(scene)         # the viewport follows back end, pixel filter, seed, lamp and world changes
    _schedule_world(scene)


_world_pending = set()


def _schedule_world(scene):
    """After a world edit, render its new importance map a second later (once the edits
    settle), outside any handler: a handler cannot render."""
    if scene.render.engine != 'CYCLES' or scene.name in _world_pending:
        return
    script = next((t.nodes.get(osl_script.SCRIPT) for t in binding.trees()
                   if t.library is None and t.nodes.get(osl_script.SCRIPT)), None)
    if script is None:
        return
    key = world.world_key(scene)
    current = script.inputs["World"].default_value if "World" in script.inputs else ""
    if key is None or (current and Path(current).name == world.map_path(".", key).name):
        return
    name = scene.name
    _world_pending.add(name)

    def run():
        _world_pending.discard(name)
        target = bpy.data.scenes.get(name)
        if target is not None and not bpy.app.is_job_running("RENDER"):
            update_world(target)
        return None
    bpy.app.timers.register(run, first_interval=1.0)


@persistent
def _on_load_post(*_):
    later = ([t for t in binding.trees() if t.library is None and refits.stale_fit(t)]
             if refits.refit_in_thread() else [])
    refits.refit_later(later, upgrade, sync)
    for tree in list(binding.trees()):
        if tree in later:
            continue
        try:
            upgrade(tree)
        except Exception as e:      # noqa: BLE001  (the fit still renders)
            print(f"FlowBSDF: could not add the OSL back end to {tree.name}: {e}")
    for scene in bpy.data.scenes:
        sync(scene, refresh=True, bake_world=scene.render.engine == 'CYCLES' and any(binding.trees()))


@persistent
def _on_save_pre(*_):
    """The file is saved rendering what works without the add-on, in any Blender: the SVM
    graph (no OSL needed) where no lamp renders, else the fit (a Script node would render black
    where OSL is off; under lamps the fit beats the SVM graph at equal time: backends.resolve).
    load_post and the next scene update choose again."""
    scene = bpy.context.scene
    lit = bool(lamps.scene_lamps(scene)) if scene is not None else True
    for tree in binding.trees():
        if tree.library is None:
            _set_switches(tree, "svm" if binding.has_svm(tree) and not lit else "fit")


@persistent
def _on_save_post(*_):
    for scene in bpy.data.scenes:
        sync(scene)


def _handlers():
    h = bpy.app.handlers
    return ((h.render_pre, _on_render_pre), (h.load_post, _on_load_post),
            (h.depsgraph_update_post, _on_scene_change), (h.frame_change_post, _on_scene_change),
            (h.save_pre, _on_save_pre), (h.save_post, _on_save_post))


def register():
    bpy.types.Scene.flowbsdf_backend = bpy.props.EnumProperty(
        name="FlowBSDF back end",
        description="How Learned BSDF nodes render",
        items=[("auto", "Auto", "OSL where Cycles runs it (CPU, Open Shading Language on), else the SVM "
                                "graph (any device; under lamps from 4096 render samples, below them the fit, "
                                "which has less error there), else the closure fit"),
               ("osl", "OSL", "Sample the baked tables exactly and light-sample lamps and the world "
                              "(Cycles CPU, Open Shading Language)"),
               ("fit", "Closure fit", "Cycles closures fitted at bake time (Eevee, previews): approximate"),
               ("svm", "SVM graph", "Sample the baked tables exactly with shader nodes (every Cycles device; "
                                    "exact under lamps visible to the camera that have a size, but noisy)")],
        default="auto", update=lambda self, _ctx: sync(self))
    setattr(bpy.types.Scene, FILM_PROP, bpy.props.BoolProperty(
        name="Stratify camera samples",
        description="Learned BSDF: take camera rays' random numbers from their place in the pixel "
                    "(3-6x less error at usual sample counts; where light changes across a pixel a small "
                    "error shrinks slower than noise: turn off for a render that must converge exactly)",
        default=True, update=lambda self, _ctx: sync(self)))
    for handlers, fn in _handlers():
        if fn not in handlers:
            handlers.append(fn)


def unregister():
    for handlers, fn in _handlers():
        if fn in handlers:
            handlers.remove(fn)
    if bpy.app.timers.is_registered(refits.refit_poll):        # (a refit's thread only writes its fit file)
        bpy.app.timers.unregister(refits.refit_poll)
    if hasattr(bpy.types.Scene, backends.SCENE_PROP):
        del bpy.types.Scene.flowbsdf_backend
    if hasattr(bpy.types.Scene, FILM_PROP):
        delattr(bpy.types.Scene, FILM_PROP)
