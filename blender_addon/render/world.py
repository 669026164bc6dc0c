"""The world's importance map for the Learned BSDF's shaders (bake/export/world_map.py).

`bake_world_map(scene, folder)` makes the world's equirectangular radiance map and writes the
texture the shaders sample: an Environment Texture world straight from its image's texels
(box-averaged: nothing missed), a world of one colour as that colour; any other world — a
Sky Texture, mixes, procedurals — by rendering it with Cycles (a temporary scene holding only
a panoramic camera, so nothing occludes the world). A Sky Texture's sun disc gets techniques of its own (`sun_of`): the SVM
graph draws portal directions in its cone; the OSL shader lights it by next-event estimation
with the disc's radiance fitted to a render of it (`bake_sun`: Cycles' own law, exact to 1e-4),
and the map has the disc painted out (`without_sun`). The textures are named after the world's state (`world_key`):
its node tree, their values and images, and the frame when the world is animated; an
unchanged world reuses its file.

The map decides only where the shaders draw directions (Cycles evaluates the true world
along them), so an outdated map costs noise, never bias. That is why it is rebuilt outside
renders (a render cannot start another one): when a material is bound, when a file loads and
shortly after the world changes (`schedule`), and before a render only if it is missing.
"""
import hashlib
import math
import os
import tempfile
from pathlib import Path

import bpy

from .. import deps

WIDTH, HEIGHT, SPP = 1024, 512, 16
# An Environment Texture world's map keeps its image's own pixels up to this size: next-event
# estimation reads the image itself, so every map pixel holding several texels of a small sun
# draws directions uniformly over them and costs variance (measured, numpy, a Lambertian under
# the 2048 x 1024 rendered default sky, 64 stratified samples: 0.017-0.06 per sample at the
# image's resolution, 0.44-2.8 at half of it).
IMAGE_WIDTH, IMAGE_HEIGHT = 2048, 1024
# The shares of portal directions drawn from the world map and from a Sky Texture's sun disc:
# no map for a near-constant world, where the tables alone are the better choice.
SHARE = 0.5
# ... by material (material_share), for a map with neither a small sun nor a Sky Texture's sun:
# a matte material's cosine-like lobe finds a broad sun poorly, a glossy one's narrow lobe is
# the better guide. Measured on the lights acceptance's sunny HDRI (peak 38), 96 spp x 8,
# per-sample variance x CPU time per spp at a share of 0.65 over 0.5: paper_white (matte
# fraction 0.88) 0.69 OSL / 0.74 SVM, cm_military_green (0.23) 1.06 OSL, chm_mint (0.14) 1.64
# OSL / 1.54 SVM; 0.3: paper_white 2.0 OSL (scripts/map_share_render.py). The share runs
# linearly in the matte fraction.
SHARE_GLOSSY, SHARE_MATTE = 0.35, 0.7
# ... and for a map with a small sun (peak >= BRIGHT, below): most of its light is in a few pixels
# only the map finds. Rendered (SVM, the lights acceptance's sky, 4 x 32 spp, per-sample variance
# at 0.8 over 0.5): paper_white 0.87, cm_military_green 0.99, chm_mint 0.79; scripts/map_share_model.py's numpy
# model had promised 0.31 and 0.42, so it misses something of the render. OSL samples such pixels
# by next-event estimation instead (per-sample variance 4.5x below the SVM's on paper_white).
SMALL_SUN_SHARE = 0.8
SUN_SHARE, SUN_MAP_SHARE = 0.3, 0.2     # with a sun: its disc, and the map for the sky
FLAT = 1.5          # the map's peak pdf over a uniform sphere's, below which the world is "flat"
# OSL: an image world whose map peaks at BRIGHT times a uniform sphere's pdf or more (a small sun)
# gets next-event estimation of its pixels that bright, drawn from a map of those pixels alone
# (WorldMap.bright_only; drawn from the whole map, a quarter of the draws fell in dimmer pixels
# and were lost); the rest of it, and a world with no such pixels, is sampled through the
# portal's mixture with the map (no shadow rays: measured on the
# lights acceptance's sunny HDRI, peak 38: the same noise per sample as next-event estimation of
# the whole map, which cost 2.6x the time per sample; the rendered sky's sun: 16 pixels of
# 1e4-1.6e5x uniform hold 75 % of its light, the other pixels are below 3x).
BRIGHT = 100.0
# The image of the sun disc its radiance is fitted to (OSL's next-event estimation of a Sky
# Texture's sun): pixels a side, samples per pixel, and its half width over the disc's.
SUN_RES, SUN_SPP, SUN_MARGIN = 64, 4, 1.25


_LAYOUT_PROPS = {"rna_type", "location", "location_absolute", "width", "height", "select", "dimensions",
                 "name", "label", "show_options", "show_preview", "hide", "show_texture", "warning_propagation"}


def _value(v):
    if isinstance(v, float):
        return round(v, 6)
    if isinstance(v, (str, int, bool)) or v is None:
        return v
    try:
        return tuple(_value(x) for x in v)
    except TypeError:
        return repr(v)


def world_key(scene):
    """A content hash of the scene's world as it renders now (nodes, values, images, frame when animated)."""
    world = scene.world
    if world is None:
        return None
    h = hashlib.sha256()
    h.update(repr((world.name, WIDTH, HEIGHT, SPP, IMAGE_WIDTH, IMAGE_HEIGHT)).encode())
    tree = world.node_tree      # (use_nodes is deprecated in 5.0; worlds made by Blender have a tree)
    if tree is None:
        h.update(repr(_value(world.color)).encode())
    else:
        for node in sorted(tree.nodes, key=lambda n: n.name):
            h.update(repr((node.name, node.bl_idname)).encode())
            for prop in node.bl_rna.properties:
                if prop.identifier in _LAYOUT_PROPS:
                    continue
                value = getattr(node, prop.identifier, None)
                if isinstance(value, bpy.types.Image):
                    file = bpy.path.abspath(value.filepath)
                    value = (value.filepath, os.path.getmtime(file) if os.path.isfile(file) else 0)
                elif prop.type in ('POINTER', 'COLLECTION'):
                    continue
                h.update(repr((prop.identifier, _value(value))).encode())
            for sock in node.inputs:
                if not sock.is_linked and hasattr(sock, "default_value"):
                    h.update(repr(_value(sock.default_value)).encode())
        for link in tree.links:
            h.update(repr((link.from_node.name, link.from_socket.identifier,
                           link.to_node.name, link.to_socket.identifier)).encode())
    if world.animation_data or (tree is not None and tree.animation_data):
        h.update(repr(scene.frame_current).encode())
    return h.hexdigest()


def sun_of(scene):
    """(direction toward the sun, cos of its half angle) of the world's Sky Texture with a sun
    disc; None without one, or when its Vector input is linked (mapped)."""
    import math
    world = scene.world
    tree = world.node_tree if world is not None else None
    if tree is None:
        return None
    for node in tree.nodes:
        if (node.bl_idname == "ShaderNodeTexSky" and not node.mute and getattr(node, "sun_disc", False)
                and node.sky_type not in ("PREETHAM", "HOSEK_WILKIE")
                and not any(sock.is_linked for sock in node.inputs) and node.outputs[0].is_linked):
            e, r = node.sun_elevation, node.sun_rotation
            # measured against the rendered map: azimuth pi / 2 - rotation in world space
            return ((math.cos(e) * math.sin(r), math.cos(e) * math.cos(r), math.sin(e)),
                    math.cos(0.5 * node.sun_size))
    return None


def shader_inputs(path, meta, sun, env=None, sun_radiance=None, bright=None):
    """The shaders' world inputs for a map (path, its metadata or None), a sun (sun_of), an
    image world the OSL shader can read exactly (exact_environment), the sun disc's radiance
    (sun_fit's: OSL samples the sun by next-event estimation) and the map of the image's bright
    pixels (bright_path: OSL's next-event estimation of a small sun)."""
    flat = meta is None or meta.get("peak", 0.0) <= FLAT
    small_sun = meta is not None and meta.get("peak", 0.0) >= BRIGHT
    share = 0.0 if flat else SMALL_SUN_SHARE if small_sun else SHARE
    # The SVM back end's control variate (svm.py) pays where the world has a small bright light
    # (the portal finds it all or nothing; Cycles' light sampling of the closures does not): a
    # small sun or a Sky Texture's sun (and lamps: node._world_inputs). Elsewhere the portal's
    # mixture alone is better: the lights acceptance's sunny HDRI (peak 38), equal time, MSE
    # with / without it: paper_white 4.60e-4 / 1.39e-4, cm_military_green 1.22e-5 / 4.2e-6,
    # chm_mint 2.95e-3 / 1.58e-3; a constant world, per-pixel variance 64 spp: paper_white
    # 3.4e-4 / 2.6e-6, chm_mint 4.8e-4 / 1.1e-4.
    # LightDirection: where that small light is, the direction the SVM graph matches its control
    # variate to (svm._cv_matched: the closures carry all of the light's part).
    inputs = {"World": str(path) if meta else "", "WorldShare": share,
              "ControlVariate": 1.0 if small_sun or sun is not None else 0.0,
              "LightDirection": tuple(meta["light"]) if small_sun and "light" in meta else (0.0, 0.0, 0.0),
              "SunDirection": (0.0, 0.0, 1.0), "SunCos": 1.0, "SunAngle": 0.0, "SunShare": 0.0,
              "EnvImage": "", "EnvStrength": 0.0, "EnvLinear": 1, "EnvMap": "",
              "SunNEE": 0, "SunSky": (0.0, 0.0, 0.0, 1.0), "SunBase": (0.0, 0.0, 0.0, 1.0),
              "SunRise": (0.0, 0.0, 0.0, 1.0)}
    if sun is not None:
        inputs.update(SunDirection=sun[0], LightDirection=tuple(sun[0]), SunCos=sun[1], SunAngle=math.acos(sun[1]),
                      SunShare=SUN_SHARE, WorldShare=0.0 if flat else SUN_MAP_SHARE)
        if sun_radiance is not None:
            # (colour sockets are RGBA)
            inputs.update(SunNEE=1, **{key: (*sun_radiance[name], 1.0) for key, name in
                                       (("SunSky", "sky"), ("SunBase", "base"), ("SunRise", "rise"))})
    if env is not None and small_sun and bright is not None and Path(bright).is_file():
        inputs.update(EnvImage=env[0], EnvStrength=env[1], EnvLinear=env[2], EnvMap=str(bright))
    return inputs


def matte_fraction(fit):
    """The diffuse share of a closure fit's albedo at normal incidence (luminance), in [0, 1];
    None without a fit."""
    if not fit:
        return None
    lum = lambda c: 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]        # noqa: E731
    total = lum(fit["fit_albedo"][0]) if "fit_albedo" in fit else 0.0
    return min(max(lum(fit["diffuse"][0]) / total, 0.0), 1.0) if total > 0.0 else None


def material_share(inputs, matte):
    """The world inputs (shader_inputs) for one material of matte fraction `matte`
    (matte_fraction): a plain map's share (SHARE) becomes SHARE_GLOSSY .. SHARE_MATTE; the other
    cases and a material without a fit keep theirs."""
    if matte is None or inputs.get("WorldShare") != SHARE or inputs.get("SunShare", 0.0) > 0.0:
        return inputs
    return {**inputs, "WorldShare": SHARE_GLOSSY + (SHARE_MATTE - SHARE_GLOSSY) * matte}


# Colour spaces whose float values Cycles renders as they are in the file (what OSL's texture()
# reads): only then is the shader's own lookup of the image the world's radiance.
LINEAR_SPACES = {"Linear", "Linear Rec.709", "Linear CIE-XYZ E", "Non-Color", "Raw", "Scene Linear"}


def exact_environment(scene):
    """(file, strength, 1 for linear / 0 for closest interpolation) when the world is an
    Environment Texture whose radiance the OSL shader can read itself exactly: a float image
    file in a linear colour space, Linear or Closest interpolation, unmapped; else None."""
    found = _environment_image(scene)
    if found is None:
        return None
    image, strength = found
    tree = scene.world.node_tree
    env = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeTexEnvironment" and n.image == image)
    path = bpy.path.abspath(image.filepath, library=image.library) if image.source == 'FILE' else ""
    if (not path or image.packed_file is not None or not os.path.isfile(path) or not image.is_float
            or image.colorspace_settings.name not in LINEAR_SPACES or env.interpolation not in ('Linear', 'Closest')):
        return None
    return os.path.abspath(path), strength, 1 if env.interpolation == 'Linear' else 0


def map_path(folder, key):
    return Path(folder) / f"world-{key[:16]}.exr"


def sun_path(folder, key):
    return Path(folder) / f"world-{key[:16]}.sun.json"


def read_sun(path):
    """The sun disc's radiance fit (sun_fit) saved at path, None when missing or unreadable."""
    import json
    try:
        fit = json.loads(Path(path).read_text())
        return fit if all(len(fit.get(k, ())) == 3 for k in ("sky", "base", "rise")) else None
    except (OSError, ValueError, AttributeError):
        return None


def sun_frame(direction):
    """(x, y) axes (world space) of the sun's image (render_sun): x horizontal unless the sun is
    near the zenith."""
    import numpy as np
    d = np.asarray(direction, float)
    x = np.cross(d, (0.0, 0.0, 1.0) if abs(d[2]) < 0.999 else (0.0, 1.0, 0.0))
    x /= np.linalg.norm(x)
    return x, np.cross(x, d)


def render_sun(scene, sun, path=None, res=SUN_RES, spp=SUN_SPP):
    """The world around its sun (sun_of), res x res (rows from the top, RGB): a perspective
    camera at the origin looking at the sun, sun_frame's x to the right and y up, SUN_MARGIN
    times the disc's radius either side, every sample at its pixel's centre (kept in the
    OpenEXR `path` when given)."""
    from mathutils import Matrix
    x, y = sun_frame(sun[0])
    z = [-c for c in sun[0]]                # a camera looks along its -Z

    def perspective(cam_data, cam):
        cam_data.type = 'PERSP'
        cam_data.sensor_fit = 'HORIZONTAL'
        cam_data.angle = 2.0 * math.atan(SUN_MARGIN * math.tan(math.acos(sun[1])))
        cam_data.clip_start = 1e-3
        cam.matrix_world = Matrix(((x[0], y[0], z[0], 0.0), (x[1], y[1], z[1], 0.0),
                                   (x[2], y[2], z[2], 0.0), (0.0, 0.0, 0.0, 1.0)))
    return _render_world_view(scene, perspective, res, res, spp, path, at_centres=True)


def sun_pixels(res, sun):
    """Per pixel of render_sun's image: its centre's angle from the sun over the disc's half
    angle (r), and its height across the disc (h: 0 the disc's bottom, 1 its top)."""
    import numpy as np
    t = SUN_MARGIN * math.tan(math.acos(sun[1]))
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    a, b = np.meshgrid(c * t, -c * t)
    x, y = sun_frame(sun[0])
    d = np.asarray(sun[0], float) + a[..., None] * x + b[..., None] * y
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    half = math.acos(sun[1])
    r = np.arccos(np.clip(d @ np.asarray(sun[0], float), -1.0, 1.0)) / half
    height = (np.arcsin(np.clip(d[..., 2], -1, 1)) - math.asin(sun[0][2])) / (2.0 * half) + 0.5
    return r, height


def limb(r):
    """The Sky Texture's limb darkening of its sun disc at r (angle over the half angle)."""
    import numpy as np
    return 1.0 - 0.6 * (1.0 - np.sqrt(np.clip(1.0 - r * r, 0.0, 1.0)))


def sun_fit(px, sun):
    """The sun disc's radiance as the OSL shader models it, fitted to render_sun's pixels (px):
    sky + (base + rise h) limb(r) per channel — the Sky Texture's disc: a colour linear in
    height, limb-darkened, over the sky (here the mean of a ring just outside the disc). A dict
    of RGB lists (sky, base, rise), or None when the disc is not in the image (below the
    horizon)."""
    import numpy as np
    r, height = sun_pixels(px.shape[0], sun)
    ring, inner = (r > 1.1) & (r < 1.2), r < 0.98
    sky = px[ring].mean(0)
    if not ring.any() or inner.sum() < 3 or px[inner].mean() < 10.0 * max(sky.mean(), 1e-12):
        return None
    basis = np.stack([limb(r[inner]), limb(r[inner]) * height[inner]], -1)
    coef, *_ = np.linalg.lstsq(basis, px[inner] - sky, rcond=None)
    return {"sky": sky.tolist(), "base": coef[0].tolist(), "rise": coef[1].tolist()}


def sun_model(fit, r, height):
    """sun_fit's radiance at (r, height) (numpy; the shader's sun_radiance)."""
    import numpy as np
    return (np.asarray(fit["sky"]) + limb(r)[..., None]
            * (np.asarray(fit["base"]) + height[..., None] * np.asarray(fit["rise"])))


def bake_sun(scene, sun, path):
    """sun_fit of the world's sun, rendered and saved at path (JSON); None without a disc."""
    import json
    fit = sun_fit(render_sun(scene, sun), sun)
    with deps.bake_module("io.files").atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(fit))
    return fit


def render_world(scene, width=WIDTH, height=HEIGHT, spp=SPP, path=None):
    """The scene's world as an equirectangular radiance image (height, width, 3), row 0 the
    zenith, column u = 0.5 - atan2(y, x) / 2 pi (bake/export/world_map.py); with `path`, the 32-bit
    OpenEXR Cycles wrote is kept there too (the reference tracer reads it as its environment)."""
    def equirectangular(cam_data, cam):
        cam_data.type = 'PANO'
        if hasattr(cam_data, "panorama_type"):
            cam_data.panorama_type = 'EQUIRECTANGULAR'
        else:                                   # Blender < 4.0
            cam_data.cycles.panorama_type = 'EQUIRECTANGULAR'
        cam.rotation_euler = (1.5707963267948966, 0.0, -1.5707963267948966)   # measured: Blender's convention
    return _render_world_view(scene, equirectangular, width, height, spp, path)


def _render_world_view(scene, set_camera, width, height, spp, path=None, at_centres=False):
    """Render the scene's world alone (a temporary scene holding only a camera, which
    set_camera(camera data, camera object) sets up) with Cycles on the CPU: the pixels (height,
    width, 3), row 0 the top; the 32-bit OpenEXR kept at `path` when given. A one-pixel box
    filter, or with at_centres every sample at its pixel's centre (a Gaussian of width 0.01:
    Cycles' box is one pixel wide whatever its width)."""
    tmp = bpy.data.scenes.new("FlowBSDF world")
    cam_data = bpy.data.cameras.new("FlowBSDF world")
    cam = bpy.data.objects.new("FlowBSDF world", cam_data)
    if path is None:
        fd, out = tempfile.mkstemp(suffix=".exr", prefix="flowbsdf_world_")
        os.close(fd)
    else:
        out = str(path)
    try:
        tmp.world = scene.world
        tmp.frame_current = scene.frame_current
        tmp.collection.objects.link(cam)
        tmp.camera = cam
        set_camera(cam_data, cam)
        r = tmp.render
        r.engine = 'CYCLES'
        r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
        r.image_settings.file_format = 'OPEN_EXR'
        r.image_settings.color_depth = '32'
        r.filepath = out
        tmp.cycles.device = 'CPU'
        tmp.cycles.samples = spp
        tmp.cycles.use_adaptive_sampling = False
        tmp.cycles.use_denoising = False
        tmp.cycles.pixel_filter_type = 'GAUSSIAN' if at_centres else 'BOX'
        if at_centres:
            tmp.cycles.filter_width = 0.01
        tmp.view_settings.view_transform = 'Standard'
        bpy.ops.render.render(write_still=True, scene=tmp.name)
        image = bpy.data.images.load(out)
        try:
            import numpy as np
            px = np.array(image.pixels[:], np.float32).reshape(height, width, image.channels)
        finally:
            bpy.data.images.remove(image)
        return px[::-1, :, :3]          # Blender's pixels start at the bottom row
    finally:
        bpy.data.scenes.remove(tmp)
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(cam_data)
        if path is None:
            Path(out).unlink(missing_ok=True)


def _environment_image(scene):
    """(image, strength) when the world is a Background lit by an equirectangular Environment
    Texture as it is (no mapping, constant strength), else None."""
    tree = scene.world.node_tree if scene.world is not None else None
    bg = next((n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground"), None) if tree else None
    if bg is None or bg.inputs["Strength"].is_linked or not bg.inputs["Color"].is_linked:
        return None
    env = bg.inputs["Color"].links[0].from_node
    if (env.bl_idname != "ShaderNodeTexEnvironment" or env.image is None or env.projection != 'EQUIRECTANGULAR'
            or any(sock.is_linked for sock in env.inputs) or not env.image.has_data and not env.image.filepath):
        return None
    return env.image, float(bg.inputs["Strength"].default_value)


def image_radiance(scene, width=IMAGE_WIDTH, height=IMAGE_HEIGHT):
    """An Environment Texture world's radiance straight from its image, box-averaged down to at
    most width x height (Blender's equirectangular convention, as the map's): every texel
    counts, so a sun a fraction of a map pixel wide is never missed (a rendered map's few
    samples per pixel can miss it). None for other worlds (render_world then)."""
    found = _environment_image(scene)
    if found is None:
        return None
    import numpy as np
    image, strength = found
    w, h = image.size
    if w < 1 or h < 1:
        return None
    px = np.empty(w * h * image.channels, np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(h, w, image.channels)[::-1, :, :3]
    if not image.is_float:
        px = px ** 2.2          # display-encoded bytes, roughly linear: the map sets noise, not the image
    env = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeTexEnvironment" and n.image == image)
    if env.interpolation != 'Closest':
        # Interpolated, a texel's light spreads into its neighbours' cells: the mean of the
        # bilinear interpolant over each texel's cell is (1/8, 3/4, 1/8) of the texels per axis
        # (periodic in azimuth, clamped at the poles) (measured: without it a 2-texel sun, whose
        # light bleeds half a texel outwards, rendered 14 % dark at 256 spp).
        px = 0.75 * px + 0.125 * (np.roll(px, 1, axis=1) + np.roll(px, -1, axis=1))
        px = 0.75 * px + 0.125 * (np.concatenate([px[:1], px[:-1]]) + np.concatenate([px[1:], px[-1:]]))
    rows = np.linspace(0, h, min(h, height) + 1).astype(int)
    cols = np.linspace(0, w, min(w, width) + 1).astype(int)
    sums = np.add.reduceat(np.add.reduceat(px.astype(np.float64), rows[:-1], axis=0), cols[:-1], axis=1)
    return strength * sums / (np.diff(rows)[:, None, None] * np.diff(cols)[None, :, None])


def constant_radiance(scene, width=WIDTH, height=HEIGHT):
    """The radiance of a world that is one colour everywhere (a world without nodes, or whose
    Cycles output's Surface is unlinked or a Background with nothing linked to it) as the map
    rendering it would give: (height, width, 3); None for other worlds. Blender's default world
    and the black one of a lamp-lit scene are such worlds: rendering their map took 2-4 s here."""
    import numpy as np
    world = scene.world
    if world is None:
        return None
    tree = world.node_tree
    colour = tuple(world.color) if tree is None else (0.0, 0.0, 0.0)
    if tree is not None:
        outputs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputWorld" and n.is_active_output
                   and getattr(n, "target", "ALL") in ("ALL", "CYCLES")]
        if len(outputs) != 1:
            return None
        links = outputs[0].inputs["Surface"].links
        if links:
            bg = links[0].from_node
            if (bg.bl_idname != "ShaderNodeBackground" or bg.mute or not links[0].is_valid
                    or any(sock.is_linked for sock in bg.inputs)):
                return None
            strength = float(bg.inputs["Strength"].default_value)
            colour = tuple(strength * c for c in bg.inputs["Color"].default_value[:3])
    return np.broadcast_to(np.asarray(colour[:3], np.float64), (height, width, 3)).copy()


def without_sun(radiance, sun):
    """An equirectangular map (render_world's) with a sun's disc (sun_of) painted over by the sky
    around it: the shaders sample the sun by a technique of its own, and the map's few pixels
    holding it would draw most map samples into the disc."""
    if sun is None:
        return radiance
    import numpy as np
    h, w = radiance.shape[:2]
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (0.5 - (np.arange(w) + 0.5) / w) * 2.0 * np.pi
    st = np.sin(theta)[:, None]
    dirs = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(np.cos(theta)[:, None], (h, w))], -1)
    angle = np.arccos(np.clip(dirs @ np.asarray(sun[0], float), -1.0, 1.0))
    disc = np.arccos(sun[1]) + 1.5 * np.pi / h          # the disc and the pixels it bleeds into
    ring = (angle >= disc) & (angle < disc + 3.0 * np.pi / h)
    out = radiance.copy()
    if ring.any():
        out[angle < disc] = radiance[ring].mean(0)
    return out


def bake_world_map(scene, folder):
    """The shader's world inputs (shader_inputs) for the scene's world, its map rendered when
    missing; no map for no world, a black one, or where numpy/bake are missing."""
    key = world_key(scene)
    world_map = deps.bake_module("export.world_map")
    if key is None or world_map is None:
        return shader_inputs(None, None, None)
    path, sky_file, bright_file = map_path(folder, key), sky_path(folder, key), bright_path(folder, key)
    meta = world_map.read_world_meta(path)
    exact, sun = exact_environment(scene), sun_of(scene)
    small_sun = meta is not None and meta.get("peak", 0.0) >= BRIGHT
    if meta is None or (exact is None and not sky_file.is_file()) or \
            (small_sun and (not bright_file.is_file() or "light" not in meta)):
        try:
            radiance = image_radiance(scene)
            if radiance is None:
                radiance = constant_radiance(scene)
            if radiance is None:
                radiance = without_sun(render_world(scene), sun)
            wm = world_map.WorldMap(radiance)
            meta = {"key": key, "peak": wm.peak}
            if wm.peak >= BRIGHT:
                meta["light"] = [float(x) for x in wm.light_direction(BRIGHT / (4.0 * math.pi))]
                world_map.write_world_texture(bright_file, wm.bright_only(radiance, BRIGHT / (4.0 * math.pi)),
                                              {"key": key, "bright": BRIGHT})
            world_map.write_world_texture(path, wm, meta)
            if exact is None:
                write_sky(sky_file, radiance)
        except world_map.FlowBSDFError:         # black world: nothing to sample
            meta = None
        remove_superseded(folder)
    sun_file = sun_path(folder, key)
    radiance = read_sun(sun_file) if sun is not None else None
    if sun is not None and not sun_file.is_file():
        radiance = bake_sun(scene, sun, sun_file)
    return shader_inputs(path, meta, sun, _environment(exact, sky_file), radiance, bright_file)


def remove_superseded(folder):
    """Remove the world maps in `folder` (world-<key>.*) that no scene of the open .blend renders
    now: each world edit makes a new map (~5 MB) and the old one would stay forever. Not while a
    world is animated (its map changes with the frame: the other frames' maps are still wanted),
    and never a file an image of the .blend still reads from disk."""
    keys, animated = set(), False
    for scene in bpy.data.scenes:
        key = world_key(scene)
        if key is not None:
            keys.add(key[:16])
        world = scene.world
        if world is not None and (world.animation_data or (world.node_tree is not None
                                                            and world.node_tree.animation_data)):
            animated = True
    if animated:
        return []
    in_use = {os.path.normpath(bpy.path.abspath(i.filepath)) for i in bpy.data.images
              if i.filepath and i.packed_file is None and i.users}
    removed = []
    for path in Path(folder).glob("world-*"):
        key = path.name[len("world-"):].split(".")[0]
        if key in keys or os.path.normpath(str(path)) in in_use:
            continue
        try:
            path.unlink()
            removed.append(path)
        except OSError:
            pass
    return removed


def bright_path(folder, key):
    return Path(folder) / f"world-{key[:16]}.bright.exr"


def sky_path(folder, key):
    return Path(folder) / f"world-{key[:16]}.sky.exr"


def write_sky(path, radiance):
    """The map's radiance (rows from the zenith) as the float image the OSL shader reads."""
    import numpy as np
    rgba = np.concatenate([radiance, np.ones(radiance.shape[:2] + (1,))], -1).astype(np.float32)
    deps.bake_module("io.exrio").write_rgba_exr(path, rgba, "flowbsdf", {"sky": True})


def _environment(exact, sky_file):
    """What the OSL shader reads as the world's radiance for its next-event estimation: the
    world's own image (exact_environment), else the map's radiance (sky_path: the world as
    rendered, the sun painted out; at the map's resolution, read Closest). The shader uses it
    as a control variate (Cycles adds the true world), so an approximate image costs noise,
    never bias."""
    if exact is not None:
        return exact
    return (str(sky_file), 1.0, 0) if sky_file.is_file() else None


def current_inputs(scene, folder):
    """The shader's world inputs from the map already made for the world as it is now (none
    when it is not made yet: then the tables sample alone, unbiased, noisier)."""
    key = world_key(scene)
    world_map = deps.bake_module("export.world_map")
    path = map_path(folder, key) if key else None
    meta = world_map.read_world_meta(path) if path is not None and world_map is not None else None
    env = _environment(exact_environment(scene), sky_path(folder, key)) if key else None
    return shader_inputs(path, meta, sun_of(scene) if key else None, env,
                         read_sun(sun_path(folder, key)) if key else None, bright_path(folder, key) if key else None)
