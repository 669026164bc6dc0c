"""The FlowBSDF panel, in the Shader Editor's sidebar and in Material Properties.

Laid out for Blender's default sidebar width (about 230 px at UI scale 1): one control per
row with its label on the left (property split), buttons one to a row (the back-end
switch four short ones), and every long text (what renders, job messages, scan results)
wrapped to the region's width (uitext.wrapped, measured in the UI font), never cut.
"""
import os

import bpy

from . import worker
from .uitext import wrapped

STATE_ICONS = {"current": "CHECKMARK", "stale": "FILE_REFRESH", "missing": "ERROR", "error": "CANCEL",
               "unsupported": "INFO", "unknown": "QUESTION"}


def _material(context):
    mat = getattr(context, "material", None)
    if mat is None and getattr(context, "active_object", None) is not None:
        mat = context.active_object.active_material
    return mat


def draw_job(layout, context):
    """The running job (what it does, a progress bar, Cancel), or the last one's result."""
    state = context.window_manager.flowbsdf_job
    job = worker.current
    running = job is not None and not job.done
    if not running and not state.message:
        return
    box = layout.box()
    icon = "TIME" if running else "ERROR" if state.failed else "INFO"
    wrapped(box, state.message or "starting", icon, context, boxes=1)
    if running:
        row = box.row(align=True)
        if hasattr(row, "progress"):             # Blender 4.0+
            row.progress(factor=state.progress / 100.0, type="BAR", text=f"{state.progress:.0f} %")
        else:
            row.prop(state, "progress", text="", slider=True)
        row.operator("flowbsdf.cancel", text="", icon="CANCEL")


def _learned_group(mat):
    from ..render import binding
    tree = mat.node_tree
    if tree is None:
        return None
    return next((n for n in tree.nodes if n.bl_idname == "ShaderNodeGroup" and n.node_tree is not None
                 and binding.TREE_KEY in n.node_tree.keys()), None)


_previews = None          # bpy.utils.previews collection of the bakes' preview images


def preview_file(mat):
    """The bake's preview image (<name>.preview.png beside the tables the node renders), or None."""
    import os
    from ..render import binding
    group = _learned_group(mat)
    if group is None:
        return None
    info = binding.read(group.node_tree)
    path = os.path.join(os.path.dirname(info.get("tables", "")), f"{info.get('material')}.preview.png")
    return path if os.path.isfile(path) else None


def preview_icon(path):
    """An icon id showing the image file (not stored in the .blend; reloaded when the file
    changes); 0 where Blender has no icons (background)."""
    import os
    import bpy.utils.previews
    global _previews
    if _previews is None:
        _previews = bpy.utils.previews.new()
    key = f"{path}@{os.stat(path).st_mtime_ns}"
    preview = _previews.get(key) or _previews.load(key, path, "IMAGE")
    return preview.icon_id


def close_previews():
    global _previews
    if _previews is not None:
        import bpy.utils.previews
        bpy.utils.previews.remove(_previews)
        _previews = None


def draw_preview(layout, mat):
    path = preview_file(mat)
    icon = preview_icon(path) if path else 0
    if icon:
        layout.template_icon(icon_value=icon, scale=5.0)


def draw_renders(layout, mat, scene, context, boxes=1):
    """What the material's Learned BSDF node renders in this scene, why, the step to the exact
    result and the status's detail (node.node_state)."""
    from ..render import node
    group = _learned_group(mat)
    if group is None:
        return
    status = node.node_state(group, scene)
    if status is None:
        return
    wrapped(layout, status.text, "ERROR" if status.action else "CHECKMARK", context, boxes)
    if status.action and status.operator:
        idname, props = status.operator
        op = layout.operator(idname, text=status.action, icon="FORWARD")
        for key, value in props.items():
            setattr(op, key, value)
    elif status.action:
        wrapped(layout, status.action, "FORWARD", context, boxes)
    if status.detail:           # what else the artist should know (a compile wait, a clamp, a hidden lamp)
        wrapped(layout, status.detail[:1].upper() + status.detail[1:], "INFO", context, boxes)


def _split(layout):
    col = layout.column()
    col.use_property_split = True
    col.use_property_decorate = False
    return col


def draw_material(layout, mat, context):
    s = mat.flowbsdf
    if not s.enabled:
        layout.operator("flowbsdf.enable", icon="NODE_MATERIAL")
        return
    draw_renders(layout, mat, context.scene, context)
    draw_preview(layout, mat)
    layout.prop(s, "enabled")
    col = _split(layout)
    col.prop(s, "name")
    col.prop(s, "source_kind")
    if s.source_kind == "FILE":
        col.prop(s, "filepath")
        if s.filepath.strip():          # the field shows the path's start: say which file it is
            wrapped(layout, bpy.path.basename(s.filepath), "FILE", context, boxes=1)
            col = _split(layout)
    elif s.source_kind == "ANALYTIC":
        col.prop(s, "analytic_preset")
        col.prop(s, "analytic_params")
    else:
        col.prop(s, "python_callable")
        col.prop(s, "python_isotropic")
    col.prop(s, "bake_quality")
    col.prop(s, "tables_from")
    if s.source_kind == "FILE":
        col.prop(s, "carried")
    trained = s.tables_from == "MODEL"
    if trained:                         # what training uses: only on the trained model's route
        col.prop(s, "preset")
        col.prop(s, "domain")
    col = layout.column(align=True)
    col.operator("flowbsdf.bake", text="Bake", icon="RENDER_STILL").only_active = True
    if trained:
        col.operator("flowbsdf.train_bake", text="Train + Bake", icon="PLAY").only_active = True
        col.operator("flowbsdf.load_model", text="Load Model", icon="FILEBROWSER")


_disk = {}                      # tables folder -> (its mtime, the text): the panel redraws often


def disk_use(folder):
    """How much the tables folder takes, in words ("" when there is none)."""
    try:
        mtime = os.stat(folder).st_mtime_ns
    except OSError:
        return ""
    if _disk.get(folder, (None,))[0] != mtime:
        files = [e for e in os.scandir(folder) if e.is_file()]
        _disk[folder] = (mtime, f"Tables: {sum(e.stat().st_size for e in files) / 1e6:.1f} MB, {len(files)} files")
    return _disk[folder][1]


def packed_use():
    """What FlowBSDF packed into the .blend, and why, in words ("" when nothing): the SVM back
    end's textures (svm._image packs them: unpacked, Cycles under Open Shading Language read a
    new texture as zeros now and then), those that something still uses (the ones saved)."""
    try:
        from ..render.svm import PACKED
    except ImportError:
        return ""
    sizes = [i.packed_file.size for i in bpy.data.images if i.get(PACKED) and i.packed_file is not None and i.users]
    if not sizes:
        return ""
    return (f"Packed in the .blend: {len(sizes)} texture{'s' if len(sizes) > 1 else ''}, {sum(sizes) / 1e6:.1f} MB "
            "(the SVM back end reads them)")


def draw_scene(layout, context):
    s = context.scene.flowbsdf
    col = _split(layout)
    col.prop(s, "out_dir")
    from . import scan
    used = disk_use(os.path.join(scan.out_dir(context.scene), "tables"))
    if used:
        wrapped(layout, used, "DISK_DRIVE", context)
    packed = packed_use()
    if packed:
        wrapped(layout, packed, "PACKAGE", context)
    from . import jobs
    where = jobs.unsaved_problem(context.scene)
    if where:
        wrapped(layout, where, "ERROR", context)
    col = layout.column(align=True)
    col.operator("flowbsdf.scan", text="Scan Scene", icon="VIEWZOOM")
    col.operator("flowbsdf.bake", text="Bake Scene", icon="RENDER_STILL").only_active = False
    try:
        from ..render import backends
        backend = backends.backend_of(context.scene)
    except (ImportError, AttributeError):
        backend = None
    if backend is not None:
        layout.label(text="Back end, all nodes:")
        row = layout.row(align=True)
        for key, label in (("auto", "Auto"), ("osl", "OSL"), ("svm", "SVM"), ("fit", "Fit")):
            row.operator("flowbsdf.set_backend", text=label, depress=(backend == key)).backend = key
    for item in s.scan_items:
        box = layout.box()
        name = item.material if item.learned in ("", item.material) else f"{item.material} ({item.learned})"
        wrapped(box, f"{name}: {item.state}, {item.users} object(s)", STATE_ICONS.get(item.state, "QUESTION"),
                context, boxes=1)
        for text in (item.needs, item.detail):
            if text:
                wrapped(box, text, "BLANK1", context, boxes=1)
    if s.scan_items:
        layout.operator("flowbsdf.validate", text="Validate", icon="IMAGE_REFERENCE")
    layout.operator("flowbsdf.make_library", text="Make Asset Library\u2026", icon="ASSET_MANAGER")


class _Panel:
    bl_label = "FlowBSDF"

    def draw(self, context):
        layout = self.layout
        draw_job(layout, context)
        mat = _material(context)
        if mat is not None:
            draw_material(layout.box(), mat, context)
        draw_scene(layout, context)


class FLOWBSDF_PT_node_editor(_Panel, bpy.types.Panel):
    bl_idname = "FLOWBSDF_PT_node_editor"
    bl_space_type = "NODE_EDITOR"
    bl_region_type = "UI"
    bl_category = "FlowBSDF"

    @classmethod
    def poll(cls, context):
        space = context.space_data
        return space is not None and getattr(space, "tree_type", "") == "ShaderNodeTree"


class FLOWBSDF_PT_material(_Panel, bpy.types.Panel):
    """Open by default: an artist sees it without hunting for it."""
    bl_idname = "FLOWBSDF_PT_material"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "material"

    @classmethod
    def unregister(cls):
        close_previews()


classes = (FLOWBSDF_PT_node_editor, FLOWBSDF_PT_material)
