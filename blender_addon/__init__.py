"""FlowBSDF for Blender: learned importance sampling of measured BSDFs in Cycles.

One package, two install forms: a Blender 4.2+ extension (blender_manifest.toml; built by
scripts/build_extension.py) and a legacy add-on for Blender 3.4+ (bl_info below). Modules:
    props      FlowBSDF data on materials/scenes     scan      what the scene needs -> manifest
    prefs      the Python that trains                worker    subprocess jobs, progress, cancel
    operators  the panel's operators                 jobs      scan -> worker -> bind nodes
    panels     Shader Editor sidebar + Material tab  batch     blender --background / -c flowbsdf
    node       the Learned BSDF node (issue 6)       validate  reference tracer vs Cycles
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


def _node_module():
    """The Learned BSDF node module (issue 6), or None while it is not there."""
    try:
        from . import node
    except ImportError as e:
        print(f"FlowBSDF: the Learned BSDF node is not available ({e})")
        return None
    return node


def register():
    global _cli_handle
    import bpy
    from . import operators, panels, prefs, props, validate
    props.register()
    for cls in prefs.classes + operators.classes + validate.classes + panels.classes:
        bpy.utils.register_class(cls)
    node = _node_module()
    if node is not None:
        node.register()
    if hasattr(bpy.utils, "register_cli_command"):          # Blender 4.2+: blender -c flowbsdf ...
        from . import batch
        _cli_handle = bpy.utils.register_cli_command("flowbsdf", batch.cli_command)


def unregister():
    global _cli_handle
    import bpy
    from . import operators, panels, prefs, props, validate, worker
    worker.clear()
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    node = _node_module()
    if node is not None:
        node.unregister()
    for cls in reversed(prefs.classes + operators.classes + validate.classes + panels.classes):
        bpy.utils.unregister_class(cls)
    props.unregister()
