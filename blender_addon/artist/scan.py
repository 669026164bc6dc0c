"""What a scene needs: the learned materials that rendered objects use, written as a manifest.

A material is learned when its FlowBSDF settings are enabled (`material.flowbsdf`). An object
counts when it renders: not hidden for render, in a collection that renders in the view
layer (not excluded, no hidden-for-render collection above it), or instanced by one that
does (collection instances, particles, geometry nodes, via the evaluated depsgraph).
"""
import json
import math
import os

import bpy

from . import props


def _walk_layer(layer_coll, out):
    if layer_coll.exclude or layer_coll.collection.hide_render:
        return
    for obj in layer_coll.collection.objects:
        if not obj.hide_render:
            out[obj.name_full] = obj
    for child in layer_coll.children:
        _walk_layer(child, out)


def _instanced(obj, out, depth=0):
    coll = obj.instance_collection if obj.instance_type == "COLLECTION" else None
    if coll is None or depth > 16 or coll.hide_render:
        return
    for child in coll.all_objects:
        if not child.hide_render and child.name_full not in out:
            out[child.name_full] = child
            _instanced(child, out, depth + 1)


def rendered_objects(scene, view_layer=None):
    """{name_full: object} of the objects that render in this view layer."""
    view_layer = view_layer or scene.view_layers[0]
    out = {}
    _walk_layer(view_layer.layer_collection, out)
    for obj in list(out.values()):
        _instanced(obj, out)
    return out


def used_materials(scene, view_layer=None, depsgraph=None):
    """{material name_full: (material, sorted object names)} over the rendered objects."""
    view_layer = view_layer or scene.view_layers[0]
    objects = rendered_objects(scene, view_layer)
    users = {}

    def add(mat, obj_name):
        if mat is not None:
            mat = mat.original
            users.setdefault(mat.name_full, (mat, set()))[1].add(obj_name)

    for name, obj in objects.items():
        for slot in obj.material_slots:
            add(slot.material, name)
    if depsgraph is None and bpy.context.scene == scene and bpy.context.view_layer == view_layer:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    if depsgraph is not None:        # instances and materials set by modifiers / geometry nodes
        for inst in depsgraph.object_instances:
            owner = (inst.parent if inst.is_instance and inst.parent else inst.object).original
            if owner.name_full not in objects:
                continue
            for slot in inst.object.material_slots:
                add(slot.material, inst.object.original.name_full)
    return {k: (m, sorted(names)) for k, (m, names) in users.items()}


class ScanError(ValueError):
    """The scene's learned materials cannot make a manifest; the message says which and why."""


def scan(scene, view_layer=None):
    """The learned materials in use: a list of {material, name, entry, users}, by manifest name.
    Blender materials sharing a name must share the source (they share the tables)."""
    rows, by_name, problems = [], {}, []
    for mat, users in sorted(used_materials(scene, view_layer).values(), key=lambda mu: mu[0].name_full):
        if not mat.flowbsdf.enabled:
            continue
        try:
            entry = props.manifest_entry(mat)
        except props.SourceError as e:
            problems.append(str(e))
            continue
        row = {"material": mat, "name": entry["name"], "entry": entry, "users": users}
        other = by_name.get(entry["name"])
        if other is not None and other["entry"] != entry:
            problems.append(f"materials {other['material'].name!r} and {mat.name!r} are both named "
                            f"{entry['name']!r} in FlowBSDF but differ: rename one")
            continue
        by_name.setdefault(entry["name"], row)
        rows.append(row)
    if problems:
        raise ScanError("; ".join(problems))
    return rows


def out_dir(scene, fallback=None):
    """The scene's FlowBSDF folder, absolute. '//' needs a saved file, else the fallback folder."""
    raw = scene.flowbsdf.out_dir.strip() or "//flowbsdf"
    if raw.startswith("//") and not bpy.data.filepath:
        if fallback is None:
            from . import prefs
            fallback = prefs.user_dir("unsaved", bpy.path.clean_name(scene.name))
        return os.path.normpath(fallback)
    return os.path.normpath(bpy.path.abspath(raw))


# -- the manifest ----------------------------------------------------------------------------

def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ScanError(f"cannot write {v} in a manifest")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)          # a TOML basic string (same escapes)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise ScanError(f"cannot write a {type(v).__name__} in a manifest")


def _toml_key(k):
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def _portable(source, base):
    """A file source inside the project (the folder holding the manifest's folder, e.g. the
    .blend's beside //flowbsdf) relative to the manifest's folder `base`, so the project moves as
    one folder (the bake reads a relative source against the manifest's folder); one elsewhere as
    given, absolute."""
    if not isinstance(source, str) or not base or not os.path.isabs(source):
        return source
    try:
        rel = os.path.relpath(source, base).replace(os.sep, "/")
    except ValueError:              # another drive (Windows)
        return source
    return source if rel.startswith("../../") else rel


def manifest_text(rows, notes=None, source="", base=None):
    """The manifest's text; file sources relative to `base` (its folder) where they can be."""
    notes = notes or {}
    lines = ["# FlowBSDF manifest written by the Blender add-on's scene scan" + (f" of {source}" if source else ""),
             "# (the learned materials that rendered objects use); regenerated on each scan.", ""]
    seen = set()
    for row in rows:
        entry = row["entry"]
        if entry["name"] in seen:
            continue
        seen.add(entry["name"])
        users = [r for r in rows if r["name"] == entry["name"]]
        mats = ", ".join(sorted({r["material"].name for r in users}))
        objs = sorted({o for r in users for o in r["users"]})
        lines.append(f"# Blender material(s): {mats}; used by {len(objs)} object(s): "
                     + ", ".join(objs[:8]) + (" ..." if len(objs) > 8 else ""))
        if entry["name"] in notes:
            lines.append(f"# {notes[entry['name']]}")
        lines.append("[[material]]")
        for key in ("name", "source", "domain", "train", "bake"):
            if entry.get(key) not in (None, {}):
                value = _portable(entry[key], base) if key == "source" else entry[key]
                lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def write_manifest(rows, path, notes=None, source=""):
    """Write the manifest atomically; returns its path."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(manifest_text(rows, notes, source, base=os.path.dirname(os.path.abspath(path))))
    os.replace(tmp, path)
    return path


# -- what is baked (from the worker's status lines) ------------------------------------------

def parse_status(lines):
    """{name: status dict} from a worker's `[status] {json}` lines."""
    out = {}
    for line in lines:
        if line.startswith("[status] "):
            info = json.loads(line[len("[status] "):])
            out[info["name"]] = info
    return out


def needs_text(info):
    """The incident bins a material needs, in words."""
    if info.get("isotropic") is None:
        return "unknown (the material did not open)"
    if not info["isotropic"]:
        return "theta_i x phi_i (anisotropic): no tables yet, the flow serves it"
    bins = info.get("theta_bins_deg")
    if bins:
        return f"theta_i only: {len(bins)} bins, {bins[0]:g}-{bins[-1]:g} deg"
    return "theta_i only: bins chosen at bake time"


def source_text(info):
    """Where a material's tables come from and whether it has a model, in words."""
    model = "model trained" if info.get("model") else "no trained model"
    source = info.get("tables_source")
    if source == "flow":
        return "tables from its trained model"
    return f"tables from the material; {model}" if source else model


def state_of(info):
    if info.get("error"):
        return "error"
    if info.get("isotropic") is False:
        return "unsupported"
    return info["tables"]


def fill_scan_items(scene, rows, statuses):
    items = scene.flowbsdf.scan_items
    items.clear()
    for row in rows:
        info = statuses.get(row["name"], {})
        item = items.add()
        item.material = row["material"].name
        item.learned = row["name"]
        item.users = len(row["users"])
        item.state = state_of(info) if info else "unknown"
        item.needs = needs_text(info) if info else ""
        item.detail = info.get("error") or source_text(info)


def notes_of(rows, statuses):
    return {row["name"]: f"state: {state_of(statuses[row['name']])}; needs "
            f"{needs_text(statuses[row['name']])}; {source_text(statuses[row['name']])}"
            for row in rows if row["name"] in statuses}
