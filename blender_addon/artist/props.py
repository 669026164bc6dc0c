"""FlowBSDF's data on Blender materials and scenes, and turning it into manifest entries."""
import json
import re

import bpy

# Built-in analytic materials (bake/materials/analytic.py); "Values" overrides any key.
ANALYTIC_PRESETS = {
    "MATTE": ("Matte", {"model": "lambert", "albedo": 0.8}),
    "PLASTIC": ("Red plastic", {"model": "plastic", "albedo": [0.7, 0.1, 0.08], "alpha": 0.12}),
    "GOLD": ("Glossy gold", {"model": "ggx", "alpha": 0.04, "eta": [0.143, 0.374, 1.442],
                             "k": [3.983, 2.385, 1.603]}),
    "ROUGH_METAL": ("Rough metal", {"model": "ggx", "alpha": 0.3, "f0": [0.56, 0.57, 0.58]}),
    "VELVET": ("Velvet", {"model": "sheen", "color": [0.5, 0.1, 0.4], "roughness": 0.4}),
}
# Bake settings (bake/core/settings.py BakeSettings): DRAFT for look-dev previews, FINAL = the baker's defaults.
BAKE_QUALITY = {
    "DRAFT": {"resolution": 16, "tol": 0.5, "grid": 96, "samples": 2048, "first_bins": 3,
              "ideal_resolution": 48},
    "PREVIEW": {"tol": 0.05, "samples": 4096, "ideal_resolution": 128},
    "FINAL": {},
}
NAME_RE = re.compile(r"[^A-Za-z0-9_.-]+")


def _path_options():
    """Options of a path property that may be relative to the .blend (//...): Blender 4.5+
    warns on a // path without PATH_SUPPORTS_BLEND_RELATIVE; older ones do not know it."""
    if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties:
        return {"PATH_SUPPORTS_BLEND_RELATIVE"}
    return set()


PATH_OPTIONS = _path_options()


def manifest_name(material):
    """The material's name in the manifest (letters, digits, _ . -)."""
    s = material.flowbsdf
    name = NAME_RE.sub("_", (s.name or material.name).strip()).strip("._-") or "material"
    return name if re.match(r"^[A-Za-z0-9_]", name) else "m_" + name


class SourceError(ValueError):
    """A material's FlowBSDF source is incomplete; the message names the material."""


def source_spec(material):
    """The manifest `source` for a material's FlowBSDF settings (absolute paths)."""
    s = material.flowbsdf
    if s.source_kind == "FILE":
        if not s.filepath.strip():
            raise SourceError(f"material {material.name!r}: pick an RGL .bsdf or MERL .binary file")
        return bpy.path.abspath(s.filepath, library=material.library)
    if s.source_kind == "ANALYTIC":
        spec = {"kind": "analytic", **ANALYTIC_PRESETS[s.analytic_preset][1]}
        if s.analytic_params.strip():
            try:
                extra = json.loads(s.analytic_params)
            except ValueError as e:
                raise SourceError(f"material {material.name!r}: parameters are not JSON ({e})") from None
            if not isinstance(extra, dict):
                raise SourceError(f"material {material.name!r}: parameters must be a JSON object")
            spec.update(extra)
        return spec
    if not re.match(r"^[\w.]+:\w+$", s.python_callable.strip()):
        raise SourceError(f"material {material.name!r}: the callable must look like 'module:function'")
    return {"kind": "python", "callable": s.python_callable.strip(), "isotropic": s.python_isotropic}


def manifest_entry(material):
    s = material.flowbsdf
    return {"name": manifest_name(material), "source": source_spec(material), "domain": s.domain.lower(),
            "train": {"preset": s.preset.lower()},
            "bake": {**BAKE_QUALITY[s.bake_quality], "source": "flow" if s.tables_from == "MODEL" else "auto",
                     **({"carry": s.carried} if s.source_kind == "FILE" else {})}}


QUALITY_ITEMS = [("DRAFT", "Draft", "Tiny tables, seconds: layout and tests"),
                 ("PREVIEW", "Preview", "Coarser tables for look-dev"),
                 ("FINAL", "Final", "The baker's defaults")]        # (BAKE_QUALITY's keys)


class FlowBSDFMaterial(bpy.types.PropertyGroup):
    enabled: bpy.props.BoolProperty(name="Learned BSDF", description="Render this material with FlowBSDF")
    name: bpy.props.StringProperty(name="Name", description="Name in the manifest and of the table file "
                                   "(default: the material's name)")
    source_kind: bpy.props.EnumProperty(name="Source", items=[
        ("FILE", "Measured", "A measured file: RGL .bsdf or MERL .binary"),
        ("ANALYTIC", "Analytic", "A built-in analytic BSDF"),
        ("PYTHON", "Python", "A Python callable module:function returning f(wi, wo) as (N, 3)")])
    filepath: bpy.props.StringProperty(name="File", subtype="FILE_PATH", options=PATH_OPTIONS)
    analytic_preset: bpy.props.EnumProperty(
        name="Model", items=[(k, v[0], json.dumps(v[1])) for k, v in ANALYTIC_PRESETS.items()])
    analytic_params: bpy.props.StringProperty(name="Values",
                                              description='JSON overrides of the model\'s values, e.g. {"alpha": 0.2}')
    python_callable: bpy.props.StringProperty(name="Callable", description="module:function")
    python_isotropic: bpy.props.BoolProperty(name="Isotropic", default=True)
    domain: bpy.props.EnumProperty(name="Domain", default="AUTO", items=[
        ("AUTO", "Auto", "Slope for sharp or layered gloss, disk otherwise (decided from the material)"),
        ("DISK", "Disk", "Projected hemisphere (isotropic materials)"),
        ("SPHERICAL", "Spherical", "theta, phi (anisotropic materials)"),
        ("SLOPE", "Slope", "log tan theta_h, phi_h of the half vector: sharp and layered glossy materials")])
    preset: bpy.props.EnumProperty(name="Training", default="BALANCED", items=[
        ("FAST", "Fast", "~1 min per material"), ("BALANCED", "Balanced", "2-3 min on 2 cores"),
        ("PAPER", "Paper", "GPU advised")])
    tables_from: bpy.props.EnumProperty(name="From", default="MATERIAL", items=[
        ("MATERIAL", "Material", "The material itself: its f·cos tabulated at each incident angle places the "
         "cells"),
        ("MODEL", "Trained model", "Its trained flow model places the cells (the paper's route; Final: 2-4 min; "
         "Train + Bake or Load Model first). The cells' masses come from the material either way")])
    carried: bpy.props.BoolProperty(
        name="Carried", default=False,
        description="Measured (RGL) files, OSL only: blend the tables between incident angles along the file's "
                    "own coordinates where that samples closer. Costs 5-6x OSL's time per sample: at equal "
                    "render time 6-10x the error of the default (measured). Off: fixed cells, the same look "
                    "on every device (the SVM graph renders those). Changing it bakes the tables again")
    bake_quality: bpy.props.EnumProperty(name="Tables", default="FINAL", items=QUALITY_ITEMS)


class FlowBSDFScanItem(bpy.types.PropertyGroup):
    """One row of the last scan (shown in the panel)."""
    material: bpy.props.StringProperty()
    learned: bpy.props.StringProperty()
    users: bpy.props.IntProperty()
    state: bpy.props.StringProperty()       # current | stale | missing | error | unsupported
    needs: bpy.props.StringProperty()       # incident bins
    detail: bpy.props.StringProperty()


class FlowBSDFScene(bpy.types.PropertyGroup):
    out_dir: bpy.props.StringProperty(
        name="Output", subtype="DIR_PATH", default="//flowbsdf", options=PATH_OPTIONS,
        description="Folder for the manifest, models and tables (// = beside the .blend)")
    scan_items: bpy.props.CollectionProperty(type=FlowBSDFScanItem)
    scan_index: bpy.props.IntProperty()
    last_manifest: bpy.props.StringProperty(name="Manifest", subtype="FILE_PATH", options=PATH_OPTIONS)
    validate_spp: bpy.props.IntProperty(name="Samples", default=16, min=1)
    validate_size: bpy.props.IntProperty(name="Size", default=64, min=8, max=1024)


class FlowBSDFJob(bpy.types.PropertyGroup):
    """The running job's progress, for the UI (window manager: not saved in files)."""
    running: bpy.props.BoolProperty()
    progress: bpy.props.FloatProperty(subtype="PERCENTAGE", min=0, max=100, precision=0)
    message: bpy.props.StringProperty()
    failed: bpy.props.BoolProperty()
    label: bpy.props.StringProperty()


classes = (FlowBSDFMaterial, FlowBSDFScanItem, FlowBSDFScene, FlowBSDFJob)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Material.flowbsdf = bpy.props.PointerProperty(type=FlowBSDFMaterial)
    bpy.types.Scene.flowbsdf = bpy.props.PointerProperty(type=FlowBSDFScene)
    bpy.types.WindowManager.flowbsdf_job = bpy.props.PointerProperty(type=FlowBSDFJob)


def unregister():
    del bpy.types.WindowManager.flowbsdf_job
    del bpy.types.Scene.flowbsdf
    del bpy.types.Material.flowbsdf
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
