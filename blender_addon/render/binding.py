"""Where a Learned BSDF group keeps its binding: the tree's custom property "flowbsdf" (which
material, its tables, fit and textures, what the group holds), its file paths stored relative to
the .blend with their absolute forms beside them (`write`, `read`)."""
import os

import bpy

TREE_PREFIX = "Learned BSDF: "
TREE_KEY = "flowbsdf"
PATH_KEYS = ("tables", "fit", "osl_texture", "svm_texture", "carry_texture")
ABS_KEY = "absolute"        # the paths' absolute forms, beside their relative ones (`write`)


def trees():
    for tree in bpy.data.node_groups:
        if tree.bl_idname == "ShaderNodeTree" and TREE_KEY in tree.keys():
            yield tree


def read(tree):
    """The group's binding data, its file paths absolute (stored relative to the .blend: `write`)."""
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


def relative(path):
    """`path` relative to the saved .blend (//...), so the project folder can move; as it is
    for an unsaved file (or another drive)."""
    if not path or not bpy.data.filepath:
        return path
    try:
        return bpy.path.relpath(path)
    except ValueError:
        return path


def write(tree, info):
    """Record the binding: paths relative to the .blend (`relative`), and absolute under ABS_KEY."""
    paths = {key: os.path.normpath(bpy.path.abspath(info[key])) for key in PATH_KEYS if info.get(key)}
    tree[TREE_KEY] = {**{k: v for k, v in info.items() if k != ABS_KEY},
                      **{key: relative(path) for key, path in paths.items()}, ABS_KEY: paths}


def tree_for(name):
    for tree in trees():
        if read(tree).get("material") == name and tree.library is None:
            return tree
    return bpy.data.node_groups.new(TREE_PREFIX + name, "ShaderNodeTree")


def has_svm(tree):
    from .. import svm
    return any(n.name.startswith(svm.FILM) for n in tree.nodes)
