"""The baked-table sampler as a plain Cycles shader node graph (SVM): every Cycles device.

`build_svm_sampler` adds to a shader node tree the nodes that reproduce `Tables.sample`
(bake/core/tables.py, the numpy reference) on the texture of bake/export/svm_export.py, and ends in a
Ray Portal BSDF that continues the path in the sampled direction with weight W = baked
f·cos / pdf. Nothing needs OSL: the graph runs wherever Cycles runs (CPU with OSL off,
CUDA, OptiX, HIP, Metal, oneAPI). The table sizes, offsets and search step counts are
constants of the graph, read from the texture's metadata when it is built; a table file
that changes gets a new texture (its name holds the tables' hash) and needs a rebuild.

Per shading point:
- wi = Incoming, n = the shading normal; cos theta_i = wi . n. The local frame's x is wi's
  own azimuth (isotropic tables: phi_i = 0) or, for anisotropic tables, the Tangent input
  (world x when unlinked) projected onto the tangent plane, phi_i = atan2(wi . y, wi . x);
  at normal incidence / a tangent along n, any perpendicular (as learned_bsdf.osl).
- u0, u1, u2: White Noise 4D of (Position, Ray Length) -> r, then White Noise 4D of
  (Incoming, r + portal depth + 64 Ray Depth) -> its colour (Cycles gives a node graph no
  sampler state: every path vertex hashes its own numbers). On camera rays before any
  portal, with Cycles' box pixel filter (`film_settings`, `set_film`), u0, u1 come from
  the sample's place in its pixel instead, rotated by a hash of the pixel and the render's
  seed: Cycles places a pixel's samples by its stratified sequence, so their u are
  stratified too (much less noise where the camera sees the material directly). Each u
  is uniform, so a pixel is unbiased over renders; but its u are tied to where its samples
  fall in it, so where the shading varies within a pixel (a silhouette, a sun's
  terminator) one render's pixel converges, as its samples grow, to a value off by an
  error that changes with the seed, not with the sample count (measured on a sky+sun
  sphere, 24 px across, 1024 spp: 8 % rms per pixel, up to 67 % on the silhouette).
- theta_i and phi_i bins through the texture's bin guides, the corner block's header
  gives the blend weights; the row search on u0 and the column search on u1 (v = u1 x the
  row's mass) run a fixed number of branchless steps from their guide's bracket; the
  cell's profiles give the point in the cell: the piece by comparisons with the pieces'
  cumulative masses, then its exponential's inverse CDF (both branches of exp_inverse_cdf
  computed and one selected by multiplying with 0 / 1: exact, no NaN);
  the direction goes to world space by the frame.
- Color = W when cos theta_i > 0 and the direction is above the geometric surface, else 0
  (the path ends). Cycles drops a closure whose mean weight is below 1e-5 (bsdf_ray_portal
  _setup): a weight below 2e-5 is Russian-rouletted up to 2e-5 with u2 instead (unbiased).

The world (`build_svm_sampler(..., world=...)`, the inputs blender_addon/world.py gives the
OSL shader): the portal direction is drawn from a mixture, as learned_bsdf.osl's. With
probability c_sun = SunShare (when SunCos < 1) uniform in the cone of the sky's sun (axis
SunDirection, cos of its half angle SunCos; lamps.h cone_direction), with c_world =
WorldShare from the world's importance map, else (c_tables) from the tables. The map
(bake/export/world_map.py's texture, WorldMap the numpy reference): the pixel's row and column by
branchless binary searches of the marginal and the row's conditional CDF (step counts fixed
when the graph is built, from the map's size), the direction uniform in the pixel's solid
angle; its pdf at a direction read back from the pixel's density. The technique is picked
by u1, rescaled within it (film-stratified u stay stratified per technique); u0 passes
through. Weight = baked f·cos / q, q = c_tables p_tables + c_world p_world + c_sun p_cone:
a table sample's W and pdf are the sampler's own, at a map or sun direction the tables'
inverse gives f·cos and p_tables; a technique's own sample counts its own density (the
others' are read at the direction: a direction on a pixel's or the cone's edge may round
out of its own). Zero below the shading or the geometric surface (the path ends; the
portal ray finds the true world where it escapes: the map only decides where samples go).
Each technique is a branch ending in its own Ray Portal, chosen by Mix Shaders whose
factor is exactly 0 or 1: Cycles runs only the chosen branch's nodes (svm.cpp
generate_multi_closure jumps over the other). The shares and the sun are values of two
named nodes ("FlowBSDF SVM world": WorldShare, SunShare, SunCos; "FlowBSDF SVM sun": the
direction), the map's numbers constants of its node groups (named after its image):
`update_world` changes both without a rebuild, unless the graph lacks a technique the new
inputs use. Without a map or a sun the graph is the tables' alone, as above.

Lamps (the world inputs' Lamps and LampShare: node._world_inputs): the mixture also draws
toward the lamps the portal reaches (lamps.svm_lamps: at most lamps.SVM_SLOTS), with probability
c_lamp = LampShare (the world's techniques share the rest), lamp k by its part c_k / c_lamp, c_k
in proportion to its power / distance^2 at the shading point (a sun lamp's strength), uniform
in the cone about its bounding sphere (a point or spot lamp's radius; an area lamp's half
diagonal, its object's scale included; a sun lamp: about its direction, of its angle); q adds
every lamp's c_k / (2 pi (1 - cos)) where the direction is in its cone (1 - cos as |d - axis|^2
/ 2: exact for small cones). A lamp technique's place and size are two named Combine XYZ
nodes (LAMP k, LAMP k size) that lamps.bind_svm drives from the lamp (keyframed lamps render
right at every frame); the number of techniques is the graph's (update_world asks for a
rebuild when it changes). The lamps' values are computed anew in each branch (a position
through a no-op of the branch's own; held from before the branches they would take the SVM stack
through all of it) and lamp by lamp, so few are alive at once; the lamps' branch makes them once
for its draw and the other techniques' density, before the tables' inverse. Measured
(tests/test_cycles_lights.py, a plastic sphere under an area lamp and a point lamp of radius
0.25, Blender's render settings): per-sample variance of the sphere's mean over OSL's 50-160x
-> 11-15x; Blender's smaller lamps (0.5 m, radius 0.1) 400-1250x -> 20-42x.

With a control variate (`build_svm_sampler(..., cv=...)`, the node's SVM back end whenever its
fit has one: bake/export/closure_fit.py cv_scales), a shading point takes, with probability
1 - s, Cycles closures rendering f_cv (the fit's Diffuse + GGX Glossy BSDFs scaled by per-
view-angle betas; weight / (1 - s)), which Cycles lights by its own next-event estimation of
lamps and the world with MIS; else (probability s, by u0, then rescaled: on camera rays the pick
is as stratified over a pixel's samples as u0) the
portal mixture above carrying the rest with weight (f cos - f_cv cos ok) / (q s): f_cv as
_cv_fcos computes what Cycles' bsdf_diffuse_eval and bsdf_microfacet_eval (GGX, no Fresnel)
give. The rest has both signs: its positive and negative channels are two portals (Cycles
picks a closure by the magnitude of its mean weight). The pick between closures and portal
is the graph's own, with a fixed s per view angle: Cycles' pick by weight would take a portal
whose direction found the sun (small weight there: q is large) rarely and then with a huge
weight. Unbiased for any betas and s (tests/test_svm.py: furnace, and sky + sun against the
mixture alone, with less noise). A Value node (CV) switches it: the world inputs'
ControlVariate (blender_addon/world.shader_inputs and node._world_inputs: on for a small sun, a
Sky Texture's sun or lamps, off elsewhere, where the mixture alone was better; absent: off;
update_world sets it) makes s = 1 and f_cv 0 when off.

Matched to a small light: where the world inputs give LightDirection (a Sky Texture's sun, the
map's small sun: world.shader_inputs), or else toward the lamp of the largest c_k at the shading
point (its draws then scaled as the world's light's are; the portal's share then grows from the
matched share toward the baked one with the other lamps' part of the lamps' weight, whose rest
is not ~0), the graph rescales the fit's closures at each shading
point so that f_cv = f toward that light (beta = f / f_fit there per channel, read trilinearly
from the fit's match image: bake/export/closure_fit.match_ratios, two lookups; the tables'
exact inverse there made the graph 1.6x as slow: sky sphere, CPU 20.3 vs 12.9 ms per spp in one
run), with the portal's share s of
node.matched_share (about the fit's error: the rest carries none of the light, only the
sky's difference). Where the light is below the shading surface, and at view angles whose fit
is too poor (node.MATCHED_ERROR_MAX: its f_cv overshoots f widely, and in the light's
shadow the rest renders negative pixels), the baked betas and s. beta depends on the shading
point alone, never on the sampled direction: unbiased as before. The light's direction is a
named node's value (LIGHT; update_world moves it, and asks for a rebuild when a light appears
or goes). Lamps the
portal cannot see (points without a radius) still light only f_cv: the node keeps the fit for
lamp-lit scenes without OSL (node._resolve), and for reachable lamps too, where at equal time
the fit still wins (the lights acceptance's studio).

Cycles compiles the graph into SVM instructions in node creation order wherever that
order is topological (svm.cpp generate_svm_nodes sweeps the nodes by id and emits every
node whose inputs are done), and frees a value's stack slots after its last user. The
builder creates every node just before its first use, so few values are alive at once:
the stack (255 floats; past it Cycles prints "out of SVM stack space" and renders the
material black) holds the graph with a wide margin (tests/test_svm.py measures it with
Cycles' own message: the anisotropic tables' graph needs ~80 floats, with the world
mixture ~90). Nodes that branches would share are kept apart (Cycles merges identical
nodes and runs shared ones before the branches, holding their results through all).
Channels are read with a dot product against a vector, never a Separate node (its unlinked
outputs keep stack slots for the whole shader).

`tables_pdf_graph` adds the sampler's inverse (Tables._locate): at a given direction, the
pdf and the baked f·cos, from branchless searches of the blended a edges (the row) and b
edges (the column) and the cell's profile densities: what one-sample MIS with another
sampling strategy (e.g. the world map) needs.

`build_svm_probe` builds the sampler (or its inverse, or the world mixture) on inputs read
from a probe image (per pixel u0, u1, cos theta_i, phi_i) and returns an Emission that
encodes wo (0.5 + 0.5 wo), the weight and the pdf side by side, `build_world_probe` the
map's sampling and pdf: for tests against numpy.

API: build_svm_sampler, update_world, world_layout, sample_graph, tables_pdf_graph,
build_svm_probe, build_world_probe, graph_counts, film_settings, set_film.
"""
import math
import os

import bpy

from . import deps
from .render import sockets

CUTOFF = 1e-5           # Cycles' CLOSURE_WEIGHT_CUTOFF
K_SMALL = 1e-4          # bake/core/tables.py _SMALL: the in-cell density's small-rate branch
LOG_MEAN_SERIES = 1e-3  # bake/core/tables.py LOG_MEAN_SERIES: the log mean's series below it
TANGENT = (1.0, 0.0, 0.0)
GRAPH_VERSION = deps.formats().GRAPH_VERSION      # in the node groups' names (bake/formats.py)
GROUP_PREFIX = f"FlowBSDF SVM{GRAPH_VERSION} "
FILM = "FlowBSDF SVM film"      # a Combine XYZ node per sampler: film_settings
WORLD = "FlowBSDF SVM world"    # a Combine XYZ node per mixture: (WorldShare, SunShare, SunCos)
SUN = "FlowBSDF SVM sun"        # a Combine XYZ node per mixture with a sun: SunDirection
LIGHT = "FlowBSDF SVM light"    # a Combine XYZ node per matched control variate: LightDirection
CV = "FlowBSDF SVM cv"          # a Value node per control variate: 1 on, 0 off (ControlVariate)
LAMP = "FlowBSDF SVM lamp"      # per lamp technique two Combine XYZ nodes lamps.bind_svm drives
LAMPS = "FlowBSDF SVM lamps"    # a Value node per mixture with lamps: their share (LampShare)
X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
# The fit's view tangent (node.view_tangent, and _cv_fcos_group's twin of it): the view direction
# projected onto the surface plus VIEW_TANGENT_EPS N x VIEW_TANGENT_NUDGE, a direction no shading
# normal is parallel to in practice (Cycles normalises cross(N, T): NaN for a zero tangent).
VIEW_TANGENT_NUDGE = (0.36, 0.48, 0.8)
VIEW_TANGENT_EPS = 1e-6
MATCHED_SHARE_MIN = 0.05      # node.matched_share's least share
# ... and its shares of the world's techniques (WorldShare, SunShare) there: the rest has next
# to nothing where the light is (paper_white, the lights acceptance's sky, noise per sample
# 0.162 / 0.142 / 0.139 at 1 / 0.25 / 0.05)
MATCHED_LIGHT_SCALE = 0.25


def _svm_export():
    import importlib
    from . import deps
    return importlib.import_module(f"{deps.bake.__name__}.export.svm_export")


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
    """Adds nodes to a node tree in evaluation order (see the module docstring), laid out in
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


def _weight_inputs(alpha):
    return [("Weights", "Vector")] + ([("Weight A", "Float")] if alpha else [])


def _record_group(image, alpha):
    """Group "record": the texel at UV blended over the bins: dot(colour, Weights), + alpha x
    Weight A with `alpha` (a record in red/green: Weights = (w0, w1, 0), no alpha; in
    blue/alpha: (0, 0, w0) and w1; four bins: (w0, w1, w2) and w3)."""
    done, tree = _group(f"{GROUP_PREFIX}record{' RGBA' if alpha else ' RGB'}: {image.name}",
                        [("UV", "Vector")] + _weight_inputs(alpha), [("Value", "Float")])
    if done:
        return done
    g = _Graph(tree)
    inp = g.node("NodeGroupInput").outputs
    tex = g.node("ShaderNodeTexImage", image=image, interpolation='Closest', extension='EXTEND')
    g.set(tex.inputs["Vector"], inp["UV"])
    value = g.dot(tex.outputs["Color"], inp["Weights"])
    if alpha:
        value = g.math('MULTIPLY_ADD', tex.outputs["Alpha"], inp["Weight A"], value)
    g.set(g.node("NodeGroupOutput").inputs["Value"], value)
    return tree


def _step_group(image, alpha):
    """Group "search step" (branchless binary search): index = Lo + Half; Lo moves there when
    the record at texture x Base X + index x Stride, y Base Y is <= Target."""
    done, tree = _group(f"{GROUP_PREFIX}search step{' RGBA' if alpha else ' RGB'}: {image.name}",
                        [("Lo", "Float"), ("Target", "Float"), ("Base X", "Float"), ("Base Y", "Float"),
                         ("Stride", "Float"), ("Half", "Float")] + _weight_inputs(alpha), [("Lo", "Float")])
    if done:
        return done
    g = _Graph(tree)
    inp = g.node("NodeGroupInput").outputs
    index = g.math('ADD', inp["Lo"], inp["Half"])
    uv = g.combine(g.math('MULTIPLY_ADD', index, inp["Stride"], inp["Base X"]), inp["Base Y"])
    weights = {name: inp[name] for name, _ in _weight_inputs(alpha)}
    value = g.group(_record_group(image, alpha), UV=uv, **weights)[0]
    above = g.math('GREATER_THAN', value, inp["Target"])
    lo = g.math('MULTIPLY_ADD', above, g.math('MULTIPLY', inp["Half"], -1.0), index)
    g.set(g.node("NodeGroupOutput").inputs["Lo"], lo)
    return tree


# ------------------------------------------------------------------------------ the sampler

def _key(value):
    """A socket or a number, as a dictionary key."""
    return (value.node.name, value.identifier) if isinstance(value, bpy.types.NodeSocket) else value


class _Sampler:
    """The sampler's nodes on one SVM texture (layout: bake/export/svm_export.py). `incident` adds
    the bin lookup and blend weights (once per graph), then `sample` and `locate` add the
    sampler and its inverse (the pdf at a direction).
    A texel's place is a pair (x, y) of texture coordinates (sockets or numbers), each moved by
    scalar Math and combined into a vector once per texel looked up: a Vector Math node costs
    Cycles' SVM ~5 scalar ones."""

    def __init__(self, g, texture_path, lay=None):
        self.g, self.path = g, texture_path
        self.lay = lay or _svm_export().read_layout(texture_path)
        self.image = _image(texture_path)
        self.du = 1.0 / self.lay["width"]
        self.dv = 1.0 / self.lay["height"]
        self.rpt = 4 // self.lay["NB"]          # records per texel: record q at texel q // rpt, slot q % rpt
        self.offsets, self.uvs = {}, {}
        # a cell's quantities (svm_export.CELL_QUANTITIES): mass, the a and b profiles' node values, W
        n = (_svm_export().CELL_QUANTITIES - 4) // 2
        self.on_a, self.on_b, self.on_w = range(1, 1 + n), range(1 + n, 1 + 2 * n), range(1 + 2 * n, 4 + 2 * n)

    def uv(self, at):
        """The texel place `at` (x, y) as a vector, made once per place."""
        key = tuple(map(_key, at))
        if key not in self.uvs:
            self.uvs[key] = self.g.combine(*at)
        return self.uvs[key]

    def fetch(self, at):
        tex = self.g.node("ShaderNodeTexImage", image=self.image, interpolation='Closest', extension='EXTEND')
        self.g.set(tex.inputs["Vector"], self.uv(at))
        return tex.outputs["Color"], tex.outputs["Alpha"]

    def offset(self, base, dx=0.0, dy=0.0):
        """base + (dx, dy) texels (dy down the image), each coordinate moved once per base and offset."""
        return tuple(self._moved(c, d) for c, d in zip(base, (dx * self.du, -dy * self.dv)))

    def _moved(self, c, d):
        if not d:
            return c
        key = (_key(c), d)
        if key not in self.offsets:
            self.offsets[key] = self.g.math('ADD', c, d)
        return self.offsets[key]

    def blend(self, q):
        """(alpha used?, the group inputs that blend quantity q's slot of a texel)."""
        wv, wa = self.weights[q % self.rpt]
        return wa is not None, ({"Weights": wv} if wa is None else {"Weights": wv, "Weight A": wa})

    def quantity(self, base, q):
        """Quantity q of the records at texel `base`, blended over the bins."""
        alpha, weights = self.blend(q)
        return self.g.group(_record_group(self.image, alpha), UV=self.uv(self.offset(base, q // self.rpt)),
                            **weights)[0]

    def at(self, base, index, stride):
        """The texel `index` records of `stride` texels after `base`."""
        return self.g.math('MULTIPLY_ADD', index, stride * self.du, base[0]), base[1]

    def search(self, lo, target, base, stride, steps, q, last):
        """The last index <= `last` (a socket or a number) whose quantity q is <= target, from
        lo (branchless, `steps` halvings). The end record (a total) can round to <= a target near
        its value: `last` caps the result there."""
        alpha, weights = self.blend(q)
        base = self.offset(base, q // self.rpt)
        for s in reversed(range(steps)):
            lo = self.g.group(_step_group(self.image, alpha), Lo=lo, Target=target, **{"Base X": base[0]},
                              **{"Base Y": base[1]}, Stride=stride * self.du, Half=float(2 ** s), **weights)[0]
        return self.g.math('MINIMUM', lo, last)

    def guide_lo(self, base, u, count):
        """The guide's lo for u in [0, 1] (entries at base + g texels, g < count)."""
        g = self.g
        entry = g.math('MINIMUM', g.math('FLOOR', g.math('MULTIPLY', u, float(count))), count - 1.0)
        color, _ = self.fetch(self.at(base, entry, 1))
        return g.dot(color, X)

    def bin_count(self, guide, value, index_value):
        """The bin index from a bin guide ([x0, G]) at `value`, the entry floor(index_value G)."""
        g = self.g
        x0, count = guide
        entry = g.math('FLOOR', g.math('MULTIPLY', index_value, float(count)))
        uv_x = g.math('MULTIPLY_ADD', entry, self.du, (x0 + 0.5) * self.du)
        color, alpha = self.fetch((uv_x, 1.0 - 0.5 * self.dv))
        # [value < t_j] = ceil(clamp(t_j - value, 0, 1)) per channel
        below = g.vmath('CEIL', g.vmath('MAXIMUM', g.vmath('MINIMUM', g.vmath('SUBTRACT', color, value),
                                                            (1.0, 1.0, 1.0)), (0.0, 0.0, 0.0)))
        return g.math('SUBTRACT', alpha, g.dot(below, (1.0, 1.0, 1.0)))

    def incident(self, cos_i, phi_i):
        """The corner block of the incident bins at sockets cos theta_i (>= 0) and phi_i (None
        for isotropic tables), the blend weights and the last row and column of the corner's
        own table (self.origin, self.weights, self.last: from the block's header for isotropic
        tables, whose bins may differ in size, MixedTables)."""
        g, lay = self.g, self.lay
        K, P, nx = lay["K"], lay["P"], lay["blocks_per_row"]
        bw, bh = lay["block"]
        k = self.bin_count(lay["theta_guide"], g.math('MULTIPLY', cos_i, -1.0), g.math('SUBTRACT', 1.0, cos_i)) \
            if K > 1 else 0.0
        if P > 1:
            x = g.math('FLOORED_MODULO', g.math('SUBTRACT', phi_i, lay["phi0"]), lay["period"])
            # halfvector tables: the whole periods phi_i was turned back by, plus the lobe's axes
            self.ref = g.math('ADD', g.math('SUBTRACT', g.math('SUBTRACT', phi_i, lay["phi0"]), x),
                              lay.get("frame", 0.0))
            p = self.bin_count(lay["phi_guide"], x, g.math('MULTIPLY', x, 1.0 / lay["period"]))
            corner = g.math('MULTIPLY_ADD', k, float(P), p)
        else:
            corner = k
        if lay["corners"] > nx:
            brow = g.math('FLOOR', g.math('MULTIPLY_ADD', corner, 1.0 / nx, 0.5 / nx))
            bcol = g.math('MULTIPLY_ADD', brow, -float(nx), corner)
        else:
            brow, bcol = 0.0, corner
        self.origin = (g.math('MULTIPLY_ADD', bcol, bw * self.du, 0.5 * self.du),
                       g.math('MULTIPLY_ADD', brow, -bh * self.dv, 1.0 - 1.5 * self.dv))
        head, head_a = self.fetch(self.origin)
        self.last = (lay["R"] - 1.0, lay["C"] - 1.0) if P > 1 else (g.dot(head, Z), head_a)
        t = s = 0.0
        if K > 1:
            c_k, c_k1 = g.dot(head, X), g.dot(head, Y)
            t = g.math('DIVIDE', g.math('SUBTRACT', c_k, cos_i), g.math('SUBTRACT', c_k, c_k1), clamp=True)
        if P > 1:
            start = g.dot(head, Z)
            s = g.math('DIVIDE', g.math('SUBTRACT', x, start), g.math('SUBTRACT', head_a, start), clamp=True)
        if lay["NB"] == 2:
            w0 = g.math('SUBTRACT', 1.0, t)
            self.weights = [(g.combine(w0, t), None), (g.combine(0.0, 0.0, w0), t)]
        else:
            t1, s1 = g.math('SUBTRACT', 1.0, t), g.math('SUBTRACT', 1.0, s)
            self.weights = [(g.combine(g.math('MULTIPLY', t1, s1), g.math('MULTIPLY', t, s1), g.math('MULTIPLY', t1, s)),
                             g.math('MULTIPLY', t, s))]

    def direction(self, a, b, cos_i, phi_i):
        """wo (floats x, y, z in the local frame) at table coordinates (a, b), after `incident`,
        and d omega_o / (da db) (None: 1, the "wo" coordinates; bake/core/tables.py)."""
        g, coords = self.g, self.lay.get("coords", "wo")
        if coords == "wo":
            return _from_ab(g, a, b, phi_i), None
        if coords == "halfpolar":       # the map's frame: wi's turned by pi (phi_i None: wi's frame)
            wo, jac = _polar_from_ab(g, a, b, _polar_wi(g, cos_i))
            return _turn(g, wo, _polar_ref(g, phi_i)), jac
        wo, jac = _half_from_ab(g, a, b, _half_wi(g, cos_i, phi_i, self.ref))
        return _turn(g, wo, self.ref), jac

    def coordinates(self, wo, cos_i, phi_i):
        """(a, b, d omega_o / (da db) or None) of a local direction wo, after `incident`."""
        g, coords = self.g, self.lay.get("coords", "wo")
        if coords == "wo":
            return _to_ab(g, wo, phi_i) + (None,)
        if coords == "halfpolar":
            return _polar_to_ab(g, _turn(g, wo, g.math('MULTIPLY', _polar_ref(g, phi_i), -1.0)), _polar_wi(g, cos_i))
        return _half_to_ab(g, _turn(g, wo, g.math('MULTIPLY', self.ref, -1.0)),
                           _half_wi(g, cos_i, phi_i, self.ref))

    def rows(self):
        return self.offset(self.origin, self.lay["x_row"])

    def row(self, i):
        """Texel (0, 1 + i) of the block: table row i's guide, then its records."""
        x, y = self.offset(self.origin, 0, 1)
        return x, self.g.math('MULTIPLY_ADD', i, -self.dv, y)

    def cell(self, row, j):
        """Cell j of the blended table's row at texel `row` (self.row): a function giving its
        quantity n (svm_export.CELL_QUANTITIES: mass, the a and b profiles' node values, W), each
        read where it is first needed, so few values are alive at once (the SVM stack)."""
        cell = self.at(self.offset(row, self.lay["x_cell"]), j, self.lay["cell_stride"])
        return lambda n: self.quantity(cell, n)

    def sample(self, u0, u1):
        """Tables.sample after `incident`: (a, b, weight W (colour), pdf) for sockets u0, u1."""
        g, lay = self.g, self.lay
        sr, sc = lay["row_stride"], lay["col_stride"]
        # row i: the last with CDF(i) <= u0
        rows = self.rows()
        i = self.search(self.guide_lo(self.offset(self.origin, 1), u0, lay["row_guide"]), u0, rows, sr,
                        lay["row_steps"], 0, self.last[0])
        rec = self.at(rows, i, sr)
        rec1 = self.offset(rec, sr)
        c0, a0, c1, a1 = (self.quantity(r, q) for r, q in ((rec, 0), (rec, 1), (rec1, 0), (rec1, 1)))
        v = g.math('MULTIPLY', u1, g.math('SUBTRACT', c1, c0))
        # column j of row i: the last with cumsum(i, j) <= v
        row = self.row(i)
        cols = self.offset(row, lay["x_col"])
        j = self.search(self.guide_lo(row, u1, lay["col_guide"]), v, cols, sc, lay["col_steps"], 0, self.last[1])
        rec = self.at(cols, j, sc)
        d0, b0, b1 = self.quantity(rec, 0), self.quantity(rec, 1), self.quantity(self.offset(rec, sc), 1)
        q = self.cell(row, j)
        m = q(0)
        # the point in the cell, and its density along each axis
        x, dens_a = _profile_sample(g, g.math('DIVIDE', g.math('SUBTRACT', u0, c0), g.math('SUBTRACT', c1, c0),
                                              clamp=True), _profile(g, [q(n) for n in self.on_a]))
        a = g.math('MULTIPLY_ADD', x, g.math('SUBTRACT', a1, a0), a0)
        y, dens_b = _profile_sample(g, g.math('DIVIDE', g.math('SUBTRACT', v, d0), m, clamp=True),
                                    _profile(g, [q(n) for n in self.on_b]))
        db = g.math('SUBTRACT', b1, b0)
        b = g.math('MULTIPLY_ADD', y, db, b0)
        pdf = g.math('DIVIDE', g.math('MULTIPLY', m, g.math('MULTIPLY', dens_a, dens_b)),
                     g.math('MULTIPLY', g.math('SUBTRACT', a1, a0), db))
        return a, b, g.combine(*(q(n) for n in self.on_w)), pdf

    def locate(self, a, b):
        """Tables._locate after `incident`: (pdf, W (colour)) at table coordinates a, b."""
        g, lay = self.g, self.lay
        R, C, sr, sc = lay["R"], lay["C"], lay["row_stride"], lay["col_stride"]
        rows = self.rows()
        i = self.search(0.0, a, rows, sr, _log2(R), 1, self.last[0])
        rec = self.at(rows, i, sr)
        a0, a1 = self.quantity(rec, 1), self.quantity(self.offset(rec, sr), 1)
        row = self.row(i)
        cols = self.offset(row, lay["x_col"])
        j = self.search(0.0, b, cols, sc, _log2(C), 1, self.last[1])
        rec = self.at(cols, j, sc)
        b0, b1 = self.quantity(rec, 1), self.quantity(self.offset(rec, sc), 1)
        q = self.cell(row, j)
        da, db = g.math('SUBTRACT', a1, a0), g.math('SUBTRACT', b1, b0)
        dens_a = _profile_density(g, g.math('DIVIDE', g.math('SUBTRACT', a, a0), da, clamp=True),
                                  _profile(g, [q(n) for n in self.on_a]))
        dens_b = _profile_density(g, g.math('DIVIDE', g.math('SUBTRACT', b, b0), db, clamp=True),
                                  _profile(g, [q(n) for n in self.on_b]))
        pdf = g.math('DIVIDE', g.math('MULTIPLY', q(0), g.math('MULTIPLY', dens_a, dens_b)), g.math('MULTIPLY', da, db))
        return pdf, g.combine(*(q(n) for n in self.on_w))


def _log2(n):
    """Binary search steps over n entries."""
    return max(int(n - 1).bit_length(), 0)


def _from_ab(g, a, b, phi_i):
    """bake/core/tables.py from_ab: wo (floats x, y, z) in the local frame, where wi has azimuth phi_i
    (None: 0, the isotropic frame that follows wi)."""
    sin_o = g.math('SQRT', g.math('MULTIPLY', a, g.math('SUBTRACT', 2.0, a)))
    phi_o = g.math('ADD', b, phi_i) if phi_i is not None else b
    return (g.math('MULTIPLY', sin_o, g.math('COSINE', phi_o)), g.math('MULTIPLY', sin_o, g.math('SINE', phi_o)),
            g.math('SUBTRACT', 1.0, a))


def _to_ab(g, wo, phi_i):
    """bake/core/tables.py to_ab (phi_ref = phi_i + pi) of a local direction (floats x, y, z)."""
    x, y, z = wo
    a = g.math('DIVIDE', g.math('ADD', g.math('MULTIPLY', x, x), g.math('MULTIPLY', y, y)),
               g.math('ADD', g.math('MAXIMUM', z, 0.0), 1.0))
    a = g.select(g.math('GREATER_THAN', z, 0.0), g.math('MINIMUM', a, 1.0), 1.0)
    azimuth = g.math('ARCTAN2', y, x)
    if phi_i is not None:
        azimuth = g.math('SUBTRACT', azimuth, phi_i)
    return a, g.math('FLOORED_MODULO', azimuth, 2.0 * math.pi)


def _turn(g, w, angle):
    """Floats (x, y, z) turned about z by the socket `angle`."""
    c, s = g.math('COSINE', angle), g.math('SINE', angle)
    return (g.math('SUBTRACT', g.math('MULTIPLY', c, w[0]), g.math('MULTIPLY', s, w[1])),
            g.math('MULTIPLY_ADD', s, w[0], g.math('MULTIPLY', c, w[1])), w[2])


def _half_wi(g, cos_i, phi_i, ref):
    """wi in the halfvector map's frame (turned by `ref` from the local one)."""
    sin_i = g.math('SQRT', g.math('MAXIMUM', g.math('MULTIPLY_ADD', cos_i, g.math('MULTIPLY', cos_i, -1.0), 1.0), 0.0))
    rel = g.math('SUBTRACT', phi_i, ref)
    return (g.math('MULTIPLY', sin_i, g.math('COSINE', rel)), g.math('MULTIPLY', sin_i, g.math('SINE', rel)), cos_i)


def _half_cap(g, wi, cos_h, sin_h):
    """bake/core/halfvector.py _cap: 1 - cos theta_max at the azimuth (cos_h, sin_h) of h."""
    along = g.math('MULTIPLY_ADD', wi[0], cos_h, g.math('MULTIPLY', wi[1], sin_h))
    half = g.math('SINE', g.math('MULTIPLY', g.math('ARCTAN2', wi[2], g.math('MULTIPLY', along, -1.0)), 0.25))
    return g.math('MAXIMUM', g.math('MULTIPLY', g.math('MULTIPLY', half, half), 2.0), 1e-30)


def _mirror(g, wi, h, cap):
    """(wo floats, jac) of half vector h at wi: wo = 2 (wi.h) h - wi (z at least 0), jac =
    4 (wi.h) cap, as halfvector.py's maps end."""
    cos_ih = g.dot(g.combine(*wi), g.combine(*h))
    twice = g.math('MULTIPLY', cos_ih, 2.0)
    wo = tuple(g.math('MULTIPLY_ADD', twice, hc, g.math('MULTIPLY', wc, -1.0)) for hc, wc in zip(h, wi))
    return (wo[0], wo[1], g.math('MAXIMUM', wo[2], 0.0)), g.math('MULTIPLY', g.math('MULTIPLY', cos_ih, cap), 4.0)


def _h_at(g, one_minus_cos, cos_h, sin_h):
    """h (floats) of 1 - cos theta_h and the cosine and sine of phi_h."""
    sin_t = g.math('SQRT', g.math('MAXIMUM', g.math('MULTIPLY', one_minus_cos,
                                                     g.math('SUBTRACT', 2.0, one_minus_cos)), 0.0))
    return g.math('MULTIPLY', sin_t, cos_h), g.math('MULTIPLY', sin_t, sin_h), g.math('SUBTRACT', 1.0, one_minus_cos)


def _half_from_ab(g, a, b, wi):
    """bake/core/halfvector.py from_ab: (wo floats in the map's frame, jac)."""
    x, y = g.math('MULTIPLY_ADD', a, 2.0, -1.0), g.math('MULTIPLY_ADD', b, 1.0 / math.pi, -1.0)
    wide = g.math('GREATER_THAN', g.math('ABSOLUTE', x), g.math('ABSOLUTE', y))    # ties: either way
    r = g.select(wide, x, y)
    ratio = g.math('DIVIDE', g.select(wide, y, x), r)              # Blender's divide: 0 at r = 0
    angle = g.select(wide, g.math('MULTIPLY', ratio, math.pi / 4),
                     g.math('MULTIPLY_ADD', ratio, -math.pi / 4, math.pi / 2))
    u, v = g.math('MULTIPLY', r, g.math('COSINE', angle)), g.math('MULTIPLY', r, g.math('SINE', angle))
    phi_h = g.math('ARCTAN2', v, u)
    cos_h, sin_h = g.math('COSINE', phi_h), g.math('SINE', phi_h)
    cap = _half_cap(g, wi, cos_h, sin_h)
    one_minus_cos = g.math('MULTIPLY', g.math('MULTIPLY_ADD', u, u, g.math('MULTIPLY', v, v)), cap)
    return _mirror(g, wi, _h_at(g, one_minus_cos, cos_h, sin_h), cap)


def _polar_wi(g, cos_i):
    """wi in the halfpolar map's frame, turned by phi_i + pi: (-sin theta_i, 0, cos theta_i)."""
    sin_i = g.math('SQRT', g.math('MAXIMUM', g.math('MULTIPLY_ADD', cos_i, g.math('MULTIPLY', cos_i, -1.0), 1.0), 0.0))
    return g.math('MULTIPLY', sin_i, -1.0), 0.0, cos_i


def _polar_ref(g, phi_i):
    """The halfpolar map's frame angle, phi_i + pi (phi_i None: wi's frame)."""
    return math.pi if phi_i is None else g.math('ADD', phi_i, math.pi)


def _polar_from_ab(g, a, b, wi):
    """bake/core/halfvector.py polar_from_ab: (wo floats in the map's frame, jac)."""
    cos_h, sin_h = g.math('COSINE', b), g.math('SINE', b)
    cap = _half_cap(g, wi, cos_h, sin_h)
    return _mirror(g, wi, _h_at(g, g.math('MULTIPLY', a, cap), cos_h, sin_h), cap)


def _polar_to_ab(g, wo, wi):
    """bake/core/halfvector.py polar_to_ab: (a, b, jac) of wo (floats in the map's frame)."""
    h = g.vmath('NORMALIZE', g.vmath('ADD', g.combine(*wi), g.combine(*wo)))
    hx, hy, hz = (g.dot(h, axis) for axis in (X, Y, Z))
    b = g.math('FLOORED_MODULO', g.math('ARCTAN2', hy, hx), 2.0 * math.pi)
    cap = _half_cap(g, wi, g.math('COSINE', b), g.math('SINE', b))
    flat = g.math('DIVIDE', g.math('MULTIPLY_ADD', hx, hx, g.math('MULTIPLY', hy, hy)), g.math('ADD', hz, 1.0))
    a = g.math('DIVIDE', flat, cap, clamp=True)
    return a, b, g.math('MULTIPLY', g.math('MULTIPLY', g.dot(g.combine(*wi), h), cap), 4.0)


def _half_to_ab(g, wo, wi):
    """bake/core/halfvector.py to_ab: (a, b, jac) of wo (floats in the map's frame)."""
    h = g.vmath('NORMALIZE', g.vmath('ADD', g.combine(*wi), g.combine(*wo)))
    hx, hy, hz = (g.dot(h, axis) for axis in (X, Y, Z))
    phi_h = g.math('ARCTAN2', hy, hx)
    cos_h, sin_h = g.math('COSINE', phi_h), g.math('SINE', phi_h)
    cap = _half_cap(g, wi, cos_h, sin_h)
    flat = g.math('DIVIDE', g.math('MULTIPLY_ADD', hx, hx, g.math('MULTIPLY', hy, hy)), g.math('ADD', hz, 1.0))
    radius = g.math('SQRT', g.math('DIVIDE', flat, cap), clamp=True)
    u, v = g.math('MULTIPLY', radius, cos_h), g.math('MULTIPLY', radius, sin_h)
    wide = g.math('GREATER_THAN', g.math('ABSOLUTE', u), g.math('ABSOLUTE', v))
    major = g.select(wide, u, v)                     # r = sign(major) radius, the other by its angle
    r = g.math('MULTIPLY', g.math('SIGN', major), radius)
    other = g.math('DIVIDE', g.math('MULTIPLY', r, g.math('ARCTANGENT', g.math('DIVIDE', g.select(wide, v, u), major))),
                   math.pi / 4)
    x, y = g.select(wide, r, other), g.select(wide, other, r)
    a = g.math('MULTIPLY_ADD', x, 0.5, 0.5, clamp=True)
    b = g.math('MINIMUM', g.math('MAXIMUM', g.math('MULTIPLY_ADD', y, math.pi, math.pi), 0.0), 2.0 * math.pi)
    return a, b, g.math('MULTIPLY', g.math('MULTIPLY', g.dot(g.combine(*wi), h), cap), 4.0)


def _log_mean(g, v0, v1):
    """bake/core/tables.py _log_mean: (v1 - v0) / log(v1 / v0), its series where they are close;
    and log(v1 / v0) (the piece's rate)."""
    r = g.math('DIVIDE', v1, v0)
    lr = g.math('LOGARITHM', r, math.e)
    small = g.math('LESS_THAN', g.math('ABSOLUTE', lr), LOG_MEAN_SERIES)
    exact = g.math('MULTIPLY', v0, g.math('DIVIDE', g.math('SUBTRACT', r, 1.0), lr))
    series = g.math('MULTIPLY_ADD', lr, g.math('MULTIPLY_ADD', lr, 1.0 / 6.0, 0.5), 1.0)
    return g.select(small, g.math('MULTIPLY', v0, series), exact), lr


def _profile(g, nodes):
    """A cell's blended profile along one axis: its node values, the pieces' masses and their
    total (bake/core/tables.py profile_parts), and the pieces' log rates."""
    n = len(nodes) - 1
    means, rates = zip(*(_log_mean(g, nodes[k], nodes[k + 1]) for k in range(n)))
    masses = [g.math('MULTIPLY', mean, 1.0 / n) for mean in means]
    total = masses[0]
    for mk in masses[1:]:
        total = g.math('ADD', total, mk)
    return nodes, masses, total, rates


def _pick(g, steps, values):
    """values[k] for k = the number of the 0 / 1 sockets `steps` that are 1 (a prefix of them)."""
    out = values[0]
    for step, value in zip(steps, values[1:]):
        out = g.select(step, value, out)
    return out


def _profile_piece(g, steps, nodes, rates):
    """The piece's start value and its log rate (the one _profile computed: the same value as
    log(v1 / v0) of the picked end values, without a second logarithm)."""
    return _pick(g, steps, nodes[:-1]), _pick(g, steps, rates)


def _profile_sample(g, u, profile):
    """bake/core/tables.py profile_sample: the place of u and the profile's density there (from
    the piece found: its start value, rate and place t)."""
    nodes, masses, total, rates = profile
    n = len(masses)
    target = g.math('MULTIPLY', u, total)
    cum, steps = [], []
    c = masses[0]
    for k in range(1, n):
        cum.append(c)
        steps.append(g.math('SUBTRACT', 1.0, g.math('LESS_THAN', target, c)))      # cum_k <= target
        c = g.math('ADD', c, masses[k])
    prev = _pick(g, steps, [0.0] + cum)
    mk = _pick(g, steps, masses)
    v0, rate = _profile_piece(g, steps, nodes, rates)
    t, _ = _exp_inverse_cdf(g, g.math('DIVIDE', g.math('SUBTRACT', target, prev), mk, clamp=True), rate)
    k = steps[0]
    for step in steps[1:]:
        k = g.math('ADD', k, step)
    density = g.math('DIVIDE', g.math('MULTIPLY', v0, g.math('EXPONENT', g.math('MULTIPLY', t, rate))), total)
    return g.math('DIVIDE', g.math('ADD', k, t), float(n)), density


def _profile_density(g, x, profile):
    """bake/core/tables.py profile_density."""
    nodes, masses, total, rates = profile
    n = len(masses)
    s = g.math('MULTIPLY', x, float(n))
    steps = [g.math('SUBTRACT', 1.0, g.math('LESS_THAN', s, float(k))) for k in range(1, n)]
    k = steps[0]
    for step in steps[1:]:
        k = g.math('ADD', k, step)
    t = g.math('SUBTRACT', s, k, clamp=True)
    v0, rate = _profile_piece(g, steps, nodes, rates)
    return g.math('DIVIDE', g.math('MULTIPLY', v0, g.math('EXPONENT', g.math('MULTIPLY', t, rate))), total)


def _expm1(g, k):
    """e^k - 1 to float precision near k = 0: 2 sinh(k / 2) e^(k / 2)."""
    h = g.math('MULTIPLY', k, 0.5)
    return g.math('MULTIPLY', g.math('MULTIPLY', g.math('SINH', h), g.math('EXPONENT', h)), 2.0)


def _log1p(g, z):
    """log(1 + z) to float precision near z = 0: log(w) z / (w - 1) with w = 1 + z, or z
    where w rounds to 1."""
    w = g.math('ADD', z, 1.0)
    d = g.math('SUBTRACT', w, 1.0)
    exact = g.math('LESS_THAN', g.math('ABSOLUTE', d), 1e-30)
    return g.math('MULTIPLY_ADD', exact, z, g.math('MULTIPLY', g.math('LOGARITHM', w, math.e), g.math('DIVIDE', z, d)))


def _small(g, k):
    return g.math('LESS_THAN', g.math('ABSOLUTE', k), K_SMALL)


def _exp_inverse_cdf(g, u, k):
    """bake/core/tables.py exp_inverse_cdf, both branches, one selected; also e^k - 1 (reused)."""
    series = g.math('MULTIPLY_ADD', g.math('MULTIPLY', k, g.math('MULTIPLY', u, g.math('SUBTRACT', 1.0, u))), 0.5, u)
    ex = _expm1(g, k)
    exact = g.math('DIVIDE', _log1p(g, g.math('MULTIPLY', u, ex)), k)
    return g.select(_small(g, k), series, exact, clamp=True), ex


# ------------------------------------------------------------------------------ the world

def _world_map_module():
    import importlib
    from . import deps
    return importlib.import_module(f"{deps.bake.__name__}.export.world_map")


_world_layouts = {}


def world_layout(path):
    """The numbers the graph needs of a world importance map (bake/export/world_map.py's texture): W,
    H (map pixels), Wt, Ht (texture texels), the binary searches' steps over its rows and
    columns, its layout; None when `path` is empty or not a current world map (then the graph
    draws no world-map samples). Read once per file version from the image's pixels (numpy; no
    OpenEXR module needed)."""
    if not path or not os.path.isfile(path):
        return None
    stat = os.stat(path)
    key = (os.path.abspath(path), stat.st_mtime_ns, stat.st_size)
    if key not in _world_layouts:
        _world_layouts[key] = _read_world_layout(path)
    return _world_layouts[key]


def _read_world_layout(path):
    try:
        import numpy as np
        layout = _world_map_module().LAYOUT
        image = _image(path)
        wt, ht = image.size
        px = np.empty(wt * ht * 4, np.float32)
        image.pixels.foreach_get(px)
    except (ImportError, RuntimeError, ValueError):
        return None
    if wt < 2 or ht < 3:
        return None
    px = px.reshape(ht, wt, 4)[::-1]        # Blender's pixels start at the bottom row
    version, w, h = px[0, 0, :3]
    if version != layout or min(w, h) < 1 or ht < 2 + h or wt <= max(w, h):
        return None
    w, h = int(w), int(h)
    return {"W": w, "H": h, "Wt": wt, "Ht": ht, "row_steps": (h - 1).bit_length(), "col_steps": (w - 1).bit_length(),
            "layout": layout}


def _world_texel(g, wl, image, x, row):
    """The colour of the world texture's texel (x, row)."""
    tex = g.node("ShaderNodeTexImage", image=image, interpolation='Closest', extension='EXTEND')
    wt, ht = float(wl["Wt"]), float(wl["Ht"])
    g.set(tex.inputs["Vector"], g.combine(g.math('MULTIPLY_ADD', x, 1.0 / wt, 0.5 / wt),
                                          g.math('MULTIPLY_ADD', row, -1.0 / ht, 1.0 - 0.5 / ht)))
    return tex.outputs["Color"]


def _world_group_name(kind, wl, image):
    return f"{GROUP_PREFIX}world{wl['layout']} {kind}: {image.name}"


def _is_world_group(name, kind):
    """Whether a node group is a world group of this kind (of any map, any layout)."""
    head = name.split(": ")[0]
    return head.startswith(f"{GROUP_PREFIX}world") and head.endswith(f" {kind}")


def _world_group(kind, wl, image, inputs, outputs, build):
    """The node group `kind` of a world texture (its numbers are constants of the group): a new
    map gets new groups, which update_world swaps in."""
    done, tree = _group(_world_group_name(kind, wl, image), inputs, outputs)
    if done:
        return done
    g = _Graph(tree)
    results = build(g, g.node("NodeGroupInput").outputs)
    out = g.node("NodeGroupOutput")
    for name, value in results.items():
        g.set(out.inputs[name], value)
    return tree


def _world_step_group(wl, image):
    """Group "world search step" over a CDF in texture row Row (entries 0 .. Last, the last 1):
    index = Lo + Half; Lo moves there when its entry (past Last: the last, 1) is <= Target."""
    def build(g, inp):
        index = g.math('ADD', inp["Lo"], inp["Half"])
        entry = g.dot(_world_texel(g, wl, image, g.math('MINIMUM', index, inp["Last"]), inp["Row"]), X)
        above = g.math('GREATER_THAN', entry, inp["Target"])
        return {"Lo": g.math('MULTIPLY_ADD', above, g.math('MULTIPLY', inp["Half"], -1.0), index)}
    return _world_group("search step", wl, image, [("Lo", "Float"), ("Target", "Float"), ("Half", "Float"),
                                                   ("Row", "Float"), ("Last", "Float")],
                        [("Lo", "Float")], build)


def _world_search(g, wl, image, u, row, last, steps):
    """(k, cdf_k, cdf_k+1): the last entry k < last of the CDF in texture row `row` with cdf_k <=
    u, found branchlessly in `steps` halvings (2^steps >= last)."""
    lo = 0.0
    for s in reversed(range(steps)):
        lo = g.group(_world_step_group(wl, image), Lo=lo, Target=u, Half=float(2 ** s), Row=row, Last=float(last))[0]
    c0 = g.dot(_world_texel(g, wl, image, lo, row), X)
    c1 = g.dot(_world_texel(g, wl, image, g.math('ADD', lo, 1.0), row), X)
    return lo, c0, c1


def _world_sample_group(wl, image):
    """Group "world sample": world.h sample_world / WorldMap.sample. The pixel's row by the
    rows' marginal CDF (U0), its column by the row's conditional CDF (U1), each searched
    branchlessly; the direction uniform in the pixel's solid angle (z from U0's place in its
    row's share, azimuth from U1's in its pixel's); Pdf is the pixel's density per steradian."""
    def build(g, inp):
        u0, u1 = inp["U0"], inp["U1"]
        w, h = float(wl["W"]), float(wl["H"])
        row, r0, r1 = _world_search(g, wl, image, u0, 1.0, wl["H"], wl["row_steps"])
        cond_row = g.math('ADD', row, 2.0)
        col, c0, c1 = _world_search(g, wl, image, u1, cond_row, wl["W"], wl["col_steps"])
        t_row = g.math('DIVIDE', g.math('SUBTRACT', u0, r0), g.math('SUBTRACT', r1, r0), clamp=True)
        t_col = g.math('DIVIDE', g.math('SUBTRACT', u1, c0), g.math('SUBTRACT', c1, c0), clamp=True)
        z0 = g.math('COSINE', g.math('MULTIPLY', row, math.pi / h))
        z1 = g.math('COSINE', g.math('MULTIPLY_ADD', row, math.pi / h, math.pi / h))
        z = g.math('MULTIPLY_ADD', t_row, g.math('SUBTRACT', z1, z0), z0)
        phi = g.math('MULTIPLY_ADD', g.math('ADD', col, t_col), -2.0 * math.pi / w, math.pi)
        s = g.math('SQRT', g.math('MAXIMUM', g.math('SUBTRACT', 1.0, g.math('MULTIPLY', z, z)), 0.0))
        direction = g.combine(g.math('MULTIPLY', s, g.math('COSINE', phi)), g.math('MULTIPLY', s, g.math('SINE', phi)),
                              z)
        return {"Direction": direction, "Pdf": g.dot(_world_texel(g, wl, image, col, cond_row), Y)}
    return _world_group("sample", wl, image, [("U0", "Float"), ("U1", "Float")],
                        [("Direction", "Vector"), ("Pdf", "Float")], build)


def _world_pdf_group(wl, image):
    """Group "world pdf": world.h pdf_world / WorldMap.pdf, the density per steradian of the
    map's sampling at a unit Direction (its pixel's)."""
    def build(g, inp):
        d = inp["Direction"]
        w, h = float(wl["W"]), float(wl["H"])
        theta = g.math('ARCCOSINE', g.dot(d, Z))            # (Cycles' acos clamps its argument)
        row = g.math('MINIMUM', g.math('FLOOR', g.math('MULTIPLY', theta, h / math.pi)), h - 1.0)
        u = g.math('FLOORED_MODULO', g.math('MULTIPLY_ADD', g.math('ARCTAN2', g.dot(d, Y), g.dot(d, X)),
                                            -0.5 / math.pi, 0.5), 1.0)
        col = g.math('MINIMUM', g.math('FLOOR', g.math('MULTIPLY', u, w)), w - 1.0)
        return {"Pdf": g.dot(_world_texel(g, wl, image, col, g.math('ADD', row, 2.0)), Y)}
    return _world_group("pdf", wl, image, [("Direction", "Vector")], [("Pdf", "Float")], build)


_WORLD_GROUPS = {"sample": _world_sample_group, "pdf": _world_pdf_group}


def _tables_group(sampler, kind, inputs, outputs, build):
    """Group "tables <kind>" of a sampler's texture, inputs Cos I (clamped to >= 0), Phi I
    (anisotropic tables) and `inputs`; build(g, sampler in the group, group inputs, cos_i,
    phi_i) -> {output: socket}. (A group: every node added to a tree costs in proportion to
    the tree's size (_Graph), and a material rebuilt on the same texture reuses it.)"""
    phi = [("Phi I", "Float")] if sampler.lay["P"] > 1 else []
    done, tree = _group(f"{GROUP_PREFIX}tables {kind}: {sampler.image.name}", [("Cos I", "Float")] + phi + inputs,
                        outputs)
    if done:
        return done
    g = _Graph(tree)
    inp = g.node("NodeGroupInput").outputs
    values = build(g, _Sampler(g, sampler.path, sampler.lay), inp, inp["Cos I"], inp["Phi I"] if phi else None)
    out = g.node("NodeGroupOutput")
    for name, value in values.items():
        g.set(out.inputs[name], value)
    return tree


def _tables_call(g, sampler, kind, cos_i, phi_i, **inputs):
    """The outputs of the group `kind` (_TABLES_GROUPS) of the sampler's texture at these inputs."""
    if phi_i is not None:
        inputs["Phi I"] = phi_i
    inputs_, outputs, build = _TABLES_GROUPS[kind]
    return g.group(_tables_group(sampler, kind, inputs_, outputs, build), **{"Cos I": cos_i}, **inputs)


def _pdf_in_group(g, inner, inp, cos_i, phi_i):
    pdf, fcos = _inverse(g, inner, cos_i, phi_i, (inp["X"], inp["Y"], inp["Z"]))
    return {"Pdf": pdf, "F cos": fcos}


def _sample_in_group(g, inner, inp, cos_i, phi_i):
    inner.incident(cos_i, phi_i)
    a, b, weight, pdf = inner.sample(inp["U0"], inp["U1"])
    wo, jac = inner.direction(a, b, cos_i, phi_i)
    if jac is not None:
        pdf = g.math('DIVIDE', pdf, jac)
    return {"X": wo[0], "Y": wo[1], "Z": wo[2], "Weight": weight, "Pdf": pdf}


# The per-texture groups: "pdf", _inverse's pdf and f·cos at the local direction (X, Y, Z);
# "sample", Tables.sample at U0, U1: the local direction, the weight W and the pdf per steradian.
_TABLES_GROUPS = {
    "pdf": ([("X", "Float"), ("Y", "Float"), ("Z", "Float")], [("Pdf", "Float"), ("F cos", "Vector")],
            _pdf_in_group),
    "sample": ([("U0", "Float"), ("U1", "Float")],
               [("X", "Float"), ("Y", "Float"), ("Z", "Float"), ("Weight", "Vector"), ("Pdf", "Float")],
               _sample_in_group),
}


def _tables_sample(g, sampler, cos_i, phi_i, u0, u1):
    """(local direction (x, y, z), W, pdf per steradian) of the tables' sample at u0, u1."""
    out = _tables_call(g, sampler, "sample", cos_i, phi_i, U0=u0, U1=u1)
    return (out["X"], out["Y"], out["Z"]), out["Weight"], out["Pdf"]


class _Mixture:
    """The portal direction's mixture (module docstring) for the world inputs `world`
    (blender_addon/world.shader_inputs): which techniques the graph has, its value nodes, and
    its branches. False when it has none (then the graph is the tables' alone)."""

    def __init__(self, world):
        world = dict(world or {})
        self.inputs = world
        self.path = str(world.get("World") or "")
        self.map = world_layout(self.path) if world.get("WorldShare", 0.0) > 0.0 else None
        self.sun = bool(world.get("SunShare", 0.0) > 0.0 and world.get("SunCos", 1.0) < 1.0)
        self.lamps = int(world.get("Lamps", 0)) if world.get("LampShare", 0.0) > 0.0 else 0
        self.light = _light_direction(world)
        # no small light in the world: the control variate is matched to the lamp that lights
        # the shading point most
        self.match_lamp = self.light is None and self.lamps > 0
        self._lamp_nodes = self._lamp_data = None

    def light_axis(self, g, at):
        """The small light's direction at the shading point: the world's (LightDirection, from
        its named node: update_world) or the brightest lamp's there."""
        if self.match_lamp:
            return self.lamp_data(g, at)["axis"]
        node = g.node("ShaderNodeCombineXYZ", name=LIGHT, label=LIGHT)
        for socket, value in zip(node.inputs, self.light):
            socket.default_value = value
        return g.vmath('NORMALIZE', node.outputs[0])

    def __bool__(self):
        return self.map is not None or self.sun or self.lamps > 0

    def lamp_nodes(self, g):
        """Per lamp technique its two named nodes' outputs (lamps.bind_svm drives them): place (a
        sun's direction) and (radius or a sun's angle, power, 1 for a sun)."""
        if self._lamp_nodes is None:
            self._lamp_nodes = []
            for k in range(self.lamps):
                where = g.node("ShaderNodeCombineXYZ", name=f"{LAMP} {k}", label=f"{LAMP} {k}")
                size = g.node("ShaderNodeCombineXYZ", name=f"{LAMP} {k} size", label=f"{LAMP} {k} size")
                where["flowbsdf_lamp"], size["flowbsdf_lamp_size"] = k, k
                self._lamp_nodes.append((where.outputs[0], size.outputs[0]))
        return self._lamp_nodes

    def lamp_cone(self, g, p, where, size):
        """A lamp technique's cone at the shading point p (its axis unnormalised, "to"; 1 - cos of
        its half angle) about the lamp's bounding sphere (a sun lamp: about its direction, of its
        angle), and the weight that shares the lamps' draws (~ irradiance: power / distance^2, a
        sun's strength)."""
        radius, power, is_sun = (g.dot(size, axis) for axis in (X, Y, Z))
        to = g.vmath('SUBTRACT', where, g.scale(p, g.math('SUBTRACT', 1.0, is_sun)))
        d2 = g.math('MAXIMUM', g.dot(to, to), g.math('MULTIPLY', radius, radius))
        s2 = g.math('MINIMUM', g.math('DIVIDE', g.math('MULTIPLY', radius, radius), d2), 1.0)
        # 1 - cos without cancellation: sin^2 / (1 + cos) for a sphere, 2 sin^2(angle / 4) for a sun
        sphere = g.math('DIVIDE', s2, g.math('ADD', 1.0, g.math('SQRT', g.math('SUBTRACT', 1.0, s2))))
        half = g.math('SINE', g.math('MULTIPLY', radius, 0.25))
        omc = g.select(is_sun, g.math('MULTIPLY', g.math('MULTIPLY', half, half), 2.0), sphere)
        return {"to": to, "omc": omc,
                "weight": g.select(is_sun, power, g.math('DIVIDE', power, d2))}

    def lamp_data(self, g, at):
        """Before the branches: the lamps' total weight, the largest, the brightest lamp's axis
        (the matched control variate's) and (values) the lamps' share c_lamp."""
        if self._lamp_data is None:
            total = best = to = None
            for where, size in self.lamp_nodes(g):
                cone = self.lamp_cone(g, at["p"], where, size)
                if total is None:
                    total, best, to = cone["weight"], cone["weight"], cone["to"]
                    continue
                total = g.math('ADD', total, cone["weight"])
                better = g.math('GREATER_THAN', cone["weight"], best)
                to = g.vmath('MULTIPLY_ADD', cone["to"], g.combine(better, better, better),
                             g.scale(to, g.math('SUBTRACT', 1.0, better)))
                best = g.math('MAXIMUM', best, cone["weight"])
            # (normalised once, as picked: the same axis as the brightest lamp's own cone has)
            self._lamp_data = {"total": total, "best": best, "axis": g.vmath('NORMALIZE', to) if self.match_lamp else None}
        return self._lamp_data

    def lamp_stream(self, g, at, tag):
        """Each lamp's cone at the shading point with its share c_k ("c": LampShare x its weight /
        the total, the matched lamp's x scale) and "cone" (c_k p_k inside the cone), one lamp at
        a time (a generator: a caller that folds them in keeps one lamp's values alive, not all),
        from a position through a no-op of its own (`tag`): values the branches shared Cycles
        would compute before them and hold on its stack through all (measured: 4 lamps so took
        28 of its 255 floats)."""
        p = g.vmath('MAXIMUM', at["p"], (-1e30 * tag,) * 3)
        data = self._lamp_data
        share = g.math('DIVIDE', self.lamp_share, data["total"])
        for where, size in self.lamp_nodes(g):
            cone = self.lamp_cone(g, p, where, size)
            cone["axis"] = g.vmath('NORMALIZE', cone["to"])
            c = g.math('MULTIPLY', cone["weight"], share)
            if self.match_lamp and self.scale is not None:   # the brightest lamp's draws scaled
                top = g.math('SUBTRACT', 1.0, g.math('LESS_THAN', cone["weight"], data["best"]))
                c = g.math('MULTIPLY', c, g.math('MULTIPLY_ADD', top, g.math('SUBTRACT', self.scale, 1.0), 1.0))
            cone["c"] = c
            cone["cone"] = g.math('DIVIDE', c, g.math('MULTIPLY', cone["omc"], 2.0 * math.pi))
            yield cone

    def values(self, g, at, scale=None):
        """The named nodes the add-on changes (update_world) and the shares, sun axis and cones
        from them (constants to Cycles: it folds them; a lamp's share varies over the surface).
        `scale`: a matched control variate's points (1 elsewhere): fewer draws of the matched
        light, whose part of the rest is ~0."""
        node = g.node("ShaderNodeCombineXYZ", name=WORLD, label=WORLD)
        node["flowbsdf_map"] = self.path if self.map else ""
        node["flowbsdf_sun"] = int(self.sun)
        node["flowbsdf_lamps"] = self.lamps
        for socket, value in zip(node.inputs, _world_values(self.inputs, self.map is not None, self.sun)):
            socket.default_value = value
        shares = node.outputs[0]
        self.scale = scale
        if scale is not None and not self.match_lamp:
            shares = g.vmath('MULTIPLY', shares, g.combine(scale, scale, 1.0))
        rest = 1.0
        if self.lamps:
            value = g.node("ShaderNodeValue", name=LAMPS, label=LAMPS)
            value.outputs[0].default_value = float(self.inputs.get("LampShare", 0.0))
            self.lamp_share = value.outputs[0]
            data = self.lamp_data(g, at)
            self.c_lamp = self.lamp_share
            if self.match_lamp and scale is not None:       # LampShare (total - (1 - scale) best) / total
                self.c_lamp = g.math('MULTIPLY', self.lamp_share, g.math('SUBTRACT', 1.0, g.math(
                    'DIVIDE', g.math('MULTIPLY', g.math('SUBTRACT', 1.0, scale), data["best"]), data["total"])))
            rest = g.math('SUBTRACT', 1.0, self.c_lamp)
        # the world's techniques share what the lamps leave
        self.c_world = (g.math('MULTIPLY', g.dot(shares, X), rest) if self.lamps else g.dot(shares, X)) if self.map else 0.0
        self.c_sun = 0.0
        if self.sun:
            sun = g.node("ShaderNodeCombineXYZ", name=SUN, label=SUN)
            for socket, value in zip(sun.inputs, self.inputs["SunDirection"]):
                socket.default_value = value
            self.sun_cos = g.dot(shares, Z)
            self.c_sun = g.math('MULTIPLY', g.dot(shares, Y), g.math('LESS_THAN', self.sun_cos, 1.0))
            if self.lamps:
                self.c_sun = g.math('MULTIPLY', self.c_sun, rest)
            self.axis = g.vmath('NORMALIZE', sun.outputs[0])
            self.omc = g.math('SUBTRACT', 1.0, self.sun_cos)
            # c_sun p_cone inside the cone (0 for c_sun = 0: Cycles' divide by 0 gives 0)
            self.cone = g.math('DIVIDE', self.c_sun, g.math('MULTIPLY', self.omc, 2.0 * math.pi))
        self.c_light = g.math('ADD', self.c_sun, self.c_world)
        if self.lamps:
            self.c_light = g.math('ADD', self.c_light, self.c_lamp)
        self.c_tables = g.math('SUBTRACT', 1.0, self.c_light)

    @staticmethod
    def sample_cone(g, axis, omc, u0, u1):
        """lamps.h cone_direction: uniform in the cone about `axis` of 1 - cos its half angle
        `omc` (1 - cos computed as t (2 - t))."""
        near_x = g.math('SUBTRACT', 1.0, g.math('LESS_THAN', g.math('ABSOLUTE', g.dot(axis, X)), 0.9))
        tx = g.vmath('NORMALIZE', g.vmath('CROSS_PRODUCT', axis, g.combine(g.math('SUBTRACT', 1.0, near_x), near_x)))
        ty = g.vmath('CROSS_PRODUCT', axis, tx)
        t = g.math('MULTIPLY', u0, omc)
        s = g.math('SQRT', g.math('MULTIPLY', t, g.math('SUBTRACT', 2.0, t)))
        phi = g.math('MULTIPLY', u1, 2.0 * math.pi)
        d = g.vmath('ADD', g.vmath('ADD', g.scale(tx, g.math('MULTIPLY', s, g.math('COSINE', phi))),
                                   g.scale(ty, g.math('MULTIPLY', s, g.math('SINE', phi)))),
                    g.scale(axis, g.math('SUBTRACT', 1.0, t)))
        return g.vmath('NORMALIZE', d)

    def light_pdf(self, g, d, own, at=None, tag=0, drawn=None, lamps=None):
        """c_world p_world(d) + c_sun p_cone(d) + the lamps' c_k p_k(d) (`lamps`, or lamp_stream
        with `tag` at `at`), the technique `own` left out (its caller adds its own sample's
        density); in the lamps' branch the lamp of index `drawn` counts as inside its cone."""
        total = None

        def add(term):
            nonlocal total
            total = term if total is None else g.math('ADD', total, term)
        if self.map and own != "world":
            add(g.math('MULTIPLY', self.c_world, g.group(self.pdf_group(), Direction=d)[0]))
        if self.sun and own != "sun":
            add(g.math('MULTIPLY', self.cone, g.math('SUBTRACT', 1.0, g.math('LESS_THAN', g.dot(d, self.axis),
                                                                               self.sun_cos))))
        for k, lamp in enumerate(lamps if lamps is not None else self.lamp_stream(g, at, tag) if self.lamps else ()):
            # inside the cone: 1 - cos = |d - axis|^2 / 2 (no cancellation for small cones)
            gap = g.vmath('DISTANCE', d, lamp["axis"])
            inside = g.math('LESS_THAN', g.math('MULTIPLY', g.math('MULTIPLY', gap, gap), 0.5), lamp["omc"])
            if drawn is not None:
                inside = g.math('MAXIMUM', inside, g.math('COMPARE', drawn, float(k), 0.25))
            add(g.math('MULTIPLY', lamp["cone"], inside))
        return 0.0 if total is None else total

    def pdf_group(self):
        return _world_pdf_group(self.map, _image(self.path))

    def graph(self, g, sampler, at, closure, scale=None):
        """The mixture's shader: a branch per technique ending in closure(dict of direction,
        weight, q (the mixture's pdf), technique (0 tables, 1 map, 2 sun, 3 + k lamp k), ok (1
        when the direction counts)), chosen by u1 through Mix Shaders whose factor is exactly 0
        or 1 (Cycles skips the nodes of the branch not taken: svm.cpp generate_multi_closure):
        u1 in [0, c_sun) the sun, then the map, then the lamps (one branch: a branch per lamp
        took 7 more of Cycles' 255 stack floats per lamp), the rest the tables."""
        self.values(g, at, scale)
        u1 = at["u1"]
        techniques = ([("sun", self.c_sun)] if self.sun else []) + ([("world", self.c_world)] if self.map else []) \
            + ([("lamps", self.c_lamp)] if self.lamps else [])
        branches, start = [], 0.0
        for kind, share in techniques:
            end = g.math('ADD', start, share) if start != 0.0 else share
            branches.append((end, self.light_branch(g, sampler, at, kind, start, share, closure)))
            start = end
        out = self.tables_branch(g, sampler, at, closure)
        for end, branch in reversed(branches):
            out = _mix_shader(g, g.math('LESS_THAN', u1, end), out, branch)
        return out

    def tables_branch(self, g, sampler, at, closure):
        t1 = g.math('MINIMUM', g.math('DIVIDE', g.math('SUBTRACT', at["u1"], self.c_light), self.c_tables),
                    1.0 - 2.0 ** -24)
        wo, weight, pdf = _tables_sample(g, sampler, at["cos_i"], at["phi_i"], at["u0"], t1)
        d = _to_world(g, at, wo)
        q = g.math('MULTIPLY_ADD', self.c_tables, pdf, self.light_pdf(g, d, "tables", at, 1))
        ok = _valid(g, at, wo[2], d)
        return closure({"direction": d, "weight": g.scale(weight, g.math('DIVIDE', g.math('MULTIPLY', pdf, ok), q)),
                        "q": q, "technique": 0.0, "ok": ok})

    def light_branch(self, g, sampler, at, kind, start, share, closure):
        u0 = at["u0"]
        u1 = g.math('DIVIDE', g.math('SUBTRACT', at["u1"], start) if start != 0.0 else at["u1"], share)
        drawn = lamps = None
        if kind == "sun":
            d = self.sample_cone(g, self.axis, self.omc, u0, u1)
            own, technique, noop = self.cone, 2.0, -2.0
        elif kind == "world":
            out = g.group(_world_sample_group(self.map, _image(self.path)), U0=u0, U1=u1)
            d, own, technique, noop = out["Direction"], g.math('MULTIPLY', self.c_world, out["Pdf"]), 1.0, -1.0
        else:
            d, drawn, lamps = self.sample_lamps(g, at, u0, u1)
            own, technique, noop = 0.0, g.math('ADD', drawn, 3.0), -3.0
        # the other techniques' density first: the lamps' values (here the drawn ones, not made
        # twice) are then no longer alive while the tables' inverse runs
        light = self.light_pdf(g, d, kind, at, {"sun": 2, "world": 3, "lamps": 4}[kind], drawn, lamps)
        wo = tuple(g.dot(d, axis) for axis in (at["tx"], at["ty"], at["n"]))
        # its own incident nodes (cos theta_i through a no-op unlike the other branches'): Cycles
        # would merge identical ones into nodes run before the branches, their results held
        # on the stack through every branch
        out = _tables_call(g, sampler, "pdf", g.math('MAXIMUM', at["cos_i"], noop), at["phi_i"], X=wo[0], Y=wo[1], Z=wo[2])
        pdf, fcos = out["Pdf"], out["F cos"]
        q = g.math('MULTIPLY_ADD', self.c_tables, pdf, g.math('ADD', own, light) if kind != "lamps" else light)
        ok = _valid(g, at, wo[2], d)
        return closure({"direction": d, "weight": g.scale(fcos, g.math('DIVIDE', ok, q)), "q": q,
                        "technique": technique, "ok": ok})

    def sample_lamps(self, g, at, u0, u1):
        """(direction, index of the lamp drawn, the lamps' values: lamp_stream's): the lamp by u1
        in parts c_k / c_lamp, u1 rescaled within its part, uniform in its cone (picked by flags:
        exact, x 1 and x 0)."""
        lo, axis, omc, v, index = 0.0, (0.0, 0.0, 0.0), 0.0, 0.0, 0.0
        last = self.lamps - 1
        lamps = list(self.lamp_stream(g, at, 5))
        for k, lamp in enumerate(lamps):
            part = g.math('DIVIDE', lamp["c"], self.c_lamp)
            hi = g.math('ADD', lo, part) if k else part
            above = g.math('SUBTRACT', 1.0, g.math('LESS_THAN', u1, lo)) if k else 1.0
            flag = above if k == last else g.math('MULTIPLY', above, g.math('LESS_THAN', u1, hi)) if k else \
                g.math('LESS_THAN', u1, hi)
            within = g.math('DIVIDE', g.math('SUBTRACT', u1, lo) if k else u1, part)
            if not last:
                axis, omc, v = lamp["axis"], lamp["omc"], within
                break
            axis = g.vmath('MULTIPLY_ADD', lamp["axis"], g.combine(flag, flag, flag), axis)
            omc = g.math('MULTIPLY_ADD', lamp["omc"], flag, omc)
            v = g.math('MULTIPLY_ADD', within, flag, v)
            index = g.math('MULTIPLY_ADD', flag, float(k), index)
            lo = hi
        return self.sample_cone(g, axis, omc, u0, g.math('MINIMUM', v, 1.0 - 2.0 ** -24)), index, lamps


def _light_direction(world):
    """The world's small light (LightDirection: a sun, a small sun in the map) or None."""
    d = tuple(float(x) for x in (world or {}).get("LightDirection", (0.0, 0.0, 0.0)))
    return d if any(d) else None


def _matching(mix, matchable):
    """Whether a control variate (with a match image: `matchable`) is matched to the light of
    the mixture `mix` (its world has a small light and something to sample)."""
    return matchable and (mix.light is not None or mix.match_lamp) and bool(mix)


def control_variate_wanted(texture_path, fit):
    """Whether the node's SVM back end hands build_svm_sampler a control variate: isotropic
    tables with a fit (for anisotropic tables the fit is made at phi_i 0 only)."""
    return bool(fit and fit.get("cv")) and _svm_export().read_layout(texture_path)["P"] == 1


def _world_values(world, has_map, has_sun):
    """(WorldShare, SunShare, SunCos) of the world node: 0 for a technique the graph lacks."""
    return (float(world.get("WorldShare", 0.0)) if has_map else 0.0,
            float(world.get("SunShare", 0.0)) if has_sun else 0.0,
            float(world.get("SunCos", 1.0)) if has_sun else 1.0)


def _mix_shader(g, fac, first, second):
    """first where fac is 0, second where it is 1 (a Mix Shader: the other branch is skipped)."""
    node = g.node("ShaderNodeMixShader")
    g.set(node.inputs[0], fac)
    g.set(node.inputs[1], first)
    g.set(node.inputs[2], second)
    return node.outputs[0]


def _to_world(g, at, wo):
    return g.vmath('ADD', g.vmath('ADD', g.scale(at["tx"], wo[0]), g.scale(at["ty"], wo[1])), g.scale(at["n"], wo[2]))


def _valid(g, at, cos_o, d):
    """1 when wi and wo are above the shading surface and d above the geometric one, else 0."""
    return g.math('MULTIPLY', g.math('GREATER_THAN', at["cos_raw"], 0.0),
                  g.math('MULTIPLY', g.math('GREATER_THAN', cos_o, 0.0),
                         g.math('GREATER_THAN', g.dot(d, at["ng"]), 0.0)))


def update_world(tree, world):
    """Hand new world inputs (blender_addon/world.shader_inputs) to the sampler graphs in `tree`
    built with a world: their shares and sun (the named value nodes) and, for a new map, its
    node groups. Returns False when a graph lacks a technique the new inputs use (the map or
    the sun; or `tree` has no world graph and the inputs have a technique): rebuild it then."""
    mix = _Mixture(world)
    for node in tree.nodes:
        if node.name.startswith(CV):
            matched = _matching(mix, bool(node.get("flowbsdf_matchable", 0)))
            if node.get("flowbsdf_light", 0) != int(matched) \
                    or node.get("flowbsdf_match_lamp", 0) != int(matched and mix.match_lamp):
                return False
            sockets.assign(node.outputs[0], _cv_value(world))
        if node.name.startswith(LIGHT) and mix.light is not None:
            for socket, value in zip(node.inputs, mix.light):
                sockets.assign(socket, value)
    nodes = [node for node in tree.nodes if node.name.startswith(WORLD)]
    if not nodes:
        return not mix
    for node in nodes:
        if (mix.map and not node.get("flowbsdf_map")) or (mix.sun and not node.get("flowbsdf_sun")) \
                or mix.lamps > node.get("flowbsdf_lamps", 0):       # (slots it has and the scene leaves empty: power 0)
            return False
    for node in tree.nodes:
        if node.name.startswith(LAMPS) and node.bl_idname == "ShaderNodeValue":
            sockets.assign(node.outputs[0], float(mix.inputs.get("LampShare", 0.0)))
    for node in nodes:
        has_map, has_sun = bool(node.get("flowbsdf_map")), bool(node.get("flowbsdf_sun"))
        for socket, value in zip(node.inputs, _world_values(mix.inputs, has_map and mix.map, has_sun)):
            sockets.assign(socket, value)
        if mix.map and node["flowbsdf_map"] != mix.path:
            node["flowbsdf_map"] = mix.path
    if mix.sun:
        for node in tree.nodes:
            if node.name.startswith(SUN):
                for socket, value in zip(node.inputs, mix.inputs["SunDirection"]):
                    sockets.assign(socket, value)
    if mix.map:
        image, swapped = _image(mix.path), False
        for node in tree.nodes:
            if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
                for kind, build in _WORLD_GROUPS.items():
                    name = node.node_tree.name
                    if _is_world_group(name, kind) and name != _world_group_name(kind, mix.map, image):
                        node.node_tree, swapped = build(mix.map, image), True
        if swapped:
            drop_unused()
    return True


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


# ------------------------------------------------------------------------------ public

def _frame(g, n, reference):
    """Unit x and y of the local frame: `reference` projected onto the plane of n, or any
    perpendicular where that vanishes (as learned_bsdf.osl)."""
    along = g.vmath('SUBTRACT', reference, g.scale(n, g.dot(reference, n)))
    usable = g.math('GREATER_THAN', g.vmath('LENGTH', along), 1e-7)
    # cross(n, x) unless n is near x, then cross(n, (1, 1, 0))
    near_x = g.math('GREATER_THAN', g.math('ABSOLUTE', g.dot(n, X)), 0.9)
    other = g.vmath('CROSS_PRODUCT', n, g.combine(1.0, near_x))
    tx = g.vmath('NORMALIZE', g.vmath('ADD', g.scale(along, usable),
                                      g.scale(other, g.math('SUBTRACT', 1.0, usable))))
    return tx, g.vmath('CROSS_PRODUCT', n, tx)


def portal_depth(light_path):
    """How many Ray Portals the path has gone through: Light Path's Portal Depth (Blender 5.0+);
    before 5.0 its Transparent Depth, which a portal also counts (Cycles' path_state_next: a
    portal is a transparent bounce, 4.5 as 5.0), and so does a transparent surface: there camera
    rays take hashed u instead of their pixel's stratified ones and the hash mixes in that count,
    unbiased either way."""
    return light_path.outputs.get("Portal Depth") or light_path.outputs["Transparent Depth"]


def _random(g, geometry, light_path):
    """u0, u1, u2 hashed from the shading point and the incoming ray (module docstring)."""
    noise = g.node("ShaderNodeTexWhiteNoise", noise_dimensions='4D')
    g.set(noise.inputs["Vector"], geometry.outputs["Position"])
    g.set(noise.inputs["W"], light_path.outputs["Ray Length"])
    depth = g.math('MULTIPLY_ADD', light_path.outputs["Ray Depth"], 64.0, portal_depth(light_path))
    noise2 = g.node("ShaderNodeTexWhiteNoise", noise_dimensions='4D')
    g.set(noise2.inputs["Vector"], geometry.outputs["Incoming"])
    g.set(noise2.inputs["W"], g.math('ADD', noise.outputs["Value"], depth))
    return tuple(g.dot(noise2.outputs["Color"], axis) for axis in (X, Y, Z))


def _shading(g, sampler, tangent):
    """The shading point: (geometry node, n, wi, cos theta_i as is and clamped to >= 0, and
    for anisotropic tables the frame (tx, ty) and phi_i, else None, None, None: the
    isotropic frame follows wi, `_frame(g, n, wi)`, built where it is used)."""
    geometry = g.node("ShaderNodeNewGeometry")
    n, wi = geometry.outputs["Normal"], geometry.outputs["Incoming"]
    cos_raw = g.dot(wi, n)
    frame = (None, None, None)
    if sampler.lay["P"] > 1:
        tx, ty = _frame(g, n, TANGENT if tangent is None else tangent)
        frame = (tx, ty, g.math('ARCTAN2', g.dot(wi, ty), g.dot(wi, tx)))
    return geometry, n, wi, cos_raw, g.math('MAXIMUM', cos_raw, 0.0), frame


def film_settings(scene):
    """(raster width, raster height, film) of a scene, film = 0 where camera rays must hash
    their u, else 1 + the render's seed (mod 2^20): only Cycles' box filter places a pixel's
    samples uniformly in it (1 px whatever its width setting; other filters spread them by
    their weight), and the seed rotates a pixel's u per render (as learned_bsdf.osl's)."""
    r = scene.render
    box = (scene.render.engine == 'CYCLES' and scene.cycles.pixel_filter_type == 'BOX'
           and bool(getattr(scene, "flowbsdf_film_u", scene.get("flowbsdf_film_u", True))))  # see node.film_settings
    cy = scene.cycles
    seed = cy.seed + (scene.frame_current if getattr(cy, "use_animated_seed", False) else 0)
    return (r.resolution_x * r.resolution_percentage / 100.0, r.resolution_y * r.resolution_percentage / 100.0,
            1.0 + (int(seed) & 0xFFFFF) if box else 0.0)


def set_film(tree, scene):
    """Write the scene's film_settings into the sampler graphs in `tree` (their "FlowBSDF SVM
    film" nodes); call it when the scene's resolution, pixel filter or seed (or, with an
    animated seed, the frame) changes."""
    values = film_settings(scene)
    for node in tree.nodes:
        if node.name.startswith(FILM):
            for socket, value in zip(node.inputs, values):
                sockets.assign(socket, value)


def _film_u(g, light_path, hashed):
    """(u0, u1): on camera rays before any portal, the sample's place in its pixel (raster
    position from the Window coordinate, Cranley-Patterson rotated by a hash of the pixel and
    the seed), when the film node says so (set_film); else the hashed u0, u1. Cycles places a
    pixel's samples by its stratified sequence, so a pixel's u are stratified too."""
    film = g.node("ShaderNodeCombineXYZ", name=FILM, label=FILM)
    for socket, value in zip(film.inputs, film_settings(bpy.context.scene)):
        socket.default_value = value
    raster = g.vmath('MULTIPLY', g.node("ShaderNodeTexCoord").outputs["Window"], film.outputs[0])
    rotation = g.node("ShaderNodeTexWhiteNoise", noise_dimensions='4D')
    g.set(rotation.inputs["Vector"], g.vmath('FLOOR', raster))
    g.set(rotation.inputs["W"], g.dot(film.outputs[0], Z))
    u = g.vmath('FRACTION', g.vmath('ADD', g.vmath('FRACTION', raster), rotation.outputs["Color"]))
    first = g.math('MULTIPLY', light_path.outputs["Is Camera Ray"],
                   g.math('LESS_THAN', portal_depth(light_path), 0.5))
    use = g.math('MULTIPLY', first, g.math('GREATER_THAN', g.dot(film.outputs[0], Z), 0.5))
    return tuple(g.select(use, g.dot(u, axis), h) for axis, h in zip((X, Y), hashed))


def sample_graph(tree, texture_path, group_input_tangent_socket=None, location=(0.0, 0.0)):
    """Add to `tree` the sampler of the SVM texture `texture_path` without the closure: a dict
    of sockets: "direction" (world, unit), "weight" (colour W = baked f·cos / pdf), "pdf"
    (per steradian), "valid" (1 when cos theta_i > 0 and the direction is above the geometric
    surface, else 0), "position" (the shading point) and "u2" (a third uniform number of
    this path vertex, unused by the sampler; film-stratified u0, u1 are used). For building
    on: build_svm_sampler, or a mixture with another strategy (one-sample MIS, with
    tables_pdf_graph at the other strategy's direction). Anisotropic tables take their frame's
    x from `group_input_tangent_socket` (world x when None)."""
    return _sample(_Graph(tree, location), texture_path, group_input_tangent_socket)


def _sample(g, texture_path, group_input_tangent_socket, cv=None):
    sampler = _Sampler(g, texture_path)
    geometry, n, wi, cos_raw, cos_i, (tx, ty, phi_i) = _shading(g, sampler, group_input_tangent_socket)
    light_path = g.node("ShaderNodeLightPath")
    u0, u1, u2 = _random(g, geometry, light_path)
    u0, u1 = _film_u(g, light_path, (u0, u1))
    take = None
    if cv is not None:
        take, u0 = _cv_pick(g, cv, u0)
    wo, weight, pdf = _tables_sample(g, sampler, cos_i, phi_i, u0, u1)
    if phi_i is None:
        tx, ty = _frame(g, n, wi)
    direction = g.vmath('ADD', g.vmath('ADD', g.scale(tx, wo[0]), g.scale(ty, wo[1])), g.scale(n, wo[2]))
    valid = g.math('MULTIPLY', g.math('GREATER_THAN', cos_raw, 0.0),
                   g.math('GREATER_THAN', g.dot(direction, geometry.outputs["True Normal"]), 0.0))
    return {"direction": direction, "weight": weight, "pdf": pdf, "valid": valid,
            "position": geometry.outputs["Position"], "u2": u2, "wi": wi, "n": n, "take": take}


def build_svm_sampler(tree, texture_path, group_input_tangent_socket=None, location=(0.0, 0.0), world=None,
                      cv=None):
    """Add to the shader node tree `tree` the sampler of the SVM texture `texture_path`
    (bake/export/svm_export.ensure_svm_export) ending in a Ray Portal BSDF; returns its shader output
    socket. Anisotropic tables take their frame's x from `group_input_tangent_socket` (a
    vector socket, e.g. the Learned BSDF group's Tangent input), world x when None. Camera
    rays stratify u by the film when the current scene allows it (set_film updates that).
    `world`: the world inputs (blender_addon/world.shader_inputs: World, WorldShare,
    SunDirection, SunCos, SunShare): the portal direction is then drawn from the mixture of
    the tables, the world map and the sun (module docstring); update_world changes them.
    Without a world map or sun to draw from (None, shares 0, no readable map), the graph is
    the tables' alone.
    `cv`: a control variate f_cv, the fit's Cycles closures (node._svm_backend: "fit" its
    parameters' sockets (node._fit_params: kd, ks per lobe, roughness, anisotropy) of a Diffuse
    and GGX Glossy BSDFs; "betas" (beta_d, beta_s, s) and "matched_share" (s_m in x) sockets;
    "has_betas"; "match_image" (the fit's match image path or None); "closures" (scale_d,
    scale_s) -> the closures' shader, kd and each ks scaled by those colours): a shading point
    takes the closures (colours beta kd, beta ks, weight 1 / (1 - s)) with probability 1 - s,
    else the portal carrying f - f_cv with weight (f - f_cv) cos / (q s), as two portals (its
    positive and negative channels); matched to the world's light where it has one.
    """
    g = _Graph(tree, location)
    mix = _Mixture(world)
    if cv is not None:
        cv = _cv_switched(g, cv, world, _matching(mix, bool(cv.get("match_image"))), mix.match_lamp)
    if mix:
        return _mixture(g, texture_path, group_input_tangent_socket, mix, cv)
    out = _sample(g, texture_path, group_input_tangent_socket, cv)
    # zero (the path ends) for light from below the surface or a direction below the geometry
    weight = g.scale(out["weight"], out["valid"])
    if cv is None:
        return _portal(g, weight, out["position"], out["direction"], out["u2"])
    rest = _cv_rest(g, cv, out["wi"], out["n"], out["direction"], weight, out["valid"], out["pdf"])
    return _mix_shader(g, out["take"], _cv_closures(g, cv),
                       _signed_portals(g, rest, out["position"], out["direction"], out["u2"]))


def _cv_switched(g, cv, world, matched, match_lamp=False):
    """`cv` with "on" (the value of a node named CV: 1 uses the control variate, 0 leaves the
    portal alone: world inputs' ControlVariate, update_world; and only on camera rays) and "s",
    the share of shading points that take the portal: cv's share when on, else 1. None (the
    node kept, marked) for a control variate with no betas when the world has no light to
    match it to.
    Camera rays only: past a diffuse or rough bounce Cycles renders closures other than they
    are (Filter Glossy, on by default, blurs the GGX lobes; Caustics off drops them), so f_cv as
    rendered there is not the f_cv the portal's rest subtracts; the portal alone is exact there.
    A ray a portal continued at a camera-hit point is still a camera ray, neither blurred nor
    filtered (Cycles path_state_next: the portal adds only the transparent flag). The closures'
    own bounce is a diffuse or glossy one, so what they continue to is blurred or filtered,
    unlike what the portal continues to: node.caustics_gate turns the control variate off when
    Caustics are off (measured -8.9 % without); Filter Glossy's +2.1 % there is kept."""
    node = g.node("ShaderNodeValue", name=CV, label=CV)
    node.outputs[0].default_value = _cv_value(world)
    node["flowbsdf_light"] = int(matched)
    node["flowbsdf_matchable"] = int(bool(cv.get("match_image")))
    node["flowbsdf_match_lamp"] = int(matched and match_lamp)
    if not matched and not cv["has_betas"]:
        return None
    on = g.math('MULTIPLY', node.outputs[0], g.node("ShaderNodeLightPath").outputs["Is Camera Ray"])
    beta_d, beta_s = g.dot(cv["betas"], X), g.dot(cv["betas"], Y)
    return dict(cv, on=on, matching=matched, diffuse=g.combine(beta_d, beta_d, beta_d),
                specular=g.combine(beta_s, beta_s, beta_s),
                s=g.math('SUBTRACT', 1.0, g.math('MULTIPLY', on, g.math('SUBTRACT', 1.0, g.dot(cv["betas"], Z)))))


def _cv_value(world):
    return float((world or {}).get("ControlVariate", 0.0))


def _cv_pick(g, cv, u0):
    """(1 when the shading point takes the portal (probability s, the control variate's portal
    share), else 0; u0 rescaled within the part taken: uniform again for the portal's sampling).
    By u0, so that on camera rays the pick is as stratified over a pixel's samples as u0 is."""
    s = cv["s"]
    take = g.math('LESS_THAN', u0, s)
    inside = g.select(take, g.math('DIVIDE', u0, s),
                      g.math('DIVIDE', g.math('SUBTRACT', u0, s), g.math('SUBTRACT', 1.0, s)))
    return take, g.math('MINIMUM', inside, 1.0 - 2.0 ** -24)


def _cv_fcos(g, cv, wi, n, d):
    """What the control variate's closures render toward d, f_cv cos theta_o (colour): Cycles'
    Diffuse BSDF (colour kd scaled by cv["diffuse"]) and the fit's GGX Glossy BSDFs (colours
    ks_j scaled by cv["specular"], roughness r_j, anisotropy a_j, the tangent along the view:
    node.view_tangent) as bsdf_diffuse_eval and bsdf_microfacet_eval compute them (no Fresnel,
    height-correlated G2), at wi and d about the normal n, each tilted closure about its own
    normal (node._closures; the tilted Diffuse times Cycles' bump shadowing). (A node group, one
    for every lobe count and set of tilted closures: a mixture's branches each take it.)"""
    fit = cv["fit"]
    lobes = len(fit["ks"])
    tilted = tuple(bool(t) for t in fit.get("tilted", [False] * (lobes + 1))) if CV_TILTS else (False,) * (lobes + 1)
    inputs = {f"Specular {j + 1}": ks for j, ks in enumerate(fit["ks"])}
    if any(tilted[1:4]):
        inputs["Tilt"] = fit["tilt"]
    if lobes > 3 or tilted[0]:
        inputs["Lobe 4"] = fit["lobe4"]
    return g.group(_cv_fcos_group(lobes, tilted), Wi=wi, N=n, D=d, Diffuse=fit["kd"], Roughness=fit["roughness"],
                   Anisotropy=fit["anisotropy"], DiffuseScale=cv["diffuse"], SpecularScale=cv["specular"],
                   **inputs)[0]


# The control variate's closures tilted as the fit's (node._closures): else untilted, in the
# closures and in _cv_fcos alike (any f_cv is unbiased where the graph's equals what its closures render).
CV_TILTS = True


def _cv_fcos_group(lobes, tilted=None):
    """_cv_fcos's group: `lobes` GGX lobes (the first three view-aligned where their Anisotropy
    is not 0, the 4th isotropic: its roughness, tilt and the Diffuse's tilt from "Lobe 4" =
    (r_4, t_4, t_d)), tilted[k] whether closure k (the Diffuse first) has its own normal
    normalize(N + t T / |T|) (T the view tangent; else N)."""
    tilted = tuple(tilted or (False,) * (lobes + 1))
    names = (["Wi", "N", "D", "Diffuse"] + [f"Specular {j + 1}" for j in range(lobes)]
             + ["Roughness", "Anisotropy"] + (["Tilt"] if any(tilted[1:4]) else [])
             + (["Lobe 4"] if lobes > 3 or tilted[0] else []) + ["DiffuseScale", "SpecularScale"])
    mark = "" if not any(tilted) else ", tilted " + "".join("d" if k == 0 else str(k) for k, t in enumerate(tilted) if t)
    done, tree = _group(f"{GROUP_PREFIX}control variate f cos, {lobes} view-aligned lobes{mark}, scaled",
                        [(name, "Vector") for name in names], [("F cos", "Vector")])
    if done:
        return done
    g = _Graph(tree)
    inp = g.node("NodeGroupInput").outputs
    wi, n, d = inp["Wi"], inp["N"], inp["D"]
    cos_i = g.dot(wi, n)
    cos_o = g.dot(d, n)
    above = g.math('MULTIPLY', g.math('GREATER_THAN', cos_i, 0.0), g.math('GREATER_THAN', cos_o, 0.0))
    # Cycles' frame of an anisotropic closure (make_orthonormals_tangent): y = normalize(N x T),
    # x = y x N, T the view's tangent (node.view_tangent: wi less its normal part, nudged)
    tangent = g.vmath('MULTIPLY_ADD', g.vmath('CROSS_PRODUCT', n, VIEW_TANGENT_NUDGE), (VIEW_TANGENT_EPS,) * 3,
                      g.vmath('SUBTRACT', wi, g.scale(n, cos_i)))
    h = g.vmath('NORMALIZE', g.vmath('ADD', wi, d))
    separated = {}

    def component(name, c):
        if name not in separated:
            separated[name] = g.node("ShaderNodeSeparateXYZ")
            g.set(separated[name].inputs[0], inp[name])
        return separated[name].outputs[c]

    untilted = {}
    if any(tilted):
        # A tilted closure's normal normalize(N + t U) (U = T / |T|: orthogonal to N) and its
        # frame (make_orthonormals_tangent with T: y = normalize(N' x T) = N x U, the untilted y;
        # x = y x N') turn the untilted frame (U, y, N) about y: a vector's coordinates there are
        # ((v.U - t v.N) c, v.y, (v.N + t v.U) c), c = 1 / sqrt(1 + t^2). So each lobe takes scalars
        # of these dots alone, of its own branch: every value here depends on d, through a no-op
        # for the tilts (min with a 1e30 of d), else Cycles would merge the branches' equal nodes,
        # compute them before the branches and hold them all on its stack through all.
        big = g.math('MAXIMUM', cos_o, 1e30)
        # (U and y through the no-op too: each branch's own, not held through all; y = N x U exactly)
        unit = g.vmath('MINIMUM', g.vmath('NORMALIZE', tangent), big)
        fy = g.vmath('CROSS_PRODUCT', n, unit)
        # (wi.y: 0, wi in the plane of N and T; Cycles' float dot is ~1e-8 there)
        dots = {"h": (g.dot(h, unit), g.dot(h, fy), g.dot(h, n)), "i": (g.dot(wi, unit), 0.0, cos_i),
                "o": (g.dot(d, unit), g.dot(d, fy), cos_o)}

    def tilt_of(closure):       # 0: the Diffuse, j + 1: lobe j (this branch's own)
        t = component("Lobe 4", 2 if closure == 0 else 1) if closure in (0, 4) else component("Tilt", closure - 1)
        return g.math('MINIMUM', t, big)

    def turned(t, c, v, aniso):
        a, y, b = v
        z = g.math('MULTIPLY', g.math('MULTIPLY_ADD', a, t, b), c)
        if not aniso:
            return None, None, z
        return g.math('MULTIPLY', g.math('MULTIPLY_ADD', b, g.math('MULTIPLY', t, -1.0), a), c), y, z

    def local_of(closure, aniso):
        """(mask, local h, wi, d: each (x, y, z); x, y None for an isotropic lobe) about the
        closure's normal."""
        if not tilted[closure]:
            if aniso not in untilted:
                untilted[aniso] = (above, *_cv_local(g, n, tangent, h, wi, d, cos_i, cos_o, aniso))
            return untilted[aniso]
        t = tilt_of(closure)
        c = g.math('INVERSE_SQRT', g.math('MULTIPLY_ADD', t, t, 1.0))
        lh, li, lo = (turned(t, c, dots[k], aniso) for k in ("h", "i", "o"))
        # (Cycles: wi and d above the closure's normal, d above the surface's)
        mask = g.math('MULTIPLY', g.math('MULTIPLY', g.math('GREATER_THAN', li[2], 0.0), g.math('GREATER_THAN', lo[2], 0.0)),
                      g.math('GREATER_THAN', cos_o, 0.0))
        return mask, lh, li, lo
    def square(x):      # x x, not a Power node: pow costs ~4x a multiply in Cycles' SVM (and a constant 2)
        return g.math('MULTIPLY', x, x)
    lobe = []
    for j in range(lobes):
        aniso = j < 3
        r = g.math('MINIMUM', g.math('MAXIMUM', component("Roughness", j) if j < 3 else component("Lobe 4", 0), 0.0), 1.0)
        alpha = g.math('MULTIPLY', r, r)
        mask, lh, li, lo = local_of(j + 1, aniso)
        if aniso:
            a = g.math('MINIMUM', g.math('MAXIMUM', component("Anisotropy", j), -0.99), 0.99)
            neg = g.math('LESS_THAN', a, 0.0)
            # svm closure.h: a < 0: (alpha / (1 + a), alpha (1 + a)), else (alpha (1 - a), alpha / (1 - a))
            # (each at most 1: bsdf_microfacet_ggx_setup saturates them)
            ax = g.math('MINIMUM', g.select(neg, g.math('DIVIDE', alpha, g.math('ADD', 1.0, a)),
                                            g.math('MULTIPLY', alpha, g.math('SUBTRACT', 1.0, a))), 1.0)
            ay = g.math('MINIMUM', g.select(neg, g.math('MULTIPLY', alpha, g.math('ADD', 1.0, a)),
                                            g.math('DIVIDE', alpha, g.math('SUBTRACT', 1.0, a))), 1.0)
            hx, hy, hz = lh
            q = g.math('ADD', g.math('ADD', square(g.math('DIVIDE', hx, ax)), square(g.math('DIVIDE', hy, ay))),
                       g.math('MULTIPLY', hz, hz))
            ndf = g.math('DIVIDE', 1.0 / math.pi,
                         g.math('MULTIPLY', g.math('MULTIPLY', ax, ay), g.math('MULTIPLY', q, q)))

            def lam(v, ax=ax, ay=ay):    # bsdf_lambda<GGX>: 0.5 (sqrt(1 + (ax^2 vx^2 + ay^2 vy^2) / vz^2) - 1)
                t2 = g.math('DIVIDE', g.math('ADD', square(g.math('MULTIPLY', ax, v[0])),
                                              square(g.math('MULTIPLY', ay, v[1]))),
                            g.math('MULTIPLY', v[2], v[2]))
                return g.math('MULTIPLY', g.math('SUBTRACT', g.math('SQRT', g.math('ADD', t2, 1.0)), 1.0), 0.5)
        else:
            # isotropic (alpha at most 1): D = 1 / (pi alpha^2 q^2), q = (1 - hz^2) / alpha^2 + hz^2;
            # lambda = 0.5 (sqrt(1 + alpha^2 (1 - vz^2) / vz^2) - 1)
            hz = lh[2]
            hz2 = g.math('MULTIPLY', hz, hz)
            alpha2 = g.math('MULTIPLY', alpha, alpha)
            q = g.math('ADD', g.math('DIVIDE', g.math('SUBTRACT', 1.0, hz2), alpha2), hz2)
            ndf = g.math('DIVIDE', 1.0 / math.pi, g.math('MULTIPLY', alpha2, g.math('MULTIPLY', q, q)))

            def lam(v, alpha2=alpha2):
                vz2 = g.math('MULTIPLY', v[2], v[2])
                t2 = g.math('DIVIDE', g.math('MULTIPLY', alpha2, g.math('SUBTRACT', 1.0, vz2)), vz2)
                return g.math('MULTIPLY', g.math('SUBTRACT', g.math('SQRT', g.math('ADD', t2, 1.0)), 1.0), 0.5)
        g2 = g.math('ADD', g.math('ADD', lam(li), lam(lo)), 1.0)
        lobe.append(g.math('DIVIDE', g.math('MULTIPLY', ndf, mask), g.math('MULTIPLY', g.math('MULTIPLY', li[2], 4.0), g2)))
    # the Diffuse: max(d.N', 0) / pi, tilted times Cycles' bump shadowing G1 (bsdf.h
    # bump_shadowing_term: alpha^2 = min(tan^2 / 8, 1) of the tilt, tan^2 = t_d^2 as T is
    # orthogonal to N; 0 where d.N < 1e-6)
    if tilted[0]:
        td = tilt_of(0)
        td2 = g.math('MULTIPLY', td, td)
        cos_od = turned(td, g.math('INVERSE_SQRT', g.math('ADD', td2, 1.0)), dots["o"], False)[2]    # d.N'
        a2 = g.math('MINIMUM', g.math('MULTIPLY', td2, 0.125), 1.0)
        c = g.math('MAXIMUM', cos_o, 1e-6)
        tan2 = g.math('SUBTRACT', g.math('DIVIDE', 1.0, g.math('MULTIPLY', c, c)), 1.0)
        g1 = g.math('DIVIDE', 2.0, g.math('ADD', 1.0, g.math('SQRT', g.math('MULTIPLY_ADD', a2, tan2, 1.0))))
        shade = g.math('MULTIPLY', g.math('MULTIPLY', g.math('MAXIMUM', cos_od, 0.0), 1.0 / math.pi),
                       g.math('MULTIPLY', g1, g.math('GREATER_THAN', cos_o, 1e-6)))
    else:
        shade = g.math('MULTIPLY', g.math('MAXIMUM', cos_o, 0.0), 1.0 / math.pi)
    # the colours last (made last, Cycles runs them last: fewer values alive on its stack meanwhile)
    out = g.scale(g.vmath('MULTIPLY', inp["Diffuse"], inp["DiffuseScale"]), shade)
    for j, value in enumerate(lobe):
        out = g.vmath('MULTIPLY_ADD', g.vmath('MULTIPLY', inp[f"Specular {j + 1}"], inp["SpecularScale"]),
                      g.combine(value, value, value), out)
    g.set(g.node("NodeGroupOutput").inputs["F cos"], out)
    return tree


def _cv_local(g, nj, tangent, h, wi, d, cos_i, cos_o, aniso):
    """(h, wi, d) in the frame of normal nj (Cycles' make_orthonormals_tangent with the view
    tangent: y = normalize(nj x T), x = y x nj), each (x, y, z); x, y None when not `aniso`."""
    if not aniso:
        return (None, None, g.dot(h, nj)), (None, None, cos_i), (None, None, cos_o)
    fy = g.vmath('NORMALIZE', g.vmath('CROSS_PRODUCT', nj, tangent))
    fx = g.vmath('CROSS_PRODUCT', fy, nj)
    return ((g.dot(h, fx), g.dot(h, fy), g.dot(h, nj)), (g.dot(wi, fx), g.dot(wi, fy), cos_i),
            (g.dot(d, fx), g.dot(d, fy), cos_o))


def _cv_rest(g, cv, wi, n, d, weight, ok, q):
    """The portal's weight for the BSDF less the control variate (when on), when taken with
    probability s: (weight - on f_cv cos ok / q) / s."""
    rest = g.vmath('SUBTRACT', weight, g.scale(_cv_fcos(g, cv, wi, n, d),
                                              g.math('DIVIDE', g.math('MULTIPLY', ok, cv["on"]), q)))
    return g.scale(rest, g.math('DIVIDE', 1.0, cv["s"]))


def _signed_portals(g, weight, position, direction, u2):
    """Two portals along `direction`, the positive and the negative channels of `weight`:
    Cycles picks a closure by its mean weight's magnitude, which for a colour of mixed signs
    may be near 0 while its channels are not (the path's weight over the pick would explode)."""
    pos = _portal(g, g.vmath('MAXIMUM', weight, (0.0, 0.0, 0.0)), position, direction, u2)
    neg = _portal(g, g.vmath('MINIMUM', weight, (0.0, 0.0, 0.0)), position, direction, u2)
    node = g.node("ShaderNodeAddShader")
    g.set(node.inputs[0], pos)
    g.set(node.inputs[1], neg)
    return node.outputs[0]


def _portal(g, weight, position, direction, u2):
    """A Ray Portal BSDF continuing the path along `direction` with colour `weight`. Cycles
    drops a closure of mean weight (magnitude) < CUTOFF: those below 2 CUTOFF are rouletted up
    to it."""
    keep = g.math('MULTIPLY', g.math('ABSOLUTE', g.dot(weight, (1.0 / 3, 1.0 / 3, 1.0 / 3))), 0.5 / CUTOFF,
                  clamp=True)
    survive = g.math('LESS_THAN', g.math('MULTIPLY', u2, 1.0 - 2.0 ** -24), keep)
    weight = g.scale(weight, g.math('DIVIDE', survive, keep))
    portal = g.node("ShaderNodeBsdfRayPortal")
    g.set(portal.inputs["Color"], weight)
    g.set(portal.inputs["Position"], position)
    g.set(portal.inputs["Direction"], direction)
    return portal.outputs["BSDF"]


def _mixture(g, texture_path, group_input_tangent_socket, mix, cv=None):
    """The shading point and its u (as _sample), then the mixture's branches, each ending in a
    portal (two with a control variate `cv`: build_svm_sampler)."""
    sampler = _Sampler(g, texture_path)
    geometry, n, wi, cos_raw, cos_i, (tx, ty, phi_i) = _shading(g, sampler, group_input_tangent_socket)
    light_path = g.node("ShaderNodeLightPath")
    u0, u1, u2 = _random(g, geometry, light_path)
    u0, u1 = _film_u(g, light_path, (u0, u1))
    if phi_i is None:
        tx, ty = _frame(g, n, wi)
    at = {"n": n, "wi": wi, "ng": geometry.outputs["True Normal"], "cos_raw": cos_raw, "cos_i": cos_i, "tx": tx, "ty": ty,
          "phi_i": phi_i, "u0": u0, "u1": u1, "p": geometry.outputs["Position"]}
    position = geometry.outputs["Position"]
    if cv is None:
        return mix.graph(g, sampler, at, lambda out: _portal(g, out["weight"], position, out["direction"], u2))

    scale = None
    if cv["matching"]:
        unmatched = None
        if mix.match_lamp:      # (the brightest lamp's share of the lamps' weight: equal time, 4096
            # Principled spp, studio: MSE x0.83 / 0.75 / 1.10 on satin / military / vch, 6 seeds)
            data = mix.lamp_data(g, at)
            unmatched = g.math('SUBTRACT', 1.0, g.math('DIVIDE', data["best"], data["total"]))
        cv = _cv_matched(g, cv, at, mix.light_axis(g, at), unmatched)
        scale = g.math('SUBTRACT', 1.0, g.math('MULTIPLY', cv["matched"], 1.0 - MATCHED_LIGHT_SCALE))
    take, at["u0"] = _cv_pick(g, cv, u0)

    def closure(out):
        rest = _cv_rest(g, cv, wi, n, out["direction"], out["weight"], out["ok"], out["q"])
        return _signed_portals(g, rest, position, out["direction"], u2)
    return _mix_shader(g, take, _cv_closures(g, cv), mix.graph(g, sampler, at, closure, scale))


def _cv_closures(g, cv):
    """The control variate's closures, colours / (1 - s) (their weight when taken)."""
    keep = g.math('SUBTRACT', 1.0, cv["s"])
    return cv["closures"](g.vmath('DIVIDE', cv["diffuse"], g.combine(keep, keep, keep)),
                          g.vmath('DIVIDE', cv["specular"], g.combine(keep, keep, keep)))


def _cv_matched(g, cv, at, axis, unmatched=None):
    """`cv` with the fit's closures scaled at this shading point so that f_cv = f toward the
    light's direction `axis` (beta = f / f_fit there per channel, trilinear in the match image:
    bake/export/closure_fit.match_ratios), the portal's share its matched_share: the light's part
    of the rest is ~0 (Cycles' light sampling of the closures carries it). The baked betas and
    share where the light is below the surface or the view angle's fit is too poor
    (matched_share 0)."""
    wo = tuple(g.dot(axis, v) for v in (at["tx"], at["ty"], at["n"]))
    beta = _match_lookup(g, cv["match_image"], at["cos_i"], wo)
    share = g.dot(cv["matched_share"], X)
    # (between a knot matched and one not, the share falls to 0: off below the least share)
    on = g.math('MULTIPLY', g.math('GREATER_THAN', wo[2], 0.05),
                g.math('MULTIPLY', g.math('GREATER_THAN', share, 0.99 * MATCHED_SHARE_MIN), cv["on"]))
    off = g.math('SUBTRACT', 1.0, on)
    if unmatched is not None:
        # the other lamps' part of the rest is not ~0: toward the baked share as their weight grows
        share = g.math('MULTIPLY_ADD', g.math('MAXIMUM', g.math('SUBTRACT', cv["s"], share), 0.0), unmatched, share)
    return dict(cv, matched=on, s=g.math('MULTIPLY_ADD', on, share, g.math('MULTIPLY', cv["s"], off)),
                diffuse=g.vmath('MULTIPLY_ADD', g.combine(on, on, on), beta, g.scale(cv["diffuse"], off)),
                specular=g.vmath('MULTIPLY_ADD', g.combine(on, on, on), beta, g.scale(cv["specular"], off)))


def _match_lookup(g, path, cos_v, wo):
    """The match image's ratio (colour) at view cosine cos_v and the light's local direction wo
    (x, y, z; the view's azimuth 0): bilinear in (|phi|, cos theta_l) within a view's tile
    (texel centres are the grid's nodes, so a lookup never blends two tiles), linear between
    the two nearest views' tiles."""
    image = _image(path)
    n = image.size[1]
    width, height = n * n, n
    fv = g.math('MULTIPLY', g.math('MINIMUM', g.math('MAXIMUM', cos_v, 0.0), 1.0), n - 1.0)
    i0 = g.math('MINIMUM', g.math('FLOOR', fv), n - 2.0)
    t = g.math('SUBTRACT', fv, i0)
    fphi = g.math('MULTIPLY', g.math('ABSOLUTE', g.math('ARCTAN2', wo[1], wo[0])), (n - 1.0) / math.pi)
    fl = g.math('MULTIPLY', g.math('MINIMUM', g.math('MAXIMUM', wo[2], 0.0), 1.0), n - 1.0)
    v = g.math('SUBTRACT', 1.0, g.math('DIVIDE', g.math('ADD', fl, 0.5), height))

    def tile(i):
        x = g.math('DIVIDE', g.math('ADD', g.math('MULTIPLY_ADD', i, float(n), fphi), 0.5), width)
        tex = g.node("ShaderNodeTexImage", image=image, interpolation='Linear', extension='EXTEND')
        g.set(tex.inputs["Vector"], g.combine(x, v))
        return tex.outputs["Color"]
    lo, hi = tile(i0), tile(g.math('ADD', i0, 1.0))
    return g.vmath('MULTIPLY_ADD', g.vmath('SUBTRACT', hi, lo), g.combine(t, t, t), lo)


def tables_pdf_graph(tree, texture_path, wo_socket, group_input_tangent_socket=None, location=(0.0, 0.0)):
    """Add to `tree` the inverse of the sampler: at the world direction `wo_socket` (a unit
    vector socket), the tables' pdf (per steradian, 0 below the shading surface) and baked
    f·cos (colour: W x pdf, 0 when wi or wo is below the surface), as Tables.pdf and
    Tables.eval x cos theta_o do. Returns (pdf socket, f·cos socket)."""
    g = _Graph(tree, location)
    sampler = _Sampler(g, texture_path)
    _, n, wi, cos_raw, cos_i, (tx, ty, phi_i) = _shading(g, sampler, group_input_tangent_socket)
    if phi_i is None:
        tx, ty = _frame(g, n, wi)
    local = tuple(g.dot(wo_socket, axis) for axis in (tx, ty, n))
    pdf, fcos = _inverse(g, sampler, cos_i, phi_i, local)
    fcos = g.scale(fcos, g.math('GREATER_THAN', cos_raw, 0.0))
    return pdf, fcos


def _inverse(g, sampler, cos_i, phi_i, wo):
    """(pdf, f·cos) at the local direction wo (floats x, y, z), both 0 for wo_z <= 0."""
    sampler.incident(cos_i, phi_i)
    a, b, jac = sampler.coordinates(wo, cos_i, phi_i)
    pdf, weight = sampler.locate(a, b)
    if jac is not None:
        pdf = g.math('DIVIDE', pdf, jac)
    pdf = g.math('MULTIPLY', pdf, g.math('GREATER_THAN', wo[2], 0.0))
    return pdf, g.scale(weight, pdf)


def build_svm_probe(tree, texture_path, probe_path, inverse=False, location=(0.0, 0.0), world=None):
    """The sampler (or with `inverse`, tables_pdf_graph's inverse) on inputs from the probe image
    `probe_path` (w x h float32 RGBA texels: u0, u1, cos theta_i, phi_i; with `inverse`,
    cos theta_o, phi_o, cos theta_i, phi_i, in the frame whose x is the tangent: wi at phi_i)
    for a camera whose window spans 3 w x h pixels (orthographic, pixel centres): pixel
    column x shows texel x mod w of the probe, as 0.5 + 0.5 wo, the weight W and the pdf
    (thirds of the image; with `inverse`: the pdf, f·cos and 0), through an Emission of
    strength 1. Returns the Emission's output socket.
    With `world` (build_svm_sampler's), the mixture at a shading point of normal world z and
    wi = (sin theta_i cos phi_i, sin theta_i sin phi_i, cos theta_i) (the frame's x from wi, or
    for anisotropic tables world x): 0.5 + 0.5 the world direction, the weight, and (q, the
    technique (0 tables, 1 map, 2 sun), 1 if the direction counts else 0)."""
    g = _Graph(tree, location)
    sampler = _Sampler(g, texture_path)
    thirds, values, alpha = _probe_input(g, probe_path)
    first, second, cos_i = (g.dot(values, axis) for axis in (X, Y, Z))
    phi_i = alpha if sampler.lay["P"] > 1 else None
    if world is not None:
        sin_i = g.math('SQRT', g.math('SUBTRACT', 1.0, g.math('MULTIPLY', cos_i, cos_i)))
        wi = g.combine(g.math('MULTIPLY', sin_i, g.math('COSINE', alpha)),
                       g.math('MULTIPLY', sin_i, g.math('SINE', alpha)), cos_i)
        tx, ty = _frame(g, Z, wi if phi_i is None else TANGENT)
        if phi_i is not None:
            phi_i = g.math('ARCTAN2', g.dot(wi, ty), g.dot(wi, tx))
        at = {"n": Z, "ng": Z, "cos_raw": cos_i, "cos_i": cos_i, "tx": tx, "ty": ty, "phi_i": phi_i,
              "u0": first, "u1": second, "p": (0.0, 0.0, 0.0)}
        return _Mixture(world).graph(g, sampler, at, lambda out: _probe_output(
            g, thirds, (g.vmath('MULTIPLY_ADD', out["direction"], (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)), out["weight"],
                        g.combine(out["q"], out["technique"], out["ok"]))))
    if inverse:
        sin_o = g.math('SQRT', g.math('SUBTRACT', 1.0, g.math('MULTIPLY', first, first)))
        wo = (g.math('MULTIPLY', sin_o, g.math('COSINE', second)), g.math('MULTIPLY', sin_o, g.math('SINE', second)),
              first)
        pdf, fcos = _inverse(g, sampler, cos_i, phi_i, wo)
        shown = (pdf, fcos, (0.0, 0.0, 0.0))
    else:
        wo, weight, pdf = _tables_sample(g, sampler, cos_i, phi_i, first, second)
        wo = g.vmath('MULTIPLY_ADD', g.combine(*wo), (0.5, 0.5, 0.5), (0.5, 0.5, 0.5))
        shown = (wo, weight, pdf)
    return _probe_output(g, thirds, shown)


def build_world_probe(tree, world_path, probe_path, location=(0.0, 0.0)):
    """The world map's sampling on u0, u1 from the probe image (build_svm_probe's layout): 0.5
    + 0.5 the direction, (its pdf, the pdf graph's density at it, 0), and 0."""
    g = _Graph(tree, location)
    wl, image = world_layout(str(world_path)), _image(world_path)
    thirds, values, _ = _probe_input(g, probe_path)
    out = g.group(_world_sample_group(wl, image), U0=g.dot(values, X), U1=g.dot(values, Y))
    again = g.group(_world_pdf_group(wl, image), Direction=out["Direction"])[0]
    return _probe_output(g, thirds, (g.vmath('MULTIPLY_ADD', out["Direction"], (0.5, 0.5, 0.5), (0.5, 0.5, 0.5)),
                                     g.combine(out["Pdf"], again), (0.0, 0.0, 0.0)))


def _probe_input(g, probe_path):
    """(the thirds' flags: left, middle, right; the probe texel's colour, its alpha) of this pixel."""
    window = g.node("ShaderNodeTexCoord").outputs["Window"]
    wx = g.math('MULTIPLY', g.dot(window, X), 3.0)
    third = g.math('FLOOR', wx)
    # one of the three by its third of the image: x 1 and x 0 (exact)
    left, right = g.math('LESS_THAN', third, 0.5), g.math('GREATER_THAN', third, 1.5)
    middle = g.math('SUBTRACT', g.math('SUBTRACT', 1.0, left), right)
    probe = g.node("ShaderNodeTexImage", image=_image(probe_path), interpolation='Closest', extension='EXTEND')
    g.set(probe.inputs["Vector"], g.combine(g.math('FRACT', wx), g.dot(window, Y)))
    return (left, middle, right), probe.outputs["Color"], probe.outputs["Alpha"]


def _probe_output(g, thirds, shown):
    """An Emission of shown[k] in third k of the image."""
    color = g.vmath('ADD', g.vmath('ADD', g.scale(shown[0], thirds[0]), g.scale(shown[1], thirds[1])),
                    g.scale(shown[2], thirds[2]))
    emission = g.node("ShaderNodeEmission")
    g.set(emission.inputs["Color"], color)
    emission.inputs["Strength"].default_value = 1.0
    return emission.outputs["Emission"]


def graph_counts(tree):
    """(shader nodes, texture lookups per sample) of a tree, node groups expanded as Cycles
    compiles them (group inputs/outputs, frames and reroutes not counted; image lookups of
    the same image at the same coordinates counted once: Cycles merges identical nodes)."""
    nodes, lookups = _count(tree, (), {})
    return nodes, len(lookups)


def _count(tree, path, outer):
    """(nodes, {(image, coordinate source)}) in `tree`, a group instance at `path` whose
    inputs come from the sources `outer` (by socket identifier)."""
    def source(socket):
        if not socket.is_linked:
            value = socket.default_value
            return ("constant", tuple(value) if hasattr(value, "__len__") else value)
        link = socket.links[0]
        if link.from_node.bl_idname == "NodeGroupInput":
            return outer.get(link.from_socket.identifier)
        return (path, link.from_node.name, link.from_socket.identifier)
    nodes, lookups = 0, set()
    for node in tree.nodes:
        if node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
            inner = {socket.identifier: source(socket) for socket in node.inputs}
            n, lk = _count(node.node_tree, path + (node.name,), inner)
            nodes, lookups = nodes + n, lookups | lk
        elif node.bl_idname not in ("NodeGroupInput", "NodeGroupOutput", "NodeFrame", "NodeReroute"):
            nodes += 1
            if node.bl_idname == "ShaderNodeTexImage":
                lookups.add((node.image.name if node.image else "", source(node.inputs["Vector"])))
    return nodes, lookups
