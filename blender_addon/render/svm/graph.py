"""The SVM graph builder: Cycles shader nodes added to a node tree in evaluation order, laid out in
columns (`_Graph`), written as arithmetic (`Value`: a float socket with Python's operators, and
the functions below, named as in OSL), node groups made once per name (`_group`), the textures
packed into the .blend (`_image`), and the clean-up of what no graph uses (`drop_unused`). Why
creation order matters (Cycles' SVM stack) and what it measured: docs/svm.md."""
import math
import os

import bpy

from ... import deps
from .. import sockets

GRAPH_VERSION = deps.formats().GRAPH_VERSION      # in the node groups' names (bake/formats.py)
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
        if isinstance(value, Value):
            value = value.out
        if isinstance(value, bpy.types.NodeSocket):
            self.tree.links.new(value, socket)
        else:
            sockets.assign(socket, value)

    def math(self, op, a, b=0.0, c=0.0, clamp=False):
        node = self.node("ShaderNodeMath", operation=op, use_clamp=clamp)
        for socket, value in zip(node.inputs, (a, b, c)[:_MATH_ARITY.get(op, 2)]):
            self.set(socket, value)
        return Value(self, node.outputs[0])

    def vmath(self, op, a, b=(0.0, 0.0, 0.0), c=(0.0, 0.0, 0.0), scale=None):
        node = self.node("ShaderNodeVectorMath", operation=op)
        for socket, value in zip(node.inputs, (a, b, c)):
            self.set(socket, value)
        if scale is not None:
            self.set(node.inputs[3], scale)
        return Value(self, node.outputs[1]) if op in ('DOT_PRODUCT', 'LENGTH', 'DISTANCE') else node.outputs[0]

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
        return Outputs(self, node)

    def outputs(self, node):
        """The node's outputs, its float ones as Values (`Outputs`)."""
        return Outputs(self, node)

    def const(self, value):
        """A constant that arithmetic gives nodes of their own (an operator between two Python
        numbers is Python's: no node)."""
        return Value(self, float(value))

    def select(self, flag, a, b, clamp=False):
        """flag ? a : b for flag in {0, 1}, exactly (a x 1 + b x 0): no rounding, unlike a mix."""
        return self.math('MULTIPLY_ADD', a, flag, self.math('MULTIPLY', b, self.math('SUBTRACT', 1.0, flag)),
                         clamp=clamp)


class Value:
    """A float in the graph, a socket (or a constant: _Graph.const) whose arithmetic adds Math
    nodes: a + b, a - b, a * b, a / b, a % b (FLOORED_MODULO, as Python's %), -a (a x -1), abs(a),
    a < b and a > b (1 or 0), and the functions below (exp, log, sqrt, where, clamp, saturate, fma
    ...). Each operator adds its node when Python evaluates it: inner first, left to right, the
    order the builder's calls g.math('DIVIDE', g.math('MULTIPLY', v0, g.math('EXPONENT', ...)),
    total) added them in, so `v0 * exp(t * rate) / total` is the same four nodes in the same
    order. Nothing is folded or reordered, and a + b * c is two nodes (fma(b, c, a) is one).
    Write a comparison with its Value first: Python turns `0.5 > x` into x < 0.5 (LESS_THAN of
    x, not GREATER_THAN of 0.5). Never a truth value (`if x`: an error)."""
    __slots__ = ("g", "out")

    def __init__(self, g, out):
        self.g, self.out = g, out

    def __add__(self, other):
        return self.g.math('ADD', self, other)

    def __radd__(self, other):
        return self.g.math('ADD', other, self)

    def __sub__(self, other):
        return self.g.math('SUBTRACT', self, other)

    def __rsub__(self, other):
        return self.g.math('SUBTRACT', other, self)

    def __mul__(self, other):
        return self.g.math('MULTIPLY', self, other)

    def __rmul__(self, other):
        return self.g.math('MULTIPLY', other, self)

    def __truediv__(self, other):       # (Cycles' divide: 0 where other is 0)
        return self.g.math('DIVIDE', self, other)

    def __rtruediv__(self, other):
        return self.g.math('DIVIDE', other, self)

    def __mod__(self, other):
        return self.g.math('FLOORED_MODULO', self, other)

    def __neg__(self):
        return self.g.math('MULTIPLY', self, -1.0)

    def __abs__(self):
        return self.g.math('ABSOLUTE', self)

    def __lt__(self, other):
        return self.g.math('LESS_THAN', self, other)

    def __gt__(self, other):
        return self.g.math('GREATER_THAN', self, other)

    def __bool__(self):
        raise TypeError("a graph value has no truth value (where(flag, a, b) selects)")


class Outputs:
    """A node's outputs by name or index, float ones as Values."""

    def __init__(self, g, node):
        self.g, self.outputs = g, node.outputs

    def __getitem__(self, key):
        socket = self.outputs[key]
        return Value(self.g, socket) if socket.type == 'VALUE' else socket


def _graph(*args):
    for a in args:
        if isinstance(a, Value):
            return a.g
    raise TypeError("no graph value among the arguments (a constant that needs a node: _Graph.const)")


def _function(name, op, doc):
    def function(*args):
        return _graph(*args).math(op, *args)
    function.__name__ = function.__qualname__ = name
    function.__doc__ = f"{doc} (a {op} node)"
    return function


exp = _function("exp", 'EXPONENT', "e^x.")
sqrt = _function("sqrt", 'SQRT', "The square root (0 below 0: Cycles' safe_sqrtf).")
inversesqrt = _function("inversesqrt", 'INVERSE_SQRT', "1 / sqrt(x).")
sin = _function("sin", 'SINE', "sin x.")
cos = _function("cos", 'COSINE', "cos x.")
sinh = _function("sinh", 'SINH', "sinh x.")
atan = _function("atan", 'ARCTANGENT', "atan x.")
atan2 = _function("atan2", 'ARCTAN2', "atan2(y, x).")
acos = _function("acos", 'ARCCOSINE', "acos x (Cycles clamps x to [-1, 1]).")
sign = _function("sign", 'SIGN', "-1, 0 or 1.")
floor = _function("floor", 'FLOOR', "floor x.")
fract = _function("fract", 'FRACT', "x - floor x.")
minimum = _function("minimum", 'MINIMUM', "min(a, b).")
maximum = _function("maximum", 'MAXIMUM', "max(a, b).")
fma = _function("fma", 'MULTIPLY_ADD', "a b + c in one node.")
compare = _function("compare", 'COMPARE', "1 where |a - b| <= eps, else 0.")


def log(x):
    """The natural logarithm."""
    return _graph(x).math('LOGARITHM', x, math.e)


def clamp(x, lo, hi):
    """min(max(x, lo), hi): two nodes (saturate: [0, 1] within x's own node)."""
    return minimum(maximum(x, lo), hi)


def saturate(x):
    """x clamped to [0, 1] by its own Math node's Clamp option (no node of its own): x must be a
    Math node's output that nothing reads yet."""
    node = x.out.node
    if node.bl_idname != "ShaderNodeMath" or x.out.is_linked or node.use_clamp:
        raise ValueError(f"saturate needs a Math node's output nothing reads yet, not {node.name}'s")
    node.use_clamp = True
    return x


def where(flag, a, b):
    """flag ? a : b for a flag in {0, 1} (a comparison's), exactly: a x flag + b x (1 - flag)."""
    return _graph(flag, a, b).select(flag, a, b)


def raw(value):
    """A Value's socket (or number), for code outside the builder (tree.links.new)."""
    return value.out if isinstance(value, Value) else value


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
    """A socket or a number (or a Value of either), as a dictionary key."""
    if isinstance(value, Value):
        value = value.out
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
