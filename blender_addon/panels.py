"""The FlowBSDF panel, in the Shader Editor's sidebar and in Material Properties."""
import bpy

from . import worker

STATE_ICONS = {"current": "CHECKMARK", "stale": "FILE_REFRESH", "missing": "ERROR", "error": "CANCEL",
               "unsupported": "INFO", "unknown": "QUESTION"}


def _material(context):
    mat = getattr(context, "material", None)
    if mat is None and context.active_object is not None:
        mat = context.active_object.active_material
    return mat


def draw_job(layout, context):
    state = context.window_manager.flowbsdf_job
    job = worker.current
    running = job is not None and not job.done
    if not running and not state.message:
        return
    box = layout.box()
    row = box.row(align=True)
    text = f"{state.label}: {state.message}" if running else state.message
    if running and hasattr(row, "progress"):             # Blender 4.0+
        row.progress(factor=state.progress / 100.0, type="BAR", text=text[:80])
    else:
        row.label(text=text[:100], icon="TIME" if running else "INFO")
    if running:
        row.operator("flowbsdf.cancel", text="", icon="CANCEL")


def _wrapped(layout, text, icon, width=38):
    """A long text as several labels (Blender cuts a label at the panel's edge)."""
    import textwrap
    for k, line in enumerate(textwrap.wrap(text, width) or [""]):
        layout.label(text=line, icon=icon if k == 0 else "BLANK1")


def draw_renders(layout, mat, scene):
    """What the material's Learned BSDF node renders in this scene, and why (node.node_status)."""
    from . import node
    tree = mat.node_tree
    group = next((n for n in tree.nodes if n.bl_idname == "ShaderNodeGroup" and n.node_tree is not None
                  and node.TREE_KEY in n.node_tree.keys()), None) if tree is not None else None
    if group is None:
        return
    status = node.node_status(group, scene)
    exact = status.startswith(("OSL", "SVM"))
    _wrapped(layout.box(), f"Renders: {status}", "CHECKMARK" if exact and "warning" not in status else "ERROR")


def draw_material(layout, mat, scene=None):
    s = mat.flowbsdf
    if not s.enabled:
        layout.operator("flowbsdf.enable", icon="NODE_MATERIAL")
        return
    if scene is not None:
        draw_renders(layout, mat, scene)
    col = layout.column()
    col.prop(s, "enabled")
    col.prop(s, "name")
    col.prop(s, "source_kind", expand=True)
    if s.source_kind == "FILE":
        col.prop(s, "filepath")
    elif s.source_kind == "ANALYTIC":
        col.prop(s, "analytic_preset")
        col.prop(s, "analytic_params")
    else:
        col.prop(s, "python_callable")
        col.prop(s, "python_isotropic")
    col.prop(s, "domain")
    row = col.row(align=True)
    row.prop(s, "preset")
    row.prop(s, "bake_quality")
    row = col.row(align=True)
    op = row.operator("flowbsdf.bake", text="Train + Bake", icon="PLAY")
    op.only_active, op.train = True, "ALWAYS"
    row.operator("flowbsdf.load_model", text="Load Model", icon="FILEBROWSER")
    op = row.operator("flowbsdf.bake", text="Bake", icon="RENDER_STILL")
    op.only_active, op.train = True, "SCENE"


def draw_scene(layout, context):
    s = context.scene.flowbsdf
    col = layout.column()
    col.prop(s, "out_dir")
    col.prop(s, "train")
    row = col.row(align=True)
    row.operator("flowbsdf.scan", icon="VIEWZOOM")
    op = row.operator("flowbsdf.bake", text="Bake Scene", icon="RENDER_STILL")
    op.only_active, op.train = False, "SCENE"
    try:
        from . import node
        backend = node.backend_of(context.scene)
    except (ImportError, AttributeError):
        backend = None
    if backend is not None:
        row = col.row(align=True)
        row.label(text=f"Back end: {backend}")
        for key, label in (("auto", "Auto"), ("osl", "OSL"), ("svm", "SVM"), ("fit", "Fit")):
            row.operator("flowbsdf.set_backend", text=label, depress=(backend == key)).backend = key
    for item in s.scan_items:
        box = col.box()
        box.label(text=f"{item.material} -> {item.learned} ({item.users} object(s)): {item.state}",
                  icon=STATE_ICONS.get(item.state, "QUESTION"))
        if item.needs:
            box.label(text=item.needs)
        if item.detail:
            box.label(text=item.detail)
    if s.scan_items:
        col.operator("flowbsdf.validate", icon="IMAGE_REFERENCE")


class _Panel:
    bl_label = "FlowBSDF"

    def draw(self, context):
        layout = self.layout
        draw_job(layout, context)
        mat = _material(context)
        if mat is not None:
            draw_material(layout.box(), mat, context.scene)
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
    bl_idname = "FLOWBSDF_PT_material"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "material"
    bl_options = {"DEFAULT_CLOSED"}


classes = (FLOWBSDF_PT_node_editor, FLOWBSDF_PT_material)
