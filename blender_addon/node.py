"""The "Learned BSDF" node: a shader node group bound to one baked material.

A plain group node (ShaderNodeGroup), so a .blend renders with or without the add-on
installed, and materials append and link like any other. Its node tree, "Learned BSDF:
<material>", holds three back ends:

- OSL (Cycles on the CPU with Open Shading Language on): a Script node running
  blender_addon/osl/learned_bsdf.osl (stored in the .blend as a text block and compiled
  bytecode). It samples the baked tables exactly, lights the material with the scene's
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
  .blend ("FlowBSDF fit: <hash>", shared by materials with the same fit), so it renders
  everywhere (Eevee, previews) even when the table files are gone; approximate.

EEVEE renders none of the three as Cycles does (no OSL, no Ray Portal BSDF, no anisotropy): the
group's second output, "EEVEE", holds the fit's EEVEE fit (closure_fit: isotropic lobes of its
own, fit to the tables; a fit before FIT_VERSION 8: the fit's closures), and the material gets
two Material Outputs, target Cycles fed by "BSDF", target EEVEE by "EEVEE" (`_wire_outputs`):
each engine takes its own, and EEVEE compiles only the EEVEE fit's closures.

Two Mix Shaders pick one: "FlowBSDF SVM backend" (fit or SVM), then "FlowBSDF backend"
(that or OSL); with constant factors Cycles compiles only the chosen branch. The factors
follow the scene's back end ("auto", "osl", "svm", "fit"; `set_backend`, `_resolve`): auto
renders OSL where Cycles runs it, else the SVM graph, else (lamps would go unlit, or not
Cycles) the fit; the node's status says which and why (`node_status`). They are set before
every render (render_pre), on every scene and frame change (depsgraph_update_post,
frame_change_post: the viewport follows) and after loading a file (load_post), with the
lamps, film settings and world inputs; before saving (save_pre) they are set to what
renders without the add-on anywhere (SVM, or the fit where lamps render).
Binding data sits in the tree's custom property "flowbsdf".

Blenders without numpy or OSL (Debian's 3.4 for the batch path): nothing here imports
numpy at module load. The fit is read from its JSON file (<name>.fit.json, written by the
bake) with the json module, and the OSL texture is found by its content-hashed name; only
missing or stale fits/textures need `bake` (numpy), imported on first use. Where Cycles
cannot run the OSL shader (`osl_compiler_available`: Debian's 3.4, Blender < 4.4) there is no Script node
(an uncompiled one has no sockets and points at an add-on path that differs per machine),
and without the SVM graph's nodes (before 5.0) no SVM graph: the group holds the fit alone.
Opening such a file with the add-on where more back ends build rebuilds the group
(load_post, `upgrade`), as it does a group whose shader an older add-on compiled. The
group's socket is made with `tree.interface` (4.0+) or the legacy `tree.outputs` (3.x).

API (used by the add-on's UI and operators): register, unregister, assign_learned_bsdf,
set_backend, backend_of, node_status, sync, update_world, film_settings.
"""
import contextlib
import json
import os
import sys
from pathlib import Path
from typing import NamedTuple

import bpy
from bpy.app.handlers import persistent

from . import deps, lamps, sockets, world

BACKENDS = ("osl", "svm", "fit", "auto")
ENUM_ORDER = ("auto", "osl", "fit", "svm")     # the scene enum's items, as stored in files (append only)
SCENE_PROP = "flowbsdf_backend"
TREE_PREFIX = "Learned BSDF: "
TREE_KEY = "flowbsdf"
NODE_LABEL = "Learned BSDF"
TEXT_NAME = "flowbsdf_learned_bsdf.osl"
SWITCH = "FlowBSDF backend"           # 1: OSL, else the SVM / fit switch below
SWITCH_SVM = "FlowBSDF SVM backend"     # 1: the SVM graph, 0: the fit
SCRIPT = "FlowBSDF OSL"
OSL_SOURCE = Path(__file__).resolve().parent / "osl" / "learned_bsdf.osl"
# The grey diffuse used when a material has neither a fit nor tables.
NEUTRAL = (0.5, 0.5, 0.5)
# The fit file format (bake/export/closure_fit.py: load_fit, FIT_VERSION), read here without numpy.
FIT_FORMAT = "flowbsdf-closure-fit"
# The versions of bake/formats.py (deps.formats: read without numpy). OSL_LAYOUT: the OSL texture's
# layout, part of its file name; CARRY_LAYOUT the carried blend's texture's; READABLE_FIT_VERSIONS the
# fits the node renders: a version 6 fit (3 lobes, no tilts) or 7 (no EEVEE fit: EEVEE renders the
# fit's closures, anisotropy dropped) until `upgrade` refits it
_FORMATS = deps.formats()
OSL_LAYOUT, CARRY_LAYOUT = _FORMATS.OSL_LAYOUT, _FORMATS.CARRY_LAYOUT
FIT_VERSION, READABLE_FIT_VERSIONS = _FORMATS.FIT_VERSION, _FORMATS.READABLE_FIT_VERSIONS
EEVEE_OUTPUT = "EEVEE"      # the group's output that the material's EEVEE-target Material Output takes
FIT_LOBES = 4           # at most (bake/export/closure_fit.LOBES); a vector socket holds lobes 1-3's r, a or tilt


def _bake_mod(name):
    """A module of the add-on's `bake` (numpy) by its name below the package ("export.world_map"),
    or None where this Blender's Python cannot import it (no numpy: Debian's Blender 3.4)."""
    import importlib
    from . import deps
    try:
        pkg = deps.bake.__name__
        return importlib.import_module(f"{pkg}.{name}")
    except ImportError:
        return None


def _file_hash(path):
    """sha256 of the file's bytes (as bake.plumbing.files.file_hash)."""
    import hashlib
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_fit(path):
    """The closure fit in a <name>.fit.json file (json only, no numpy); raises ValueError."""
    path = Path(path)
    try:
        fit = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"closure fit not found: {path}") from None
    except (OSError, ValueError) as e:
        raise ValueError(f"closure fit unreadable ({e}): {path}") from None
    if not isinstance(fit, dict) or fit.get("format") != FIT_FORMAT or fit.get("version") not in READABLE_FIT_VERSIONS:
        raise ValueError(f"not a current FlowBSDF closure fit, re-bake: {path}")
    for key in ("x", "diffuse", "specular", "roughness", "anisotropy", "rel_error", "cv"):
        if key not in fit:
            raise ValueError(f"closure fit without {key!r}: {path}")
    for key in ("x", "diffuse", "specular", "roughness", "anisotropy"):     # the EEVEE fit's (FIT_VERSION 8)
        if "eevee" in fit and key not in fit["eevee"]:
            raise ValueError(f"closure fit's EEVEE fit without {key!r}: {path}")
    if fit.get("match") and path.with_name(fit["match"]).is_file():
        fit["match_path"] = str(path.with_name(fit["match"]))      # the SVM control variate's match image
    return fit


def _fit_file(tables_path):
    """The fit file beside a table file when it is current (its tables_hash matches, of
    FIT_VERSION), else the one `bake` (re)makes, else (no numpy) one of an older readable
    version made from these tables, else a ValueError saying why."""
    path = tables_path.with_name(tables_path.stem + ".fit.json")
    digest = _file_hash(tables_path)
    older = False
    try:
        fit = load_fit(path)
        if fit.get("tables_hash") == digest and fit.get("version") == FIT_VERSION:
            return path
        older = fit.get("tables_hash") == digest
        why = f"closure fit of version {fit.get('version')}" if older else \
            f"closure fit stale (made from other tables): {path}"
    except ValueError as e:
        why = str(e)
    closure_fit = _bake_mod("export.closure_fit")
    if closure_fit is None:
        if older:
            return path         # rendered as it is (the version it says): refitting needs numpy
        raise ValueError(f"{why}; re-bake (refitting needs numpy, absent in this Blender)")
    return closure_fit.ensure_fit(tables_path)


def _osl_texture(tables_path):
    """The OSL texture of a table file: made or refreshed by `bake` where it imports, else the
    one the bake wrote (its name carries the tables' hash: bake/export/osl_export.export_path)."""
    osl_export = _bake_mod("export.osl_export")
    error = None
    if osl_export is not None:
        try:
            return str(osl_export.ensure_osl_export(tables_path))
        except Exception as e:      # noqa: BLE001  (e.g. no OpenEXR here: try the baked file)
            error = e
    path = _texture_path(tables_path, _file_hash(tables_path))
    if path.is_file():
        return str(path)
    raise ValueError(str(error) if error else f"OSL texture not exported (re-bake): {path}")


def _texture_path(tables_path, digest):
    """The OSL texture's name beside the tables (bake/export/osl_export.export_path, without numpy)."""
    return tables_path.with_name(f"{tables_path.stem}.osl{OSL_LAYOUT}-{digest[:12]}.exr")


def _carry_texture(tables_path):
    """The carried blend's texture the bake wrote beside a table file (its name carries the tables'
    hash: bake/export/carry_export.export_path), or "" (tables that do not carry, or not yet baked)."""
    tables_path = Path(tables_path)
    if not tables_path.is_file():
        return ""
    path = tables_path.with_name(f"{tables_path.stem}.carry{CARRY_LAYOUT}-{_file_hash(tables_path)[:12]}.exr")
    return str(path) if path.is_file() else ""


def svm_available():
    """Whether this Blender runs the SVM back end: the Ray Portal BSDF (4.2+) with Cycles' MIS of
    a lamp hit past a portal as 5.0 has it (4.5+: path_state_next), and a `bake` that imports
    (numpy). 4.2 LTS (past its support) renders the fit."""
    return (hasattr(bpy.types, "ShaderNodeBsdfRayPortal") and bpy.app.version >= (4, 5, 0)
            and _bake_mod("export.svm_export") is not None)


def _svm_texture(tables_path):
    """The SVM texture of a table file, made or refreshed by `bake` (bake/export/svm_export.py)."""
    return str(_bake_mod("export.svm_export").ensure_svm_export(tables_path))


def derived_current(tables_path):
    """Whether a table file's fit and OSL texture exist and were made from its contents."""
    tables_path = Path(tables_path)
    digest = _file_hash(tables_path)
    try:
        fit_ok = load_fit(tables_path.with_name(tables_path.stem + ".fit.json")).get("tables_hash") == digest
    except ValueError:
        return False
    return fit_ok and _texture_path(tables_path, digest).is_file()


def osl_compiler_available():
    """Whether this Blender's Cycles compiles and runs the OSL shader: Debian's 3.4 has no OSL;
    Cycles before 4.4 crashes optimizing its gettextureinfo() of a constant file name
    (OSLRenderServices::get_texture_info; seen with the bpy 4.2.23 wheel, 4.4 and 4.5 run it)."""
    if bpy.app.version < (4, 4, 0):
        return False
    try:
        import _cycles
    except ImportError:
        return False
    return bool(getattr(_cycles, "with_osl", False)) and hasattr(_cycles, "osl_compile")


# ------------------------------------------------------------------------------ OSL script

def ensure_oslquery():
    """Make Cycles' `oslquery` importable (bpy as a Python module does not put Blender's own
    site-packages on sys.path; without it a Script node silently gets no sockets)."""
    try:
        import oslquery  # noqa: F401
        return
    except ImportError:
        pass
    root = Path(bpy.utils.resource_path("LOCAL"))
    for site in sorted(root.glob("python/lib/python3*/site-packages")):
        if str(site) not in sys.path:
            sys.path.append(str(site))
    try:
        import oslquery  # noqa: F401
    except ImportError:         # Cycles before 4.5 queries the shader in C++ (_cycles.osl_update_node)
        pass


def shader_source(probe=False):
    """The shader as one source text: Script nodes compile a text block on their own, so the
    shader's own headers (osl/*.h) are inlined; Cycles' stdcycles.h stays an include."""
    import re

    def inline(match):
        header = OSL_SOURCE.parent / match.group(1)
        return header.read_text() if header.is_file() else match.group(0)
    src = re.sub(r'^#include "([^"]+)"$', inline, OSL_SOURCE.read_text(), flags=re.M)
    return ("#define FLOWBSDF_PROBE\n" + src) if probe else src


def _report(kind, message):
    if "ERROR" in kind:
        raise RuntimeError(f"FlowBSDF OSL shader: {message}")


def script_text(probe=False):
    """The text block holding the shader source (refreshed when the add-on's source changed)."""
    name = TEXT_NAME if not probe else "flowbsdf_learned_bsdf_probe.osl"
    src = shader_source(probe)
    text = bpy.data.texts.get(name)
    if text is None:
        text = bpy.data.texts.new(name)
    if text.as_string().rstrip("\n") != src.rstrip("\n"):
        text.from_string(src)
    return text


@contextlib.contextmanager
def _own_tempdir():
    """Cycles leaves the compiled .oso of an internal Script node in the temporary folder
    (cycles/osl.py; it compiles on every script assignment too): run compiles with a
    temporary folder of our own, removed afterwards."""
    import shutil
    import tempfile
    folder, saved = tempfile.mkdtemp(prefix="flowbsdf_osl_"), tempfile.tempdir
    tempfile.tempdir = folder
    try:
        yield
    finally:
        tempfile.tempdir = saved
        shutil.rmtree(folder, ignore_errors=True)


def make_script_node(tree, probe=False):
    """A Script node running the shader, compiled (bytecode stored in the node)."""
    if not osl_compiler_available():
        raise RuntimeError("FlowBSDF OSL shader: this Blender's Cycles cannot compile OSL")
    import cycles.osl
    ensure_oslquery()
    with _own_tempdir():
        node = tree.nodes.new("ShaderNodeScript")
        node.mode = 'INTERNAL'
        node.script = script_text(probe)
        if not cycles.osl.update_script_node(node, _report) or "BSDF" not in node.outputs:
            raise RuntimeError("FlowBSDF OSL shader: compilation gave no sockets")
    return node


def _source_hash():
    """The shipped shader's content hash: a group records the one it was built with."""
    import hashlib
    return hashlib.sha256(shader_source().rstrip("\n").encode()).hexdigest()


# ------------------------------------------------------------------------------ the group

def _trees():
    for tree in bpy.data.node_groups:
        if tree.bl_idname == "ShaderNodeTree" and TREE_KEY in tree.keys():
            yield tree


PATH_KEYS = ("tables", "fit", "osl_texture", "svm_texture", "carry_texture")
ABS_KEY = "absolute"        # the paths' absolute forms, beside their relative ones (`_store`)


def _info(tree):
    """The group's binding data, its file paths absolute (stored relative to the .blend: `_store`)."""
    info = dict(tree[TREE_KEY].to_dict()) if hasattr(tree[TREE_KEY], "to_dict") else dict(tree[TREE_KEY])
    absolute = info.pop(ABS_KEY, None) or {}
    for key in PATH_KEYS:
        if info.get(key):
            info[key] = _located(info[key], absolute.get(key), tree.library)
    return info


def _located(stored, absolute, library):
    """A stored path, absolute: relative to the .blend that holds the group (its library's for
    linked data), as a moved project folder needs; where no file is there but one is at the
    absolute path recorded beside it, that one (a group appended from another .blend, e.g. an
    asset library: Blender does not rebase custom properties on append). Else the first
    (what a missing file's message names)."""
    path = os.path.normpath(bpy.path.abspath(stored, library=library))
    if absolute and stored.startswith("//") and not os.path.exists(path) and os.path.exists(absolute):
        return os.path.normpath(absolute)
    return path


def _relative(path):
    """`path` relative to the saved .blend (//...), so the project folder can move; as it is
    for an unsaved file (or another drive)."""
    if not path or not bpy.data.filepath:
        return path
    try:
        return bpy.path.relpath(path)
    except ValueError:
        return path


def _store(tree, info):
    """Record the binding: paths relative to the .blend (`_relative`), and absolute under ABS_KEY."""
    paths = {key: os.path.normpath(bpy.path.abspath(info[key])) for key in PATH_KEYS if info.get(key)}
    tree[TREE_KEY] = {**{k: v for k, v in info.items() if k != ABS_KEY},
                      **{key: _relative(path) for key, path in paths.items()}, ABS_KEY: paths}


def _tree_for(name):
    for tree in _trees():
        if _info(tree).get("material") == name and tree.library is None:
            return tree
    return bpy.data.node_groups.new(TREE_PREFIX + name, "ShaderNodeTree")


def _ensure_interface(tree):
    """The group's sockets: the BSDF output, the EEVEE output (the EEVEE fit's closures, which
    the material's EEVEE-target Material Output takes: _wire_outputs) and the Tangent input
    (anisotropic tables' frame: world x when unlinked, projected onto the tangent plane by the
    shader)."""
    if not _has_socket(tree, "BSDF", "OUTPUT"):
        _new_socket(tree, "BSDF", "OUTPUT", "NodeSocketShader")
    if not _has_socket(tree, EEVEE_OUTPUT, "OUTPUT"):
        _new_socket(tree, EEVEE_OUTPUT, "OUTPUT", "NodeSocketShader")
    if not _has_socket(tree, "Tangent", "INPUT"):
        _new_socket(tree, "Tangent", "INPUT", "NodeSocketVector").default_value = TANGENT


def _has_socket(tree, name, in_out):
    if getattr(tree, "interface", None) is None:          # Blender < 4.0: the legacy API
        return name in (tree.inputs if in_out == "INPUT" else tree.outputs)
    return any(getattr(i, "item_type", "") == "SOCKET" and i.name == name and i.in_out == in_out
               for i in tree.interface.items_tree)


def _new_socket(tree, name, in_out, kind):
    """A new input or output socket of a node group (`in_out` "INPUT" or "OUTPUT", `kind` e.g.
    "NodeSocketVector"), in Blender 4+ or the legacy API."""
    if getattr(tree, "interface", None) is None:
        return (tree.inputs if in_out == "INPUT" else tree.outputs).new(kind, name)
    return tree.interface.new_socket(name, in_out=in_out, socket_type=kind)


def _piecewise(tree, x_socket, xs, values, loc):
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


def _fit_params(tree, fit, loc, cv=False):
    """The fit's parameters at the view angle, from its node group (_fit_group): {"kd": colour,
    "ks": [colour per lobe], "roughness": (r_1, r_2, r_3), "anisotropy": (a_1, a_2, a_3),
    "tilt": (t_1, t_2, t_3) or None, "lobe4": (r_4, t_4, t_d) or None, "tilted": per closure
    (Diffuse first) whether its tilt is anywhere not 0, "view_aligned": how many lobes take the
    view's tangent}; `cv`: and "cv" (beta_d, beta_s, s), "matched" (s_m, s_m, s_m), the control
    variate's (svm.py)."""
    node = tree.nodes.new("ShaderNodeGroup")
    node.node_tree = _fit_group(fit)
    node.location = loc
    out = node.outputs
    lobes = fit_lobes(fit)
    tilt, dtilt = fit_tilts(fit)
    params = {"kd": out["Diffuse"], "ks": [out[f"Specular {j + 1}"] for j in range(lobes)],
              "roughness": out["Roughness"], "anisotropy": out["Anisotropy"],
              "tilt": out.get("Tilt"), "lobe4": out.get("Lobe 4"),
              "tilted": [any(dtilt)] + [any(knot[j] for knot in tilt) for j in range(lobes)],
              "view_aligned": min(int(fit.get("view_aligned", 0)), 3)}
    if cv:
        params.update(cv=out["Control variate"], matched=out["Matched share"])
    return params


def _fit_group(fit):
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
        _new_socket(tree, param, "OUTPUT", "NodeSocketVector")
    facing = tree.nodes.new("ShaderNodeLayerWeight")
    facing.inputs["Blend"].default_value = 0.5          # Facing = 1 - |cos theta_i|
    out = tree.nodes.new("NodeGroupOutput")
    out.location = (3400, 0)
    for k, values in enumerate(columns.values()):
        tree.links.new(_piecewise(tree, facing.outputs["Facing"], fit["x"], values, (200, -500 * k)), out.inputs[k])
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


def _closures(tree, params, loc, scale_d=None, scale_s=None, tilts=True):
    """The fit's closures: a Diffuse BSDF (colour kd) plus a GGX Glossy BSDF per lobe (colour
    ks_j, roughness r_j, anisotropy a_j; the first params["view_aligned"] with the view's
    tangent: view_tangent), each tilted closure with its own Normal N + t normalize(T) (t its
    tilt, T the view tangent, N Geometry's Normal; a MULTIPLY_ADD: a zero tilt gives N exactly,
    Cycles normalises it; closures whose tilt is 0 at every knot take the shading normal
    unlinked, as before). `scale_d`, `scale_s`: colours multiplying kd and every ks_j (the SVM
    back end's control variate); `tilts` False: every closure untilted."""
    nodes, links = tree.nodes, tree.links
    x, y = loc[0] + 3000, loc[1]

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
        if j < params["view_aligned"] and "Anisotropy" in glossy.inputs:
            links.new(component("anisotropy", j, (x, y - 500)), glossy.inputs["Anisotropy"])
            links.new(tangent, glossy.inputs["Tangent"])
        elif "Anisotropy" in glossy.inputs:
            glossy.inputs["Anisotropy"].default_value = 0.0
        normal_of(j + 1, glossy)
        add = nodes.new("ShaderNodeAddShader")
        add.location = (x + 600, y - 300 * j - 150)
        links.new(out, add.inputs[0])
        links.new(glossy.outputs[0], add.inputs[1])
        out = add.outputs[0]
    return out


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


def _build_fit(tree, fit, loc=(-1400, -400)):
    """The fit back end's closures (a neutral grey diffuse without a fit); returns their
    shader output socket."""
    if fit is None:
        diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
        diffuse.location = (loc[0] + 3400, loc[1])
        diffuse.inputs["Color"].default_value = (*NEUTRAL, 1.0)
        return diffuse.outputs[0]
    return _closures(tree, _fit_params(tree, fit, loc), loc)


def _svm_backend(tree, svm_texture, fit, tangent, world_inputs, loc=(-1400, -3000)):
    """The SVM back end's shader: the sampler's portal mixture (svm.build_svm_sampler), with a
    fit its control variate: the fit's closures scaled by its `cv` betas (or matched to the
    world's small light: svm.py), which Cycles lights with its lamp and world sampling, taken
    with probability 1 - s; else the portal carrying the rest (bake/export/closure_fit.py)."""
    from . import svm
    has_betas = fit is not None and any(b[0] > 0.0 or b[1] > 0.0 for b in fit["cv"])
    # (a match image only where some view angle is matched: else no lookups)
    match = fit.get("match_path") if fit and any(matched_share(e) > 0.0 for e in fit["rel_error"]) else None
    if not (has_betas or match) or not svm.control_variate_wanted(svm_texture, fit):
        return svm.build_svm_sampler(tree, svm_texture, tangent, location=loc, world=world_inputs)
    params = _fit_params(tree, fit, (loc[0], loc[1] + 1600), cv=True)
    cv = {"fit": params, "betas": params["cv"], "matched_share": params["matched"],
          "has_betas": has_betas, "match_image": match,
          "closures": lambda sd, ss: _closures(tree, params, (loc[0], loc[1] + 1600), sd, ss, tilts=svm.CV_TILTS)}
    return svm.build_svm_sampler(tree, svm_texture, tangent, location=loc, world=world_inputs, cv=cv)


def _build_tree(tree, name, tables_path, fit_path):
    """(Re)build the group's nodes for a material; records the binding in tree["flowbsdf"]."""
    problems = []
    fit = None
    osl_texture = svm_texture = ""
    with_osl, with_svm = osl_compiler_available(), svm_available()
    if tables_path.is_file():
        # The OSL texture is recorded even where OSL cannot compile: a Blender that can rebuilds
        # the group from it (`upgrade`).
        try:
            osl_texture = _osl_texture(tables_path)
        except Exception as e:      # noqa: BLE001  (a broken table file must not break the material)
            problems.append(f"no OSL texture: {e}")
        if with_svm:
            try:
                svm_texture = _svm_texture(tables_path)
            except Exception as e:      # noqa: BLE001
                problems.append(f"no SVM texture: {e}")
    else:
        problems.append(f"tables missing: {tables_path}")
    try:
        if fit_path is None and tables_path.is_file():
            fit_path = _fit_file(tables_path)
        if fit_path is not None:
            fit = load_fit(fit_path)
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
    fit_out = _build_fit(tree, fit)
    # EEVEE's closures: the fit's own EEVEE fit (isotropic lobes: EEVEE renders no anisotropy),
    # else (a fit before FIT_VERSION 8, or none) the fit's closures
    eevee = fit.get("eevee") if fit else None
    links.new(_build_fit(tree, eevee, loc=(-1400, 1400)) if eevee else fit_out, out.inputs[EEVEE_OUTPUT])
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
                image.filepath = _relative(svm_texture)
        shader = _switched(tree, SWITCH_SVM, shader, svm_out, (2200, -300))
    if with_osl:                # else no Script node at all (see the module docstring); `upgrade` adds it
        script = make_script_node(tree)
        script.name = script.label = SCRIPT
        script.location = (2200, 300)
        script.inputs["Tables"].default_value = osl_texture
        script.inputs["Carried"].default_value = info["carry_texture"] = _carry_texture(tables_path)
        links.new(fit_out, script.inputs["Fallback"])
        links.new(group_in.outputs["Tangent"], script.inputs["Tangent"])
        script["flowbsdf_src"] = _source_hash()
        shader = _switched(tree, SWITCH, shader, script.outputs["BSDF"], (2400, 0))
    links.new(shader, out.inputs["BSDF"])
    _store(tree, info)


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


def _has_svm(tree):
    from . import svm
    return any(n.name.startswith(svm.FILM) for n in tree.nodes)


def upgrade(tree):
    """Rebuild a group made where a back end could not be built and can be here (OSL where
    Cycles compiles it, the SVM graph where Blender has the Ray Portal BSDF), or by an add-on
    whose OSL shader differs (its bytecode would not read the current texture layout and
    would render the fallback) or whose fit is of another version (refit from the tables, the
    SVM back end's match image with it). Returns True when it rebuilt the group."""
    if tree.library is not None:
        return False
    info = _info(tree)
    if not info.get("material") or not info.get("tables"):
        return False
    script = tree.nodes.get(SCRIPT)
    stale_osl = osl_compiler_available() and (script is None or script.get("flowbsdf_src") != _source_hash())
    missing_svm = svm_available() and not _has_svm(tree) and Path(info["tables"]).is_file()
    stale_fit = _stale_fit(tree)
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


def _stale_fit(tree):
    """Whether the group's fit is of an older version (made by an older add-on) and can be
    refit here: its tables are at hand and the bake module imports."""
    info = _info(tree)
    return bool(info.get("has_fit") and info.get("fit_version", 0) != FIT_VERSION and info.get("tables")
                and Path(info["tables"]).is_file() and _bake_mod("export.closure_fit") is not None)


# ------------------------------------------------------------------------------ refits after a file opens

# Opening a .blend whose fits an older add-on made refits each from its tables (~5 s per
# material on 2 idle cores). In the UI that runs in a thread, the older fit rendering meanwhile
# (every readable version renders), so a file with many materials opens at once; each group is
# rebuilt as its fit is written, and a final render waits for the rest (render_pre). Without a
# UI (blender --background, a farm's render) load_post refits before anything renders.
_refit = {"thread": None, "tables": [], "done": set(), "errors": {}}


def refit_in_thread():
    """Whether refits after a file opens run in a thread (the UI) rather than in load_post."""
    return not bpy.app.background


def _refit_worker(tables, done, errors):
    closure_fit = _bake_mod("export.closure_fit")
    for path in tables:
        try:
            closure_fit.ensure_fit(path)
        except Exception as e:      # noqa: BLE001  (the older fit keeps rendering; the status says why)
            errors[path] = str(e)
        done.add(path)


def refit_later(trees):
    """Refit the fits of `trees` (stale: `_stale_fit`) in a thread; a timer rebuilds each group
    once its fit file is written (`refit_poll`)."""
    import threading
    tables = list(dict.fromkeys(_info(t)["tables"] for t in trees))
    if not tables:
        return
    finish_refits()         # (a file opened while another's refits ran: those first)
    done, errors = set(), {}
    thread = threading.Thread(target=_refit_worker, args=(tables, done, errors), name="FlowBSDF refit", daemon=True)
    _refit.update(thread=thread, tables=tables, done=done, errors=errors)
    print(f"FlowBSDF: remaking {len(tables)} closure fit(s) of an older add-on in the background; "
          "the older fits render until then")
    thread.start()
    if not bpy.app.timers.is_registered(refit_poll):
        bpy.app.timers.register(refit_poll, first_interval=0.5)


def refitting(tree):
    """(done, total) of the refits running when `tree` waits for one, else None."""
    if _refit["thread"] is None or _info(tree).get("tables") not in _refit["tables"] or not _stale_fit(tree):
        return None
    return len(_refit["done"]), len(_refit["tables"])


def refit_poll():
    """Rebuild the groups whose new fit is written (a bpy timer: None stops it)."""
    done = set(_refit["done"])
    for tree in list(_trees()):
        tables = _info(tree).get("tables")
        if tables in done and _stale_fit(tree):
            if tables in _refit["errors"]:
                print(f"FlowBSDF: could not refit {tree.name} (its older fit renders): {_refit['errors'][tables]}")
                _store(tree, {**_info(tree), "problems": f"refit failed: {_refit['errors'][tables]}"})
                continue
            try:
                upgrade(tree)
            except Exception as e:      # noqa: BLE001
                print(f"FlowBSDF: could not rebuild {tree.name} with its new fit: {e}")
    if len(done) < len(_refit["tables"]):
        return 0.5
    _refit["thread"] = None
    for scene in bpy.data.scenes:
        sync(scene)
    return None


def finish_refits():
    """Wait for the refits running and rebuild their groups (before a final render)."""
    thread = _refit["thread"]
    if thread is None:
        return
    thread.join()
    refit_poll()
    if bpy.app.timers.is_registered(refit_poll):
        bpy.app.timers.unregister(refit_poll)


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
    tree = _tree_for(name)
    scene = bpy.context.scene
    if scene is not None and scene.render.engine == 'CYCLES' and tables_path.is_file():
        _world_inputs(scene, tables_path.parent, bake=True)     # the world's map first: one graph, with it
    _build_tree(tree, name, tables_path, fit_path)
    if material.node_tree is None:
        material.use_nodes = True
    mtree = material.node_tree
    node = None
    for n in mtree.nodes:
        if n.bl_idname == "ShaderNodeGroup" and n.node_tree is not None and TREE_KEY in n.node_tree.keys():
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
    node.inputs["Tangent"].hide = not _info(tree).get("anisotropic", False)
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


# ------------------------------------------------------------------------------ back ends

def backend_of(scene):
    """The scene's back end setting: "osl", "fit" or "auto" (default)."""
    if hasattr(bpy.types.Scene, SCENE_PROP):
        value = getattr(scene, SCENE_PROP)
    else:
        value = scene.get(SCENE_PROP)
        if isinstance(value, int):        # the enum as stored by a session with the add-on
            value = ENUM_ORDER[value] if 0 <= value < len(ENUM_ORDER) else "auto"
    return value if value in BACKENDS else "auto"


def set_backend(scene, backend):
    """Choose the back end for `scene`: "osl", "fit" or "auto" (OSL when the scene renders
    with Cycles on the CPU with Open Shading Language on, else the fit); applies it now."""
    if backend not in BACKENDS:
        raise ValueError(f"FlowBSDF back end must be one of {BACKENDS}, not {backend!r}")
    if hasattr(bpy.types.Scene, SCENE_PROP):
        setattr(scene, SCENE_PROP, backend)
    else:
        scene[SCENE_PROP] = backend
    sync(scene)


def osl_available(scene):
    """(bool, why not, in the UI's words): OSL renders in this scene's settings."""
    if scene.render.engine != 'CYCLES':
        return False, f"{engine_name(scene)} runs no OSL"
    if scene.cycles.device != 'CPU':
        return False, "OSL needs the CPU"
    if not scene.cycles.shading_system:
        return False, "OSL is off"
    return True, ""


ENGINE_NAMES = {"BLENDER_EEVEE": "EEVEE", "BLENDER_EEVEE_NEXT": "EEVEE", "BLENDER_WORKBENCH": "Workbench",
                "CYCLES": "Cycles"}


def engine_name(scene):
    return ENGINE_NAMES.get(scene.render.engine, scene.render.engine.title())


class Status(NamedTuple):
    """What a Learned BSDF node renders in a scene, in the words of Blender's UI: `text` what
    renders and how far it is from the measured material, `action` the one step that gets the
    exact material in this scene ("" where it renders exactly), `operator` the button that takes
    the step, (bl_idname, {property: value}), or () where the artist takes it, and `detail` what
    the short words leave out (a path): the panel's tooltip and the logs."""
    backend: str            # what renders: "osl", "svm" or "fit"
    text: str
    action: str = ""
    operator: tuple = ()
    detail: str = ""

    def line(self):
        """The status as one line (logs, reports, node_status)."""
        return (self.text + (f". {self.action}" if self.action else "")
                + (f" ({self.detail})" if self.detail else ""))


USE_OSL = ("Turn On OSL (CPU)", ("flowbsdf.use_osl", {}))
USE_SVM = ("Set Back End to SVM", ("flowbsdf.set_backend", {"backend": "svm"}))
BAKE = ("Bake the Material", ("flowbsdf.bake", {"only_active": True}))


def _reach(hidden):
    """(why, step) for the first lamp of `hidden` (lamps.unreachable): what keeps the SVM
    back end's portal from it and the button that makes it reachable."""
    name, why = next(iter(hidden.items()))
    text, button = lamps.REACH[why]
    return text.format(name), (button, ("flowbsdf.reach_lamp", {"lamp": name}))


# Render samples from which `auto` takes the SVM graph under lamps it reaches (not OSL's): at
# equal CPU time to Principled's 4096 spp (Blender's default; the SVM graph gets ~800) its MSE
# against the measured file is below the fit's (studio lamps, 48 px sphere, 6 seeds, hashed u
# as under Blender's default pixel filter; the FIT_VERSION 7 fit: SVM / fit 0.13 / 0.72 / 0.58 on
# colodur_napoli_4f, cc_nothern_aurora, irid_flake_paint1, files the lamp work was not tuned on;
# 0.80 / 0.47 / 1.73 on cm_military_green, vch_golden_yellow, satin_rosaline); at 128 spp 4-19x.
# Measured without adaptive sampling (tests/cycles_scenes.reset): with it, svm_pays.
SVM_LAMP_SAMPLES = 4096


def svm_pays(scene):
    """Whether the scene's render samples reach SVM_LAMP_SAMPLES (the SVM graph beats the fit
    under lamps at equal time from about there) with adaptive sampling off, in Blender 5.0+ where
    that was measured (4.5's SVM graph, Transparent Depth for Portal Depth, is 4-6x noisier under
    lamps relative to OSL: tests/test_cycles_lights.py's unbiased test, 62/22/19x OSL's variance
    against 5.0's 15/12/11x). Adaptive sampling (Blender's default Noise Threshold 0.01) stops the
    fit's pixels early and the SVM graph's late: at Blender's render settings (denoising off;
    studio lamps, 48 px, 2 seeds, MSE against the file) both at 4096 samples, SVM / fit MSE 1.16
    (cm_military_green) and 0.21 (vch_golden_yellow) at 3.5x and 6.8x the fit's CPU time: at
    equal time the fit wins (~4x and ~1.9x) (the note of s41, svmdef)."""
    return (bpy.app.version >= (5, 0, 0) and int(scene.cycles.samples) >= SVM_LAMP_SAMPLES
            and not scene.cycles.use_adaptive_sampling)


def clamp_note(scene):
    """What the scene's clamping does to the SVM graph under lamps ("" without clamping): Cycles
    clamps each path's contribution, and the light the graph's portal carries arrives in fewer,
    larger contributions than the OSL shader's next-event estimation (its portal finds the lamps),
    so a clamp takes more of it. Measured at Blender's render settings (Clamp Indirect 10), a
    Diffuse wall lit only by a learned sphere (satin_rosaline) under an area lamp: the wall's mean
    -5.0 % with SVM, -1.1 % with OSL (SE 0.8 %); a sphere on a Diffuse floor under the studio
    lamps (cm_military_green): no change (tests/test_cycles_lights.py's wall, the note of s41)."""
    cy = scene.cycles
    limits = [(name, float(getattr(cy, prop, 0.0))) for name, prop in
              (("Clamp Direct", "sample_clamp_direct"), ("Clamp Indirect", "sample_clamp_indirect"))]
    on = [f"{name} {v:g}" for name, v in limits if v > 0.0]
    if not on:
        return ""
    return f"{' and '.join(on)} clamp the light its portal carries more than OSL's (measured to -5 %)"


def _resolve(scene, tree, limits=None):
    """The Status of one group in one scene (`limits`: lamps.limits(scene), computed here when
    not given). The exact back ends by preference: OSL (CPU; lamps by next-event estimation in
    the shader: the least noise), then the SVM graph (every device), else the fit."""
    info = _info(tree)
    backend = backend_of(scene)
    if info.get("has_fit"):
        err, of = info.get("fit_error", -1.0), "measured material" if info.get("fit_error_of") == "file" else "tables"
        if scene.render.engine != 'CYCLES':        # EEVEE's own fit
            err = info.get("eevee_error", -1.0)
        fit = f"Fit, ~{100 * err:.0f} % off the {of}" if err >= 0 else "Fit"
    else:
        fit = "Neutral grey (no fit)"

    def fallback(why, step, detail=""):
        return Status("fit", f"{fit} ({why})", step[0], step[1], detail)
    if backend == "fit":
        return fallback("Back End: Fit", ("Set Back End to Auto", ("flowbsdf.set_backend", {"backend": "auto"})))
    if scene.render.engine != 'CYCLES':
        return fallback(engine_name(scene), ("Render with Cycles", ("flowbsdf.use_cycles", {})))
    tables = info.get("tables", "")
    if not tables or not os.path.isfile(tables):
        return fallback("tables missing", BAKE, f"tables missing: {tables}")
    osl_ok, osl_why = osl_available(scene)
    osl_step = USE_OSL
    if tree.nodes.get(SCRIPT) is None:          # built in a Blender that cannot compile OSL
        osl_ok, osl_why, osl_step = False, "no OSL in this Blender", None
    elif not os.path.isfile(info.get("osl_texture", "")):
        osl_ok, osl_why, osl_step = False, "OSL texture missing", BAKE
    svm_ok = _has_svm(tree) and os.path.isfile(info.get("svm_texture", ""))
    notes = lamps.limits(scene) if limits is None else limits
    if osl_ok and backend in ("osl", "auto"):
        exact = "OSL, carried blend, exact" if os.path.isfile(info.get("carry_texture", "")) else "OSL, exact"
        if notes:
            return Status("osl", f"{exact}, but {notes[0][0]}", notes[0][1], (), "; ".join(n for n, _ in notes))
        return Status("osl", exact)
    lit = lamps.scene_lamps(scene)
    # The SVM graph lights its fit's closures by Cycles' lamp sampling and the rest through its
    # portal, which draws toward the lamps visible to the camera that have a size: exact there.
    # Its error is noise, the fit's bias: at equal CPU time (studio lamps, 48 px sphere, MSE
    # against the FILE, scripts/lights_acceptance.py) the fit wins at Principled's 128 spp (SVM
    # 9-19x its MSE) and SVM at Blender's default 4096 (SVM_LAMP_SAMPLES) without adaptive
    # sampling (with it the fit: svm_pays), `auto` follows.
    hidden = lamps.unreachable(scene) if lit else {}
    if svm_ok and (backend == "svm" or not lit or (backend == "auto" and not hidden and svm_pays(scene))):
        clamped = "; ".join(n for n in ((clamp_note(scene) if lit else ""),
                                        ("Caustics off: control variate off" if lit and caustics_off(scene) else "")) if n)
        if hidden:
            why, step = _reach(hidden)
            return Status("svm", f"SVM, exact but {why}: it lights only the fit", *step,
                          detail="; ".join([f"{n}: {w}" for n, w in hidden.items()] + ([clamped] if clamped else [])))
        return Status("svm", "SVM, exact", detail=clamped)
    # The fit renders: the step to an exact back end. OSL where the node has it, on the CPU;
    # where the scene renders on the GPU, the SVM graph (every device runs it) first.
    if backend == "svm":
        why = "no SVM in this Blender"
    else:
        why = "lamps need OSL" if lit and backend == "auto" and osl_step is USE_OSL else osl_why
    if svm_ok and (scene.cycles.device != 'CPU' or osl_step is None):
        if hidden:
            why, step = _reach(hidden)
        else:
            why, step = (why if not lit else f"under lamps SVM needs {SVM_LAMP_SAMPLES}+ samples"
                         if int(scene.cycles.samples) < SVM_LAMP_SAMPLES else "under lamps SVM needs Noise Threshold off"), USE_SVM
        return fallback(why, step)
    return fallback(why, osl_step or ("Render in Blender 5.0+", ()))


def _refresh_export(tree):
    """Re-export the textures when the tables exist but a texture is missing or stale: the
    OSL shader takes the new file's name; the SVM graph, whose constants come from its
    texture's layout, is rebuilt (with the whole group)."""
    info = _info(tree)
    tables = Path(info.get("tables", ""))
    if not tables.is_file():
        return
    if _has_svm(tree):
        try:
            current = _svm_texture(tables)
        except Exception as e:      # noqa: BLE001
            current = info.get("svm_texture")
            print(f"FlowBSDF: no SVM texture for {tables}: {e}")
        if current != info.get("svm_texture"):
            _build_tree(tree, info["material"], tables, Path(info["fit"]) if info.get("fit") else None)
            return
    script = tree.nodes.get(SCRIPT)
    if script is None:
        return
    try:
        texture = _osl_texture(tables)
    except Exception as e:      # noqa: BLE001
        info["problems"] = f"no OSL texture: {e}"
        _store(tree, info)
        return
    carried, socket = _carry_texture(tables), script.inputs.get("Carried")     # (a script of an older shader: none)
    if texture != script.inputs["Tables"].default_value or (socket is not None and carried != socket.default_value):
        script.inputs["Tables"].default_value = texture     # OSL reads absolute paths only
        if socket is not None:
            socket.default_value = info["carry_texture"] = carried
        info["osl_texture"] = texture
        _store(tree, info)


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
    for tree in _trees():
        if tree.library is not None:
            continue
        if refresh:
            _refresh_export(tree)
        if limits is None:
            limits = lamps.limits(scene)        # once per sync: it runs on every scene change
        backend = _resolve(scene, tree, limits).backend
        _set_switches(tree, backend)
        if film is None:
            continue
        folder = Path(_info(tree).get("tables", "")).parent
        if folder not in worlds:
            worlds[folder] = _world_inputs(scene, folder, bake_world)
        inputs = world.material_share(worlds[folder], _info(tree).get("matte"))
        if _has_svm(tree):
            from . import svm
            if not svm.update_world(tree, caustics_gate(scene, inputs)):  # a technique the graph lacks: rebuild it
                info = _info(tree)
                _build_tree(tree, info["material"], Path(info["tables"]),
                            Path(info["fit"]) if info.get("fit") else None)
                _set_switches(tree, backend)
            svm.set_film(tree, scene)
            lamps.bind_svm(tree, scene)
        script = tree.nodes.get(SCRIPT)         # (after a rebuild: a new node)
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


def caustics_off(scene):
    """Whether the scene turns Caustics (reflective or refractive) off."""
    cy = getattr(scene, "cycles", None)
    return cy is not None and not (cy.caustics_reflective and cy.caustics_refractive)


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
    if not caustics_off(scene) or not inputs.get("ControlVariate"):
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
    if tree is None or TREE_KEY not in tree.keys():
        return None
    status = _resolve(scene or bpy.context.scene, tree)
    problems = _info(tree).get("problems")
    if problems and status.backend != "fit":
        status = status._replace(detail="; ".join(p for p in (status.detail, problems) if p))
    waiting = refitting(tree)
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
    finish_refits()
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
    script = next((t.nodes.get(SCRIPT) for t in _trees() if t.library is None and t.nodes.get(SCRIPT)), None)
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
    later = [t for t in _trees() if t.library is None and _stale_fit(t)] if refit_in_thread() else []
    refit_later(later)
    for tree in list(_trees()):
        if tree in later:
            continue
        try:
            upgrade(tree)
        except Exception as e:      # noqa: BLE001  (the fit still renders)
            print(f"FlowBSDF: could not add the OSL back end to {tree.name}: {e}")
    for scene in bpy.data.scenes:
        sync(scene, refresh=True, bake_world=scene.render.engine == 'CYCLES' and any(_trees()))


@persistent
def _on_save_pre(*_):
    """The file is saved rendering what works without the add-on, in any Blender: the SVM
    graph (no OSL needed) where no lamp renders, else the fit (a Script node would render black
    where OSL is off; under lamps the fit beats the SVM graph at equal time: _resolve).
    load_post and the next scene update choose again."""
    scene = bpy.context.scene
    lit = bool(lamps.scene_lamps(scene)) if scene is not None else True
    for tree in _trees():
        if tree.library is None:
            _set_switches(tree, "svm" if _has_svm(tree) and not lit else "fit")


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
    if bpy.app.timers.is_registered(refit_poll):        # (a refit's thread only writes its fit file)
        bpy.app.timers.unregister(refit_poll)
    if hasattr(bpy.types.Scene, SCENE_PROP):
        del bpy.types.Scene.flowbsdf_backend
    if hasattr(bpy.types.Scene, FILM_PROP):
        delattr(bpy.types.Scene, FILM_PROP)
