"""FlowBSDF for Blender: learned importance sampling of measured BSDFs in Cycles.

One package, two install forms: a Blender 4.2+ extension (blender_manifest.toml; built by
scripts/build_extension.py) and a legacy add-on for Blender 3.4+ (bl_info below). Modules:
    props      FlowBSDF data on materials/scenes     scan      what the scene needs -> manifest
    prefs      the Python that trains                worker    subprocess jobs, progress, cancel
    operators  the panel's operators                 jobs      scan -> worker -> bind nodes
    panels     Shader Editor sidebar + Material tab  batch     blender --background / -c flowbsdf
    node       the Learned BSDF node: its back ends  validate  reference tracer vs Cycles
    osl/       the OSL back end (tables, lamps, world) svm      the SVM back end (shader nodes)
    lamps      the scene's lamps -> the OSL shader   world     the world's importance map
    sockets    socket values written on change       library   a folder of files -> asset library
    deps       where numpy's `bake` and its Python are  worker_main  the worker (outside Blender)
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
    from . import node, operators, panels, prefs, props, validate
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
    from . import node, operators, panels, prefs, props, validate, worker
    worker.clear()
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    node.unregister()
    for cls in reversed(prefs.classes + operators.classes + validate.classes + panels.classes):
        bpy.utils.unregister_class(cls)
    props.unregister()
