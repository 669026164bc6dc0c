"""Validate: the scene rendered by the reference tracer (bake/tracer) and by Cycles, compared.

Export (here, pure bpy): the scene camera (perspective), every rendered mesh object as
world-space OBJ files (one per material slot), learned materials as manifest materials
(sampled from their baked tables), other materials as a Lambertian of their base colour
(said in the report), the world as a constant colour or its environment image (any other
world, e.g. a Sky Texture, rendered by Cycles to an equirectangular image), and every
point, spot, sun and area lamp with Cycles' radiometry (bake/tracer/lights.py): world-space
position and frame, strength = color * temperature colour * energy * 2^exposure (Normalize
off folded in), radius, soft falloff, spot size and blend, sun angle, area shape, size times
object scale and spread, camera visibility. A lamp the tracer cannot render as Cycles does
(light nodes, light linking, per-lobe factors or visibility, no shadow, a square spot,
spread 0, sheared frames, Normalize off on a point/spot with a radius) is an ExportError,
never dropped; a portal (no emitter) is left out with a note.
Then Cycles renders the same view here (small, OSL back end: it light-samples lamps and the
world as the reference does), and the worker renders the reference (MIS) and writes MSE /
SSIM and a labelled side-by-side image (validate/compare.png: Cycles, the reference and their
difference, captioned, with MSE, SSIM and the means; compare.md beside it says the same).
"""
import json
import math
import os

import bpy

from . import jobs, scan, worker
from .operators import _JobOperator

VALIDATE_DIR = "validate"
WORLD_SIZE, WORLD_SPP = (1024, 512), 64      # a world other than a colour or an image, for the tracer


class ExportError(ValueError):
    """The scene cannot be exported to the tracer's format; the message says why."""


def _vec(v):
    return [round(float(x), 6) for x in v]


def _camera(scene, width, height):
    cam = scene.camera
    if cam is None or cam.type != "CAMERA":
        raise ExportError("the scene has no camera")
    if cam.data.type != "PERSP":
        raise ExportError(f"camera {cam.name!r} is {cam.data.type.lower()}: the reference tracer "
                          "renders perspective cameras only")
    m = cam.matrix_world
    pos = m.translation
    forward = (m.to_3x3() @ _axis(0, 0, -1)).normalized()
    up = (m.to_3x3() @ _axis(0, 1, 0)).normalized()
    return {"position": _vec(pos), "look_at": _vec(pos + forward), "up": _vec(up),
            "fov": round(math.degrees(cam.data.angle), 6), "width": width, "height": height}


def _axis(x, y, z):
    from mathutils import Vector
    return Vector((x, y, z))


def _base_colour(mat):
    """(rgb, note) for a non-learned material: its Principled/Diffuse colour if unlinked."""
    if mat is not None and mat.node_tree is not None:
        for n in mat.node_tree.nodes:
            sock = n.inputs.get("Base Color") or (n.inputs.get("Color") if n.bl_idname == "ShaderNodeBsdfDiffuse"
                                                  else None)
            if sock is not None and not sock.is_linked:
                return [round(float(c), 4) for c in sock.default_value[:3]], "base colour"
    if mat is not None:
        return [round(float(c), 4) for c in mat.diffuse_color[:3]], "viewport colour"
    return [0.8, 0.8, 0.8], "no material"


def _world(scene, folder):
    """The tracer's environment: the world's constant colour or Environment Texture image as
    they are, any other world (a Sky Texture, mixes, ...) rendered by Cycles to an
    equirectangular image (world.render_world) in `folder`; (light table, note or None)."""
    world = scene.world
    if world is None or world.node_tree is None:
        raise ExportError("the scene has no world with nodes (the environment lights the comparison)")
    bg = next((n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground"), None)
    if bg is not None and not bg.inputs["Strength"].is_linked:
        strength = float(bg.inputs["Strength"].default_value)
        col = bg.inputs["Color"]
        if not col.is_linked:
            return {"type": "environment", "constant": _vec(c * strength for c in col.default_value[:3])}, None
        src = col.links[0].from_node
        if src.bl_idname == "ShaderNodeTexEnvironment" and src.image is not None:
            path = bpy.path.abspath(src.image.filepath, library=src.image.library)
            if os.path.isfile(path) and not src.inputs["Vector"].is_linked:
                return {"type": "environment", "file": path, "strength": strength}, None
    from ..render import world as world_map
    path = os.path.join(folder, "world.exr")
    world_map.render_world(scene, WORLD_SIZE[0], WORLD_SIZE[1], WORLD_SPP, path=path)
    return ({"type": "environment", "file": path, "strength": 1.0},
            f"world rendered to a {WORLD_SIZE[0]}x{WORLD_SIZE[1]} equirectangular image for the reference")


def _lamp(obj):
    """The tracer's [[light]] table for a lamp object (Cycles' conventions; checked against
    Cycles in tests/test_tracer_lamps.py), None for a portal; ExportError if it has no
    faithful equivalent."""
    light, name = obj.data, f"lamp {obj.name!r}"
    if light.type == "AREA" and light.cycles.is_portal:
        return None

    def refuse(why):
        raise ExportError(f"{name}: {why}: the reference tracer cannot render it as Cycles does")
    if getattr(light, "use_nodes", False) and light.node_tree is not None and not _plain_emission(light.node_tree):
        refuse("its light shader uses nodes (IES, textures, ...)")
    link = getattr(obj, "light_linking", None)
    if link is not None and (link.receiver_collection is not None or link.blocker_collection is not None):
        refuse("it uses light or shadow linking")
    factors = [f for f in ("diffuse_factor", "specular_factor", "transmission_factor", "volume_factor")
               if getattr(light, f, 1.0) != 1.0]
    hidden = [v for v in ("visible_diffuse", "visible_glossy", "visible_transmission", "visible_volume_scatter")
              if not getattr(obj, v, True)]
    if factors or hidden:
        refuse(f"{', '.join(factors + hidden)} (the tracer's lamps light every kind of bounce alike)")
    if not light.use_shadow:
        refuse("it casts no shadow")
    m = obj.matrix_world
    frame = m.to_3x3()
    # exposure, temperature and Normalize came in Blender 4.3; before, lamps behaved as their defaults
    normalize = getattr(light, "normalize", True)
    strength = [c * light.energy * 2.0 ** getattr(light, "exposure", 0.0) for c in light.color]
    if getattr(light, "use_temperature", False):
        strength = [s * c for s, c in zip(strength, light.temperature_color)]
    entry = {"type": light.type.lower(), "camera": bool(obj.visible_camera)}
    if light.type in ("POINT", "SPOT"):
        radius = float(light.shadow_soft_size)           # not scaled by the object (Cycles)
        if not normalize:
            if radius > 0:
                refuse("Normalize is off on a lamp with a radius")
            strength = [4.0 * s for s in strength]       # intensity S / pi instead of S / 4 pi
        entry.update(position=_vec(m.translation), strength=_vec(strength), radius=round(radius, 6),
                     soft_falloff=bool(light.use_soft_falloff))
        if light.type == "SPOT":
            if light.use_square:
                refuse("it is a square spot")
            entry.update(frame=[_vec(row) for row in frame], size=round(math.degrees(light.spot_size), 6),
                         blend=round(float(light.spot_blend), 6))
        return entry
    if light.type == "SUN":
        angle = float(light.angle)
        if not normalize and angle > 0:            # radiance S instead of S / (pi sin^2(angle/2))
            strength = [s * math.pi * math.sin(angle / 2) ** 2 for s in strength]
        entry.update(direction=_vec((frame @ _axis(0, 0, -1)).normalized()), strength=_vec(strength),
                     angle=round(math.degrees(angle), 6))
        return entry
    if light.type != "AREA":
        refuse(f"it is a {light.type.lower()} lamp")
    if light.spread <= 0:
        refuse("its spread is 0 (a parallel beam)")
    sx = light.size
    sy = light.size_y if light.shape in ("RECTANGLE", "ELLIPSE") else light.size
    u, v, w = (frame.col[k].copy() for k in range(3))
    if u.length == 0 or v.length == 0 or w.length == 0 or abs(u.normalized().dot(v.normalized())) > 1e-5 \
            or abs(abs(u.cross(v).normalized().dot(w.normalized())) - 1) > 1e-5:
        refuse("its transform is sheared or degenerate")
    if u.cross(v).dot(w) < 0:                            # mirrored: keep -(u x v) = the lamp's -Z
        u.negate()
    ellipse = light.shape in ("DISK", "ELLIPSE")
    if not normalize:                                    # radiance S / pi instead of S / (pi A)
        area = u.length * sx * v.length * sy * (math.pi / 4 if ellipse else 1.0)
        strength = [s * area for s in strength]
    entry.update(position=_vec(m.translation), axis_u=_vec(u * sx), axis_v=_vec(v * sy),
                 shape="ellipse" if ellipse else "rectangle", strength=_vec(strength),
                 # Blender's default spread is float32(pi): 180.000005 degrees, which the tracer refuses
                 spread=round(min(math.degrees(light.spread), 180.0), 6))
    return entry


def _plain_emission(tree):
    """True for a light node tree that is the default: an Emission (white, strength 1) into
    the output, nothing else."""
    kinds = sorted(n.bl_idname for n in tree.nodes)
    if kinds != ["ShaderNodeEmission", "ShaderNodeOutputLight"]:
        return False
    em = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeEmission")
    col, strength = em.inputs["Color"], em.inputs["Strength"]
    return not col.is_linked and not strength.is_linked and tuple(col.default_value[:3]) == (1.0, 1.0, 1.0) \
        and strength.default_value == 1.0


def _write_obj(path, verts, normals, tris):
    with open(path, "w", encoding="utf-8") as f:
        for v in verts:
            f.write(f"v {v[0]:.7g} {v[1]:.7g} {v[2]:.7g}\n")
        for n in normals:
            f.write(f"vn {n[0]:.7g} {n[1]:.7g} {n[2]:.7g}\n")
        for a, b, c in tris:
            f.write(f"f {a + 1}//{a + 1} {b + 1}//{b + 1} {c + 1}//{c + 1}\n")


def _mesh_parts(obj_eval):
    """{material index: (verts, normals, tris)} in world space, one vertex per triangle corner
    (so split normals survive)."""
    mesh = obj_eval.to_mesh()
    try:
        if hasattr(mesh, "calc_normals_split"):        # Blender < 4.1
            mesh.calc_normals_split()
        corner_normals = (mesh.corner_normals if hasattr(mesh, "corner_normals") else None)
        mesh.calc_loop_triangles()
        mw = obj_eval.matrix_world
        nw = mw.to_3x3().inverted_safe().transposed()
        parts = {}
        for tri in mesh.loop_triangles:
            verts, normals, tris = parts.setdefault(tri.material_index, ([], [], []))
            base = len(verts)
            for k in range(3):
                verts.append(tuple(mw @ mesh.vertices[tri.vertices[k]].co))
                loop = tri.loops[k]
                n = corner_normals[loop].vector if corner_normals is not None else mesh.loops[loop].normal
                normals.append(tuple((nw @ n).normalized()))
            tris.append((base, base + 1, base + 2))
        return parts
    finally:
        obj_eval.to_mesh_clear()


def export_scene(scene, folder, rows, width, height, manifest_path):
    """Write folder/scene.toml (+ OBJ files) for the tracer; returns (path, notes)."""
    os.makedirs(folder, exist_ok=True)
    learned = {r["material"].name_full: r["name"] for r in rows}
    depsgraph = bpy.context.evaluated_depsgraph_get()
    objects = scan.rendered_objects(scene)
    materials, shapes, lamps, notes = {}, [], [], []
    for name, obj in sorted(objects.items()):
        if obj.type == "LIGHT":
            lamp = _lamp(obj)
            if lamp is None:
                notes.append(f"portal {obj.name} left out (it guides world sampling and emits nothing)")
            else:
                lamps.append(lamp)
            continue
        if obj.type not in ("MESH", "CURVE", "SURFACE", "META", "FONT"):
            continue
        parts = _mesh_parts(obj.evaluated_get(depsgraph))
        for index, (verts, normals, tris) in sorted(parts.items()):
            if not tris:
                continue
            slot = obj.material_slots[index] if index < len(obj.material_slots) else None
            mat = slot.material if slot is not None else None
            if mat is not None and mat.name_full in learned:
                key = "learned_" + learned[mat.name_full]
                materials[key] = {"manifest": learned[mat.name_full]}
            else:
                colour, how = _base_colour(mat)
                key = "plain_" + bpy.path.clean_name(mat.name if mat else "none")
                if key not in materials:
                    notes.append(f"{mat.name if mat else 'no material'}: not learned, exported as a "
                                 f"Lambertian of its {how}")
                materials[key] = {"model": "lambert", "albedo": colour, "sampler": "cosine"}
            fname = f"{bpy.path.clean_name(obj.name)}_{index}.obj"
            _write_obj(os.path.join(folder, fname), verts, normals, tris)
            shapes.append({"type": "mesh", "file": fname, "material": key})
    if not shapes:
        raise ExportError("no rendered mesh objects to compare")
    lines = ["# Exported by the FlowBSDF add-on for validation (reference tracer scene format).", "",
             "[camera]"]
    lines += [f"{k} = {scan._toml_value(v)}" for k, v in _camera(scene, width, height).items()]
    for key, spec in materials.items():
        lines += ["", f"[materials.{key}]"] + [f"{k} = {scan._toml_value(v)}" for k, v in spec.items()]
    for shape in shapes:
        lines += ["", "[[shape]]"] + [f"{k} = {scan._toml_value(v)}" for k, v in shape.items()]
    env, note = _world(scene, folder)
    if note:
        notes.append(note)
    for light in [env] + lamps:
        lines += ["", "[[light]]"] + [f"{k} = {scan._toml_value(v)}" for k, v in light.items()]
    lines += ["", "[render]", "max_depth = 12", ""]
    path = os.path.join(folder, "scene.toml")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines))
    return path, notes


def _not_osl(scene, rows):
    """The learned materials whose node would not render the OSL back end now: "name: status"."""
    from ..render import binding, node
    out = []
    for row in rows:
        tree = row["material"].node_tree
        group = next((n for n in tree.nodes if n.bl_idname == "ShaderNodeGroup" and n.node_tree is not None
                      and binding.TREE_KEY in n.node_tree.keys()), None) if tree is not None else None
        status = node.node_status(group, scene) if group is not None else "not bound (bake first)"
        if not status.startswith("OSL"):
            out.append(f"{row['material'].name}: {status}")
    return out


def render_cycles(scene, path, width, height, spp, rows=()):
    """Render the scene with Cycles (CPU, OSL back end: lamps and world light-sampled by the
    shader) into a 32-bit EXR; every setting touched is restored afterwards. ExportError when a
    learned material of `rows` would not render the OSL back end (the comparison would not be
    like with like)."""
    from ..render import node
    saved = []

    def setv(owner, attr, value):
        if hasattr(owner, attr):
            saved.append((owner, attr, getattr(owner, attr)))
            setattr(owner, attr, value)

    r, c, img = scene.render, scene.cycles, scene.render.image_settings
    for owner, attr, value in ((r, "engine", "CYCLES"), (c, "device", "CPU"), (c, "shading_system", True),
                               (c, "samples", spp), (c, "use_adaptive_sampling", False),
                               (c, "use_denoising", False), (c, "seed", 0), (c, "pixel_filter_type", "BOX"),
                               (c, "filter_width", 1.0), (r, "resolution_x", width), (r, "resolution_y", height),
                               (r, "resolution_percentage", 100), (r, "filepath", path),
                               (r, "film_transparent", False),
                               (img, "file_format", "OPEN_EXR"), (img, "color_depth", "32")):
        setv(owner, attr, value)
    try:
        node.sync(scene, refresh=True)
        wrong = _not_osl(scene, rows)
        if wrong:
            raise ExportError("validate compares Cycles' OSL back end with the reference, but here "
                              + "; ".join(wrong))
        bpy.ops.render.render(write_still=True, scene=scene.name)
    finally:
        for owner, attr, value in reversed(saved):
            setattr(owner, attr, value)
        node.sync(scene)
    if not os.path.isfile(path):
        raise ExportError(f"Cycles did not write {path}")


def validate_args(folder, manifest, out, spp):
    return ["validate", os.path.join(folder, "scene.toml"), "--manifest", manifest, "--out", out,
            "--cycles", os.path.join(folder, "cycles.exr"), "--spp", str(spp)]


def prepare(scene, context=None, spp=None, size=None, where="ui"):
    """Export + Cycles render; returns (job, folder, notes). The reference runs in the job."""
    from . import prefs
    spp = spp or scene.flowbsdf.validate_spp
    size = size or scene.flowbsdf.validate_size
    rows, manifest, out = jobs.prepare(scene)
    missing = sorted({r["name"] for r in rows if not os.path.isfile(os.path.join(out, "tables", r["name"] + ".exr"))})
    if missing:
        raise ExportError(f"bake first: no tables for {', '.join(missing)} in {os.path.join(out, 'tables')}")
    aspect = scene.render.resolution_y / max(scene.render.resolution_x, 1)
    width, height = size, max(1, round(size * aspect))
    folder = os.path.join(out, VALIDATE_DIR)
    _, notes = export_scene(scene, folder, rows, width, height, manifest)
    python = worker.python_for(prefs.get(context), where=where)
    render_cycles(scene, os.path.join(folder, "cycles.exr"), width, height, spp, rows)
    job = worker.Job(python, validate_args(folder, manifest, out, spp), worker.extra_paths(prefs.get(context)),
                     label="Validate")
    return job, folder, notes


def parse_result(lines):
    for line in lines:
        if line.startswith("[validate] "):
            return json.loads(line[len("[validate] "):])
    raise worker.JobError("the validation job printed no result")


def show_image(path, name="FlowBSDF validate"):
    image = bpy.data.images.get(name)
    if image is not None:
        bpy.data.images.remove(image)
    image = bpy.data.images.load(path)
    image.name = name
    for window in getattr(bpy.context.window_manager, "windows", []):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
    return image


class FLOWBSDF_OT_validate(_JobOperator, bpy.types.Operator):
    """Render the scene with the reference tracer and with Cycles (OSL back end) and compare
    (MSE, SSIM, side-by-side image)"""
    bl_idname = "flowbsdf.validate"
    bl_label = "Validate Against Reference"

    def start(self, context):
        job, self._folder, self._notes = prepare(context.scene, context)
        return job

    def finish(self, context, job):
        result = parse_result(job.lines)
        show_image(result["image"])
        notes = f" ({'; '.join(self._notes)})" if self._notes else ""
        return (f"FlowBSDF validate: MSE {result['mse']:.4g}, SSIM {result['ssim']:.4f} "
                f"(reference noise {result['reference_noise']:.3g}); image {result['image']}{notes}")


classes = (FLOWBSDF_OT_validate,)
