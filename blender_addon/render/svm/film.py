"""A path vertex's uniform numbers: hashed from the shading point and the incoming ray, or on camera
rays the sample's place in its pixel (the film: Cycles' box filter); docs/svm.md."""
import bpy

from .. import sockets
from .graph import X, Y, Z, fma, where

FILM = "FlowBSDF SVM film"      # a Combine XYZ node per sampler: film_settings


def portal_depth(g, light_path):
    """How many Ray Portals the path has gone through: Light Path's Portal Depth (Blender 5.0+);
    before 5.0 its Transparent Depth, which a portal also counts (Cycles' path_state_next: a
    portal is a transparent bounce, 4.5 as 5.0), and so does a transparent surface: there camera
    rays take hashed u instead of their pixel's stratified ones and the hash mixes in that count,
    unbiased either way."""
    name = "Portal Depth" if light_path.outputs.get("Portal Depth") is not None else "Transparent Depth"
    return g.outputs(light_path)[name]


def _random(g, geometry, light_path):
    """u0, u1, u2 hashed from the shading point and the incoming ray (docs/svm.md)."""
    path = g.outputs(light_path)
    noise = g.node("ShaderNodeTexWhiteNoise", noise_dimensions='4D')
    g.set(noise.inputs["Vector"], geometry.outputs["Position"])
    g.set(noise.inputs["W"], path["Ray Length"])
    depth = fma(path["Ray Depth"], 64.0, portal_depth(g, light_path))
    noise2 = g.node("ShaderNodeTexWhiteNoise", noise_dimensions='4D')
    g.set(noise2.inputs["Vector"], geometry.outputs["Incoming"])
    g.set(noise2.inputs["W"], g.outputs(noise)["Value"] + depth)
    return tuple(g.dot(noise2.outputs["Color"], axis) for axis in (X, Y, Z))


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
    first = g.outputs(light_path)["Is Camera Ray"] * (portal_depth(g, light_path) < 0.5)
    use = first * (g.dot(film.outputs[0], Z) > 0.5)
    return tuple(where(use, g.dot(u, axis), h) for axis, h in zip((X, Y), hashed))
