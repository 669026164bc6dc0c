"""FlowBSDF for Blender: learned importance sampling of measured BSDFs in Cycles.

One package, two install forms: a Blender 4.2+ extension (blender_manifest.toml; built by
scripts/build_extension.py) and a legacy add-on for Blender 3.4+ (bl_info below). In layers,
each importing only its own or lower ones (tests/test_layers.py):
    __init__, batch   the faces: registration here; batch, the command line (blender -c flowbsdf,
                      or --python-expr "import flowbsdf.batch as b; b.main()": farms call it)
    artist/           what the artist and the farm drive: the panel, its operators and jobs, the
                      worker subprocess (artist/__init__.py lists its modules)
    render/           what renders: the Learned BSDF node, its OSL, SVM and fit back ends, the
                      lamps and the world map (render/__init__.py lists its modules); never
                      imports artist/
    deps              where numpy's `bake` and the worker's Python are (both sides use it)
"""
bl_info = {
    "name": "FlowBSDF",
    "author": "FlowBSDF developers",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "Shader Editor > Sidebar > FlowBSDF; Material Properties > FlowBSDF",
    "description": "Learned importance sampling of measured and analytic BSDFs",
    "category": "Material",
}

_cli_handle = None


def register():
    global _cli_handle
    import bpy
    from .artist import operators, panels, prefs, props, validate
    from .render import node
    props.register()
    for cls in prefs.classes + operators.classes + validate.classes + panels.classes:
        bpy.utils.register_class(cls)
    node.register()
    if hasattr(bpy.utils, "register_cli_command"):          # Blender 4.2+: blender -c flowbsdf ...
        from . import batch
        _cli_handle = bpy.utils.register_cli_command("flowbsdf", batch.cli_command)


def unregister():
    global _cli_handle
    import bpy
    from .artist import operators, panels, prefs, props, validate, worker
    from .render import node
    worker.clear()
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    node.unregister()
    for cls in reversed(prefs.classes + operators.classes + validate.classes + panels.classes):
        bpy.utils.unregister_class(cls)
    props.unregister()
