"""Small Cycles scenes for the Learned BSDF tests and scripts/cycles_acceptance.py (bpy module),
and the small baked tables and white-furnace checks the Cycles tests share.

render() returns the linear float32 image (H, W, 3), top row first, read back from a
32-bit OpenEXR, so pixel values are exactly what Cycles accumulated.
"""
import os
import tempfile
from pathlib import Path

import numpy as np


def bpy_or_skip(need_osl=True):
    """bpy, or skip the calling test module with the reason (no bpy; no OSL when `need_osl`)."""
    import pytest
    try:
        import bpy  # noqa: F401
    except Exception as e:  # noqa: BLE001
        pytest.skip(f"bpy (Blender as a Python module) is not importable: {e}", allow_module_level=True)
    import _cycles
    if need_osl and not _cycles.with_osl:
        pytest.skip("this bpy build has no OSL", allow_module_level=True)
    return bpy


def reset(width=64, height=64, spp=16, osl=True, seed=0, threads=2):
    """An empty factory scene with the tests' render settings (configure)."""
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return configure(bpy.context.scene, width, height, spp, osl, seed, threads)


def configure(sc, width=64, height=64, spp=16, osl=True, seed=0, threads=2):
    """The tests' Cycles settings on scene `sc` (CPU, fixed seed and threads, no adaptive sampling,
    denoising or clamping, 64 bounces, Filter Glossy 0, linear 32-bit EXR output)."""
    sc.render.engine = 'CYCLES'
    sc.cycles.device = 'CPU'
    sc.cycles.shading_system = osl
    sc.cycles.samples = spp
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.use_denoising = False
    sc.cycles.seed = seed
    sc.cycles.max_bounces = 64
    sc.cycles.transparent_max_bounces = 64
    sc.cycles.diffuse_bounces = sc.cycles.glossy_bounces = 64
    sc.cycles.sample_clamp_direct = 0.0
    sc.cycles.sample_clamp_indirect = 0.0
    sc.cycles.blur_glossy = 0.0
    sc.cycles.caustics_reflective = True
    sc.render.resolution_x, sc.render.resolution_y = width, height
    sc.render.resolution_percentage = 100
    sc.render.threads_mode = 'FIXED'
    sc.render.threads = threads
    sc.view_settings.view_transform = 'Standard'
    sc.view_settings.look = 'None'
    sc.view_settings.exposure = 0.0
    sc.view_settings.gamma = 1.0
    sc.render.film_transparent = False
    sc.render.image_settings.file_format = 'OPEN_EXR'
    sc.render.image_settings.color_depth = '32'
    sc.render.image_settings.exr_codec = 'ZIP'
    return sc


def set_world(scene, color=(1.0, 1.0, 1.0), image=None, strength=1.0):
    """A constant world colour, or an equirectangular environment image (closest lookups)."""
    import bpy
    world = bpy.data.worlds.new("flowbsdf world")
    scene.world = world
    if world.node_tree is None:
        world.use_nodes = True
    nt = world.node_tree
    bg = next(n for n in nt.nodes if n.type == 'BACKGROUND')
    bg.inputs["Color"].default_value = (*color, 1.0)
    bg.inputs["Strength"].default_value = strength
    if image is not None:
        tex = nt.nodes.new("ShaderNodeTexEnvironment")
        tex.image = bpy.data.images.load(str(image))
        tex.image.colorspace_settings.name = 'Non-Color'
        tex.interpolation = 'Closest'
        nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    # Environment importance sampling is light sampling, which the OSL portal cannot use;
    # the reference is BSDF-only sampling, so keep the world out of light sampling too.
    world.cycles.sampling_method = 'NONE'
    return world


def set_sky_world(scene, sun_elevation=0.5, sun_rotation=0.0, strength=1.0, sky_type=None):
    """A Sky Texture world (Blender's default sky type unless `sky_type`, its sun disc on),
    importance-sampled by Cycles as Blender's default ('AUTOMATIC')."""
    import bpy
    world = bpy.data.worlds.new("flowbsdf sky")
    scene.world = world
    if world.node_tree is None:
        world.use_nodes = True
    nt = world.node_tree
    bg = next(n for n in nt.nodes if n.type == 'BACKGROUND')
    bg.inputs["Strength"].default_value = strength
    sky = nt.nodes.new("ShaderNodeTexSky")
    if sky_type is not None:
        sky.sky_type = sky_type
    sky.sun_elevation, sky.sun_rotation = sun_elevation, sun_rotation
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    world.cycles.sampling_method = 'AUTOMATIC'
    return world


def add_lamp(scene, lamp_type, location, target=(0.0, 0.0, 0.0), visible_camera=True, **settings):
    """A lamp at `location` whose -Z (where spot, sun and area lamps shine) points at `target`;
    `settings` are the light data's attributes. Visible to the camera as lamps made in the UI
    are (bpy.data lamps start hidden from it)."""
    import bpy
    from mathutils import Vector
    light = bpy.data.lights.new(f"{lamp_type.lower()} lamp", lamp_type)
    for key, value in settings.items():
        setattr(light, key, value)
    ob = bpy.data.objects.new(light.name, light)
    ob.visible_camera = visible_camera
    scene.collection.objects.link(ob)
    ob.location = location
    ob.rotation_euler = (Vector(target) - Vector(location)).to_track_quat('-Z', 'Y').to_euler()
    return ob


def add_sphere(scene, material=None, radius=1.0, segments=128, rings=64):
    import bpy
    import bmesh
    mesh = bpy.data.meshes.new("sphere")
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=rings, radius=radius)
    bm.to_mesh(mesh)
    bm.free()
    for p in mesh.polygons:
        p.use_smooth = True
    ob = bpy.data.objects.new("sphere", mesh)
    scene.collection.objects.link(ob)
    if material is not None:
        ob.data.materials.append(material)
    return ob


def add_plane(scene, material=None, size=2.0):
    import bpy
    mesh = bpy.data.meshes.new("plane")
    h = size / 2
    mesh.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
    ob = bpy.data.objects.new("plane", mesh)
    scene.collection.objects.link(ob)
    if material is not None:
        ob.data.materials.append(material)
    return ob


def _camera(scene, distance, **settings):
    """A camera at (0, 0, distance) looking down -z, with the given camera data settings."""
    import bpy
    cam = bpy.data.cameras.new("camera")
    for key, value in settings.items():
        setattr(cam, key, value)
    cam.clip_end = 100.0
    ob = bpy.data.objects.new("camera", cam)
    scene.collection.objects.link(ob)
    ob.location = (0.0, 0.0, distance)
    scene.camera = ob
    return ob


def ortho_camera(scene, distance=5.0, scale=2.0):
    """Looking down -z at the origin, image covering [-scale/2, scale/2]^2."""
    return _camera(scene, distance, type='ORTHO', ortho_scale=scale)


def material_with(nodes_fn, name="m"):
    """A material whose surface is what nodes_fn(tree) returns (a shader output socket)."""
    import bpy
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    tree = mat.node_tree
    for n in list(tree.nodes):
        if n.bl_idname != "ShaderNodeOutputMaterial":
            tree.nodes.remove(n)
    out = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial")
    tree.links.new(nodes_fn(tree), out.inputs["Surface"])
    return mat


def render(scene):
    """Render the scene; (H, W, 3) float32, top row first."""
    import bpy
    import OpenEXR
    fd, path = tempfile.mkstemp(suffix=".exr", prefix="flowbsdf_render_")
    os.close(fd)
    try:
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True, scene=scene.name)
        ch = OpenEXR.File(path).channels()
        if "RGBA" in ch:
            img = ch["RGBA"].pixels[..., :3]
        elif "RGB" in ch:
            img = ch["RGB"].pixels
        else:
            img = np.stack([ch[c].pixels for c in "RGB"], -1)
        return np.array(img, np.float32)
    finally:
        Path(path).unlink(missing_ok=True)


def seconds_per_spp(scene, lo, hi, clock=None):
    """Render time per sample at the scene's settings: from renders at lo and hi spp, so each
    render's fixed cost (scene sync, shader compilation) cancels. `clock` time.perf_counter
    (wall) by default, or time.process_time (this process's CPU: Cycles' threads)."""
    import time
    clock = clock or time.perf_counter
    secs = []
    for spp in (lo, hi):
        scene.cycles.samples = spp
        t0 = clock()
        render(scene)
        secs.append(clock() - t0)
    return (secs[1] - secs[0]) / (hi - lo)


SEED_ATTRIBUTE = "flowbsdf_test_seed"


def render_seeds(scene, seeds):
    """Renders with Cycles seeds 0..seeds-1: (seeds, H, W, 3), where the seed's own part
    matters (the film-stratified u's per-render rotation); else render_parts, without a
    shader compilation per seed. Cycles keeps the scene between them (persistent data: no
    second sync, BVH or world map).
    With OSL on and a Learned BSDF's film-stratified u, the node's handlers would write each
    seed into the shader's Seed input, a constant that Cycles compiles into the shader (~6 s of
    CPU a render of a 16² sphere, against 0.02 s of sampling at 16 spp): seed 0 renders so, then
    the handlers stand aside and Seed reads the seed from an object attribute (Attribute node
    -> Seed; each mesh object's custom property), one compilation in all: the same images bit
    for bit (test_cycles.py: _assert_render_seeds_is_the_handlers_render)."""
    imgs = []
    keep = scene.render.use_persistent_data
    scene.render.use_persistent_data = True
    linked = []
    try:
        for seed in range(seeds):
            scene.cycles.seed = seed
            if seed == 1:
                linked = _seed_from_attribute(scene)
            for ob in (scene.objects if linked else ()):
                if ob.type == 'MESH':
                    ob[SEED_ATTRIBUTE] = seed
                    ob.update_tag()
            imgs.append(render(scene))
    finally:
        scene.render.use_persistent_data = keep
        _seed_from_handlers(scene, linked)
    return np.array(imgs)


def _seed_from_attribute(scene):
    """Where the scene renders a Learned BSDF's OSL shader with film-stratified u (its handlers
    registered, its FilmFilter set by them): link an object Attribute node to the script's Seed
    and take the node's handlers out. Returns [(tree, attribute node)] and the handlers taken
    out, for _seed_from_handlers; [] where nothing is to do."""
    import bpy
    if not scene.cycles.shading_system:
        return []
    from blender_addon.render import node as lb, osl_script
    handlers = [(h, fn) for h, fn in lb._handlers() if fn in h]
    if not handlers:
        return []
    scripts = [s for s in (tree.nodes.get(osl_script.SCRIPT) for tree in bpy.data.node_groups)
               if s is not None and s.bl_idname == "ShaderNodeScript" and "Seed" in s.inputs
               and s.inputs["FilmFilter"].default_value > 0 and not s.inputs["Seed"].is_linked]
    if not scripts:
        return []
    for h, fn in handlers:
        h.remove(fn)
    out = []
    for script in scripts:
        tree = script.id_data
        attr = tree.nodes.new("ShaderNodeAttribute")
        attr.attribute_type = 'OBJECT'
        attr.attribute_name = SEED_ATTRIBUTE
        tree.links.new(attr.outputs["Fac"], script.inputs["Seed"])
        out.append((tree, attr))
    return [out, handlers]


def _seed_from_handlers(scene, linked):
    """Undo _seed_from_attribute (the handlers write Seed again at the next render)."""
    if not linked:
        return
    attrs, handlers = linked
    for tree, attr in attrs:
        tree.nodes.remove(attr)
    for h, fn in handlers:
        if fn not in h:
            h.append(fn)
    for ob in scene.objects:
        if SEED_ATTRIBUTE in ob.keys():
            del ob[SEED_ATTRIBUTE]


def render_parts(scene, parts):
    """`parts` renders of scene.cycles.samples each, disjoint parts of one render's samples
    (Cycles' sample subset; one seed): (parts, H, W, 3). Cycles keeps the scene between them
    (persistent data: no second sync, BVH, shader compilation or world map); a new seed would
    compile the Learned BSDF's OSL shader anew (its Seed input: 3-5 s a render of a 16² scene).
    Their spread is a part's noise: the parts' means of one seed against another seed's, per
    pixel, z 0.79-1.07 rms (16², 6 parts of 64 spp, a learned and a Diffuse floor under a point
    lamp, a sphere under a sky; measured with scripts that are not kept)."""
    cy = scene.cycles
    keep = (scene.render.use_persistent_data, cy.samples, cy.use_sample_subset, cy.sample_offset,
            cy.sample_subset_length)
    spp = cy.samples
    scene.render.use_persistent_data = True
    cy.samples, cy.use_sample_subset, cy.sample_subset_length = spp * parts, True, spp
    try:
        imgs = []
        for part in range(parts):
            cy.sample_offset = part * spp
            imgs.append(render(scene))
    finally:
        (scene.render.use_persistent_data, cy.samples, cy.use_sample_subset, cy.sample_offset,
         cy.sample_subset_length) = keep
    return np.array(imgs)


def hashed_u(group_node):
    """Make a Learned BSDF node's OSL shader hash u on camera rays too (what it does without the
    scene's film settings), for comparisons. Unregisters the add-on's handlers, which would set
    the film settings again before the render."""
    from blender_addon.render import node as lb, osl_script
    lb.unregister()
    group_node.node_tree.nodes[osl_script.SCRIPT].inputs["FilmFilter"].default_value = 0


def sphere_view(width, height, scale=2.0, radius=1.0):
    """Per pixel of ortho_camera's image: the sphere's normal (H, W, 3) (camera along -z, image
    x = world x, image rows top to bottom = world y descending) and the hit mask."""
    x = (np.arange(width) + 0.5) / width * scale - scale / 2
    y = scale / 2 - (np.arange(height) + 0.5) / height * scale * height / width
    X, Y = np.meshgrid(x, y)
    r2 = (X * X + Y * Y) / radius ** 2
    hit = r2 < 1
    n = np.stack([X / radius, Y / radius, np.sqrt(np.maximum(1 - r2, 0))], -1)
    return n, hit


def persp_camera(scene, distance=6.0, fov_deg=22.0):
    """Perspective camera at (0, 0, distance) looking down -z (image up = world +y), `fov_deg`
    across the larger image side (Blender's sensor fit AUTO, as the reference tracer's fov)."""
    import math
    return _camera(scene, distance, type='PERSP', sensor_fit='AUTO', angle=math.radians(fov_deg))


def sphere_view_persp(width, height, distance=6.0, fov_deg=22.0, radius=1.0, min_cos=0.05):
    """Per pixel of persp_camera's image: the unit sphere's normal at the pixel centre (H, W, 3),
    the view cosine there, and a mask of pixels whose whole footprint (centre and 4 corners)
    hits the sphere with cos(view, normal) > min_cos at the centre (no silhouette pixels)."""
    half = np.tan(np.radians(fov_deg) / 2) / max(width, height)
    o = np.array([0.0, 0.0, distance])

    def cast(px, py):
        x, y = px * 2 - width, height - py * 2
        d = np.stack([half * x, half * y, -np.ones_like(x)], -1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        b = d @ o
        disc = b * b - (o @ o - radius * radius)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        return disc > 0, (o + t[..., None] * d) / radius, d

    X, Y = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    hit, n, d = cast(X, Y)
    cos = np.where(hit, -np.sum(n * d, -1), 0.0)
    inner = hit & (cos > min_cos)
    for dx in (-0.5, 0.5):
        for dy in (-0.5, 0.5):
            inner &= cast(X + dx, Y + dy)[0]
    return n, cos, inner


# ------------------------------------------------------------------------------ small tables

SMALL_BINS = np.radians([0.0, 30.0, 60.0, 80.0, 89.5])


def small_tables(source, name, folder, coords=None):
    """16 x 16-cell tables over SMALL_BINS from the ideal tabulation (cells over `coords`, the
    default's when None), saved as <folder>/<name>.exr."""
    from bake.core.ideal import IdealSampler
    from bake.materials import open_material
    from bake.core.tabulate import build_tables
    mat = open_material(source)
    tab = build_tables(mat, IdealSampler(mat, resolution=64), SMALL_BINS, rows=16, cols=16, grid=96, coords=coords)
    tab.meta["material"] = name
    tab.save(folder / f"{name}.exr")
    return folder / f"{name}.exr"


def aniso_small_tables(folder, coords=None):
    """Small anisotropic tables (GGX 0.3 x 0.05 at 20 deg: 3 theta x 4 phi bins over pi, cells
    over `coords`, the half vector by default), saved as <folder>/brushed.exr."""
    from bake.core.ideal import IdealSampler
    from bake.materials import open_material
    from bake.core.tabulate import build_tables
    mat = open_material({"kind": "analytic", "model": "ggx", "alpha_x": 0.3, "alpha_y": 0.05, "angle": 20})
    phi_bins = np.arange(4) * (mat.phi_period / 4)
    tab = build_tables(mat, IdealSampler(mat, resolution=48), np.radians([0.0, 45.0, 89.5]), rows=16, cols=16,
                       grid=64, phi_bins=phi_bins, coords=coords)
    path = folder / "brushed.exr"
    tab.meta["material"] = "brushed"
    tab.save(path)
    return path


def albedo_and_variance(tab, wi):
    """E[W] and Var[W] of the baked tables at one wi (local frame): what a furnace pixel
    converges to, and the per-sample variance of a table sampler's weight there (MixedTables:
    of the part that samples wi)."""
    from bake.core.mixed_tables import MixedTables
    if isinstance(tab, MixedTables):
        tab = tab.parts[tab.part_at(np.arccos(np.clip(wi[2], -1.0, 1.0)))]
    bins, _ = tab._bins(wi[None])
    m = tab._lerp(tab._m, bins)[0]
    w = tab._lerp(tab._w.astype(float), bins)[0]
    mean = np.einsum("rc,rck->k", m, w)
    return mean, np.maximum(np.einsum("rc,rck->k", m, w * w) - mean ** 2, 0.0)


def assert_furnace(got, ref, var, spp):
    """Per-pixel z-scores and the mean over the sphere within Monte Carlo error. A smooth-shaded
    mesh loses the samples that go below its geometric normal (~5e-4 here, as Cycles' own
    closures do): allowed, beside the MC error."""
    sigma = np.sqrt(var / spp + (1e-3 * ref) ** 2)
    z = (got - ref) / sigma
    assert np.sqrt(np.mean(z ** 2)) < 1.5, np.sqrt(np.mean(z ** 2, axis=0))
    rel = (got.mean(0) - ref.mean(0)) / ref.mean(0)
    sigma_mean = np.sqrt(np.sum(var / spp, axis=0)) / len(ref) / ref.mean(0)
    assert np.all(np.abs(rel) < 4 * sigma_mean + 1.5e-3), (rel, sigma_mean)


def lambert_tables(folder, albedo=0.8):
    """Baked tables of a Lambertian (ideal tabulation, 24 x 24 cells, 5 theta bins): the learned
    material whose Cycles twin is a Diffuse BSDF of that albedo. Returns the .exr path."""
    import numpy as np
    from bake.core.ideal import IdealSampler
    from bake.materials import open_material
    from bake.core.tabulate import build_tables
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": albedo})
    tab = build_tables(mat, IdealSampler(mat, resolution=64), np.radians([0.0, 30.0, 60.0, 80.0, 89.5]),
                       rows=24, cols=24, grid=96)
    tab.meta["material"] = "lambert"
    path = Path(folder) / "lambert.exr"
    tab.save(path)
    return path


def grouped_tables(source, name, folder):
    """16 x 16-cell tables of two layout groups joined at 50 deg (bins 0, 30, 50 | 50, 70, 89.9;
    tabulate.join_groups), saved as <folder>/<name>.exr."""
    from bake.core.ideal import IdealSampler
    from bake.materials import open_material
    from bake.core.tabulate import build_tables, join_groups
    mat = open_material(source)
    ideal = IdealSampler(mat, resolution=64)
    tab = join_groups([build_tables(mat, ideal, np.radians(b), rows=16, cols=16, grid=96, window=None)
                       for b in ([0.0, 30.0, 50.0], [50.0, 70.0, 89.9])])
    tab.meta["material"] = name
    tab.save(folder / f"{name}.exr")
    return folder / f"{name}.exr"


def mixed_tables(source, name, folder):
    """Tables of two layout groups of their own resolutions joined at 50 deg (bins 0, 30, 50 at
    12 x 16 cells | 50, 70, 89.9 at 24 x 20: tables.MixedTables), saved as <folder>/<name>.exr."""
    from bake.core.ideal import IdealSampler
    from bake.materials import open_material
    from bake.core.tabulate import build_tables, join_groups
    mat = open_material(source)
    ideal = IdealSampler(mat, resolution=64)
    tab = join_groups([build_tables(mat, ideal, np.radians(b), rows=r, cols=c, grid=96, window=None)
                       for b, r, c in (([0.0, 30.0, 50.0], 12, 16), ([50.0, 70.0, 89.9], 24, 20))])
    tab.meta["material"] = name
    tab.save(folder / f"{name}.exr")
    return folder / f"{name}.exr"
