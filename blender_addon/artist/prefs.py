"""Add-on preferences: the Python that bakes and trains (torch lives there, never in Blender),
and what it can do (deps.summary)."""
import bpy

# the add-on's package (this module's parent's): "blender_addon", "flowbsdf" (legacy) or "bl_ext.<repo>.flowbsdf"
ADDON_ID = __package__.rpartition(".")[0]


class FlowBSDFPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    python_path: bpy.props.StringProperty(
        name="Python", subtype="FILE_PATH",
        description="The Python that bakes (needs numpy + OpenEXR) and trains (needs torch + FlowBSDF's trainer, "
                    "e.g. the FlowBSDF checkout's .venv/bin/python). Empty: the Python Blender reports; it "
                    "trains only if it has torch and the trainer")
    module_path: bpy.props.StringProperty(
        name="Module folders", subtype="DIR_PATH",
        description="Folders added to the worker's PYTHONPATH (for materials given as a Python callable)")

    def draw(self, context):
        from .. import deps
        from . import uitext, worker
        col = self.layout.column()
        col.prop(self, "python_path")
        col.prop(self, "module_path")
        for text, icon in deps.summary(self.python_path, worker.extra_paths(self)):
            uitext.wrapped(col, text, icon, context)
        col.operator("flowbsdf.check_python", icon="CHECKMARK")


def get(context=None):
    """The preferences, or None where the add-on is not registered as such (e.g. tests)."""
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_ID)
    return addon.preferences if addon is not None else None


def user_dir(*parts):
    """A writable folder for the add-on's own files: the extension's user folder (4.2+),
    else Blender's user data folder."""
    import os
    try:
        base = bpy.utils.extension_path_user(ADDON_ID, create=True)
    except (AttributeError, ValueError, KeyError, RuntimeError):
        base = bpy.utils.user_resource("DATAFILES", path="flowbsdf", create=True)
    path = os.path.join(base, *parts)
    os.makedirs(path, exist_ok=True)
    return path


classes = (FlowBSDFPreferences,)
