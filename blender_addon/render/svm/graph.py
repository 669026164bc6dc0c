"""The SVM graph builder: Cycles shader nodes added to a node tree in evaluation order, laid out in
columns (`_Graph`), node groups made once per name (`_group`), the textures packed into the .blend
(`_image`), and the clean-up of what no graph uses (`drop_unused`). Why creation order matters
(Cycles' SVM stack) and what it measured: docs/svm.md."""
import os

import bpy

from ... import sockets

GRAPH_VERSION = 3       # in the node groups' names: a graph built by other code gets new groups
GROUP_PREFIX = f"FlowBSDF SVM{GRAPH_VERSION} "
X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


PACKED = "flowbsdf_packed"       # an image's custom property: packed by _image (the panel's "Packed in the .blend")


def _image(path):
    """The texture as Cycles must read it: texel values bit-exact, and packed into the .blend
    (marked PACKED; one image per file: Blender's check_existing finds it under any spelling of
    its path, relative or not).
    Packed, Cycles reads it through its own image manager on every device and shading system.
    A file image under Open Shading Language goes through OIIO's texture system instead, which
    read a new texture file as zeros now and then: the material rendered black (measured, bpy
    5.0.1, a scene of three spheres on fresh copies of the same three textures, back end SVM,
    OSL on: 3 of 65 scenes had a black sphere, 0 of 65 packed; OSL off, unpacked: 0 of 40).
    The .blend grows by the texture (0.3 MB for a near-matte Final bake).
    The settings are written only when they differ: a write reloads the image and Cycles
    compiles the materials anew (measured 4 s per render of a 16² scene under OSL)."""
    image = bpy.data.images.load(str(path), check_existing=True)
    if image.packed_file is None:
        image.pack()
    if not image.get(PACKED):
        image[PACKED] = True
    if bpy.data.filepath and os.path.isabs(image.filepath):    # relative to the .blend: the project moves
        try:
            image.filepath = bpy.path.relpath(image.filepath)
        except ValueError:              # another drive
            pass
    for owner, key, value in ((image.colorspace_settings, "name", 'Non-Color'), (image, "alpha_mode", 'CHANNEL_PACKED'),
                              (image, "use_half_precision", False)):
        if hasattr(owner, key) and getattr(owner, key) != value:
            setattr(owner, key, value)
    return image


# How many inputs a Math operation reads (2 unless listed)
_MATH_ARITY = {**dict.fromkeys(('SQRT', 'INVERSE_SQRT', 'ABSOLUTE', 'EXPONENT', 'SIGN', 'ROUND', 'FLOOR', 'CEIL',
                                'TRUNC', 'FRACT', 'SINE', 'COSINE', 'TANGENT', 'ARCSINE', 'ARCCOSINE', 'ARCTANGENT',
                                'SINH', 'COSH', 'TANH', 'RADIANS', 'DEGREES'), 1),
               **dict.fromkeys(('MULTIPLY_ADD', 'COMPARE', 'SMOOTH_MIN', 'SMOOTH_MAX', 'WRAP'), 3)}


class _Graph:
    """Adds nodes to a node tree in evaluation order (docs/svm.md), laid out in
    columns; inputs are sockets (linked) or constants (set).

    Every write to a node costs time in proportion to its tree's size (Blender updates the tree
    after each: 0.15 ms at 50 nodes, 0.6-1.5 ms at 500): writes that change nothing are
    skipped, and so are the inputs an operation does not read; the large stages are node
    groups of their own (_tables_group, _cv_fcos_group, node._fit_group). Measured, assigning
    a material (bpy 5.0.1, old and new code side by side): the test Lambertian 2.6-4.0 s ->
    1.5-1.7 s; cm_military_green under a sky, a second assignment 7.2 -> 1.0 s (its tree 732
    -> 277 nodes; the graph Cycles compiles the same)."""

    def __init__(self, tree, location=(0.0, 0.0)):
        self.tree, self.location, self.count = tree, location, 0

    def node(self, kind, **props):
        node = self.tree.nodes.new(kind)
        for key, value in props.items():
            if getattr(node, key) != value:
                setattr(node, key, value)
        node.location = (self.location[0] + 180.0 * (self.count // 10), self.location[1] - 160.0 * (self.count % 10))
        node.hide = True
        self.count += 1
        return node

    def set(self, socket, value):
        if isinstance(value, bpy.types.NodeSocket):
            self.tree.links.new(value, socket)
        else:
            sockets.assign(socket, value)

    def math(self, op, a, b=0.0, c=0.0, clamp=False):
        node = self.node("ShaderNodeMath", operation=op, use_clamp=clamp)
        for socket, value in zip(node.inputs, (a, b, c)[:_MATH_ARITY.get(op, 2)]):
            self.set(socket, value)
        return node.outputs[0]

    def vmath(self, op, a, b=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0), scale=None):
        node = self.node("ShaderNodeVectorMath", operation=op)
        for socket, value in zip(node.inputs, (a, b, c)):
            self.set(socket, value)
        if scale is not None:
            self.set(node.inputs[3], scale)
        return node.outputs[1 if op in ('DOT_PRODUCT', 'LENGTH', 'DISTANCE') else 0]

    def dot(self, a, b):
        return self.vmath('DOT_PRODUCT', a, b)

    def scale(self, v, f):
        return self.vmath('SCALE', v, scale=f)

    def combine(self, x, y, z=0.0):
        node = self.node("ShaderNodeCombineXYZ")
        for socket, value in zip(node.inputs, (x, y, z)):
            self.set(socket, value)
        return node.outputs[0]

    def group(self, tree, **inputs):
        node = self.node("ShaderNodeGroup", node_tree=tree)
        for name, value in inputs.items():
            self.set(node.inputs[name], value)
        return node.outputs

    def select(self, flag, a, b, clamp=False):
        """flag ? a : b for flag in {0, 1}, exactly (a x 1 + b x 0): no rounding, unlike a mix."""
        return self.math('MULTIPLY_ADD', a, flag, self.math('MULTIPLY', b, self.math('SUBTRACT', 1.0, flag)),
                         clamp=clamp)


# ------------------------------------------------------------------------------ node groups

def _group(name, inputs, outputs):
    """(existing node group of that name, None) or (None, a new empty one with the sockets)."""
    tree = bpy.data.node_groups.get(name)
    if tree is not None:
        return tree, None
    tree = bpy.data.node_groups.new(name, "ShaderNodeTree")
    for socket, kind in inputs:
        tree.interface.new_socket(socket, in_out="INPUT", socket_type=f"NodeSocket{kind}")
    for socket, kind in outputs:
        tree.interface.new_socket(socket, in_out="OUTPUT", socket_type=f"NodeSocket{kind}")
    return None, tree


def _key(value):
    """A socket or a number, as a dictionary key."""
    return (value.node.name, value.identifier) if isinstance(value, bpy.types.NodeSocket) else value


def _mix_shader(g, fac, first, second):
    """first where fac is 0, second where it is 1 (a Mix Shader: the other branch is skipped)."""
    node = g.node("ShaderNodeMixShader")
    g.set(node.inputs[0], fac)
    g.set(node.inputs[1], first)
    g.set(node.inputs[2], second)
    return node.outputs[0]


def drop_unused():
    """Remove the graphs' node groups that nothing uses, then the images _image packed that
    nothing uses. Blender saves whatever something holds, an unused group too: the superseded
    world map's groups (a search step held by the old sample group) kept the old map packed in
    the .blend beside the new one (+4.6 MB per world edit)."""
    while True:
        unused = [t for t in bpy.data.node_groups if t.name.startswith(GROUP_PREFIX) and t.users == 0]
        if not unused:
            break
        for tree in unused:
            bpy.data.node_groups.remove(tree)
    for image in [i for i in bpy.data.images if i.get(PACKED) and i.users == 0]:
        bpy.data.images.remove(image)
