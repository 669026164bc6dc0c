"""Blender's lamps in the reference tracer against Cycles' own renders.

Each case lights a Lambertian plane (and a Lambertian sphere where the lamp has a size the
sphere's shading resolves) with one lamp, in Cycles (bpy, SVM, Diffuse BSDF, black world, ortho
camera looking down -z, box pixel filter) and in the tracer (the lamp written in the scene
format with Blender's conventions spelled out here: S = color * energy * 2^exposure, sizes
times object scale). Per pixel and channel z = (Cycles - tracer) / sqrt(var + var), the Cycles
variance from 8 seeds, the tracer's from its 1024 passes; and the image means agree.
Also: each hittable lamp's sample() against its pdf_hit() (values and chi-square), and the
validate exporter: a scene with one lamp of each type, exported and rendered by the tracer,
against Cycles. Tests that need bpy skip with the reason where it is absent.
"""
import math

import numpy as np
import pytest

import cycles_scenes as cs
from conftest import slow_unless
from bake.core.baselines import CosineSampler
from bake.materials import open_material
from bake.core.metrics import chi2_test
from bake.tracer.integrator import render
from bake.tracer.scene import SceneMaterial, scene_from_dict

N = 24                  # pixels per side; the view covers [-1, 1]^2 of the plane z = 0
ALBEDO = 0.8
Z_MAX = 5.0             # per pixel and channel (~1700 values: a false alarm ~1e-3)


class OrthoCamera:
    """The tracer's side of cycles_scenes.ortho_camera: rays straight down -z from z = distance,
    image x = world x, rows top to bottom = world y descending (duck-types scene.Camera)."""

    def __init__(self, n=N, distance=5.0, scale=2.0):
        self.width = self.height = n
        self.distance, self.scale = distance, scale

    def rays(self, px, py, jitter):
        x = ((px + jitter[:, 0]) / self.width - 0.5) * self.scale
        y = (0.5 - (py + jitter[:, 1]) / self.height) * self.scale
        o = np.stack([x, y, np.full(len(x), self.distance)], axis=1)
        return o, np.tile([0.0, 0.0, -1.0], (len(x), 1))


SPHERE = ([-0.45, 0.35, 0.35], 0.35)        # centre, radius: a ball on the plane


def tracer_scene(lamps, sphere=False):
    """The plane (and the ball) lit by `lamps` (scene-format [[light]] tables)."""
    data = {"camera": {"position": [0, 0, 5], "look_at": [0, 0.001, 0], "width": N, "height": N},
            "materials": {"m": {"model": "lambert", "albedo": ALBEDO}},
            "shape": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "size": 8, "material": "m"}],
            "light": lamps, "render": {"max_depth": 64}}
    if sphere:
        data["shape"].append({"type": "sphere", "center": SPHERE[0], "radius": SPHERE[1], "material": "m"})
    scene = scene_from_dict(data)
    scene.camera = OrthoCamera()
    return scene


def cycles_scene(lamps, sphere=False, spp=64):
    """The same in Cycles; lamps: (type, object settings, light data settings) triples."""
    bpy = cs.bpy_or_skip()
    sc = cs.reset(N, N, spp=spp, osl=False, threads=1)
    sc.cycles.pixel_filter_type = 'BOX'
    sc.cycles.filter_width = 1.0
    sc.cycles.light_sampling_threshold = 0.0
    cs.set_world(sc, (0.0, 0.0, 0.0))
    cs.ortho_camera(sc, distance=5.0, scale=2.0)

    def diffuse(tree):
        node = tree.nodes.new("ShaderNodeBsdfDiffuse")
        node.inputs["Color"].default_value = (ALBEDO, ALBEDO, ALBEDO, 1.0)
        return node.outputs[0]
    mat = cs.material_with(diffuse)
    cs.add_plane(sc, mat, size=8.0)
    if sphere:
        ob = cs.add_sphere(sc, mat, radius=SPHERE[1], segments=96, rings=48)
        ob.location = SPHERE[0]
    for kind, obj, data in lamps:
        light = bpy.data.lights.new(kind.lower(), kind)
        for k, v in data.items():
            setattr(light, k, v)
        ob = bpy.data.objects.new(kind.lower(), light)
        for k, v in obj.items():
            setattr(ob, k, v)
        sc.collection.objects.link(ob)
    return sc


def compare(cycles_lamps, tracer_lamps, sphere=False, seeds=8, spp=128, tracer_spp=1024, seed=1):
    """(z per pixel and channel, image mean ratio Cycles / tracer, its standard error, the
    Cycles image, the tracer's)."""
    cyc, var_c = cycles_stats(cycles_scene(cycles_lamps, sphere, spp), seeds)
    scene = tracer_scene(tracer_lamps, sphere)
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": ALBEDO})
    scene.materials = [SceneMaterial("m", mat, learned=False, sampler="cosine")]
    ref, var_t, _ = render(scene, [CosineSampler()], spp=tracer_spp, mis=True, seed=seed)
    return (*agreement(cyc, var_c, ref, var_t), cyc, ref)


def cycles_stats(sc, seeds):
    """Cycles' image over `seeds` seeds: (mean, variance of the mean) per pixel and channel."""
    imgs = cs.render_seeds(sc, seeds).astype(float)
    return imgs.mean(0), imgs.var(0, ddof=1) / seeds


def agreement(cyc, var_c, ref, var_t):
    """(z per pixel and channel, image mean ratio Cycles / tracer, its standard error).
    Cycles' pixels are independent (its sample pattern is scrambled per pixel), as are the
    tracer's: the image mean's variance is the sum of theirs over the pixels."""
    # Where a pixel's light comes from rare paths (a few bounces off the ball, a corner of a
    # spread's reach) a pass variance can be 0 though the value is not: differences below
    # 1e-5 of the brightest pixel are taken as noise, not resolved.
    sigma = np.sqrt(var_c + var_t + (1e-5 * ref.max()) ** 2)
    m_t = ref.mean()
    se = math.sqrt((var_c.sum() + var_t.sum()) / var_t.size ** 2)
    return (cyc - ref) / sigma, cyc.mean() / m_t, se / m_t


def assert_agree(z, ratio, se, what):
    assert np.max(np.abs(z)) < Z_MAX, (what, np.max(np.abs(z)))
    assert abs(ratio - 1) < max(4 * se, 2e-3), (what, ratio, se)


def euler(rx, ry, rz):
    """Blender's XYZ Euler rotation matrix (world from local)."""
    cx, sx, cy, sy, cz, sz = (f(a) for a in (rx, ry, rz) for f in (math.cos, math.sin))
    X = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Z @ Y @ X


# Blender's conventions, spelled out: a lamp object at LOC turned by ROT (and scaled); the
# tracer's entry from its numbers. S = color * energy * 2^exposure (* the temperature's colour).
LOC, ROT = (0.1, 0.0, 1.0), (0.3, -0.2, 0.5)
R = euler(*ROT)
SEEN = {"visible_camera": True}        # Blender's lamps are invisible to camera rays by default


def point(radius=0.0, soft=True, camera=False, z=0.7, energy=50.0):
    obj = {"location": (0.3, -0.2, z), **(SEEN if camera else {})}
    data = {"energy": energy, "shadow_soft_size": radius, "use_soft_falloff": soft}
    entry = {"type": "point", "position": [0.3, -0.2, z], "strength": [energy] * 3, "radius": radius,
             "soft_falloff": soft, "camera": camera}
    return ("POINT", obj, data), entry


def spot(radius=0.0, blend=0.5, scale=(1.0, 1.0, 1.0), energy=80.0, size=60.0):
    obj = {"location": (0.1, 0.0, 1.2), "rotation_euler": ROT, "scale": scale}
    data = {"energy": energy, "spot_size": math.radians(size), "spot_blend": blend, "shadow_soft_size": radius}
    entry = {"type": "spot", "position": [0.1, 0.0, 1.2], "frame": (R @ np.diag(scale)).tolist(), "size": size,
             "blend": blend, "strength": [energy] * 3, "radius": radius, "camera": False}
    return ("SPOT", obj, data), entry


def sun(angle=0.0, energy=3.0, normalize=True):
    data = {"energy": energy, "angle": math.radians(angle), "normalize": normalize}
    s = energy if normalize else energy * math.pi * math.sin(math.radians(angle) / 2) ** 2
    entry = {"type": "sun", "direction": (-R[:, 2]).tolist(), "strength": [s] * 3, "angle": angle, "camera": False}
    return ("SUN", {"rotation_euler": ROT}, data), entry


def area(shape, spread=180.0, size=(0.8, 0.5), scale=(1.0, 1.0, 1.0), energy=30.0, color=(1.0, 1.0, 1.0),
         exposure=0.0, temperature=None, normalize=True):
    obj = {"location": LOC, "rotation_euler": ROT, "scale": scale}
    data = {"energy": energy, "shape": shape, "size": size[0], "size_y": size[1], "spread": math.radians(spread),
            "color": color, "exposure": exposure, "normalize": normalize}
    sx = size[0] * scale[0]
    sy = (size[1] if shape in ("RECTANGLE", "ELLIPSE") else size[0]) * scale[1]
    s = np.asarray(color) * energy * 2.0 ** exposure
    if temperature is not None:
        data.update(use_temperature=True, temperature=temperature)
        s = s * blackbody(temperature)
    ellipse = shape in ("DISK", "ELLIPSE")
    if not normalize:                                   # radiance S / pi: S times the area
        s = s * sx * sy * (math.pi / 4 if ellipse else 1.0)
    entry = {"type": "area", "position": list(LOC), "axis_u": (R[:, 0] * sx).tolist(),
             "axis_v": (R[:, 1] * sy).tolist(), "shape": "ellipse" if ellipse else "rectangle",
             "spread": spread, "strength": list(s), "camera": False}
    return ("AREA", obj, data), entry


def blackbody(kelvin):
    """Blender's colour of a lamp's temperature (what its temperature_color reports)."""
    bpy = cs.bpy_or_skip()
    light = bpy.data.lights.new("probe", "POINT")
    light.use_temperature, light.temperature = True, kelvin
    rgb = np.array(light.temperature_color)
    bpy.data.lights.remove(light)
    return rgb


CASES = {
    "point r=0": (point(),),
    "point r>0 soft falloff (disk), seen": (point(0.4, camera=True),),
    "point r>0 sphere, seen, ball": (point(0.4, soft=False, camera=True), True),
    "spot r=0 blend, cone edge in view": (spot(),),
    "spot r>0 non-uniform scale (elliptic cone)": (spot(0.3, blend=0.2, scale=(1.0, 0.5, 1.0)),),
    "sun angle 0, ball": (sun(), True),
    "sun angle 40, ball": (sun(40.0), True),
    "sun angle 40, normalize off": (sun(40.0, normalize=False), True),
    "area square": (area("SQUARE"),),
    "area square spread 60": (area("SQUARE", 60.0),),
    "area rectangle, non-uniform scale": (area("RECTANGLE", scale=(1.5, 0.6, 1.0)),),
    "area rectangle spread 60": (area("RECTANGLE", 60.0),),
    "area disk": (area("DISK"),),
    "area disk spread 60, normalize off": (area("DISK", 60.0, normalize=False),),
    "area ellipse": (area("ELLIPSE"),),
    "area ellipse spread 60, non-uniform scale": (area("ELLIPSE", 60.0, size=(0.8, 1.2), scale=(2.0, 0.5, 1.0)),),
    "area colour, exposure, temperature": (area("SQUARE", color=(1.0, 0.5, 0.25), exposure=1.5,
                                                temperature=4000.0),),
}


# the default run: each lamp kind, shape, spread, scale and colour option once; the rest with -m slow
SLOW_CASES = {"point r>0 sphere, seen, ball", "sun angle 0, ball", "sun angle 40, normalize off", "area square",
              "area rectangle, non-uniform scale", "area disk", "area ellipse"}


@pytest.mark.parametrize("case", slow_unless(list(CASES), default=[c for c in CASES if c not in SLOW_CASES]))
def test_lamp_matches_cycles(case):
    (blender, entry), *ball = CASES[case]
    z, ratio, se, cyc, ref = compare([blender], [entry], sphere=bool(ball))
    assert np.mean(ref > 1e-3) > 0.2                        # the lamp lights the view
    assert_agree(z, ratio, se, case)
    if case.startswith("spot r=0"):                          # pixels dark, in the blend and full
        lum = ref[..., 1] / ref[..., 1].max()
        assert (lum < 1e-3).sum() > 20 and ((lum > 0.1) & (lum < 0.6)).sum() > 20 and (lum > 0.9).sum() > 5


# ------------------------------------------------------------------------ sample() vs pdf_hit()

class LampAsSampler:
    """A lamp seen from point p as a direction sampler in a frame whose z axis points at
    `axis` (the lamp), the interface metrics.chi2_test takes."""

    def __init__(self, lamp, p, axis):
        from bake.tracer.lights import _basis
        self.lamp, self.p = lamp, np.asarray(p, float)
        z = np.asarray(axis, float)[None, :] / np.linalg.norm(axis)
        s, t = _basis(z)
        self.frame = np.concatenate([s, t, z])                   # rows: local x, y, z

    def sample(self, wi, u):
        wl, _, _, pdf = self.lamp.sample(np.tile(self.p, (len(u), 1)), u)
        return wl @ self.frame.T, pdf

    def pdf(self, wi, wo):
        d = wo @ self.frame
        o = np.tile(self.p, (len(d), 1))
        hit, t = self.lamp.intersect(o, d, np.full(len(d), np.inf))
        return np.where(hit, self.lamp.pdf_hit(o, d, np.where(hit, t, 1.0)), 0.0)


def hittable_lamps():
    from bake.tracer.lights import AreaLight, PointLight, SpotLight, SunLight
    down = np.diag([1.0, 1.0, 1.0])
    return {
        "point sphere": PointLight([0.3, 0.2, 1.0], strength=[1] * 3, radius=0.6, soft_falloff=False),
        "point disk": PointLight([0.3, 0.2, 1.0], strength=[1] * 3, radius=0.6),
        "spot sphere": SpotLight([0.3, 0.2, 1.0], frame=down, size_deg=90, blend=0.3, strength=[1] * 3,
                                 radius=0.6, soft_falloff=False),
        "sun 50 deg": SunLight([0.2, 0.4, -1.0], strength=[1] * 3, angle_deg=50.0),
        "area rectangle": AreaLight([0.3, 0.2, 0.8], R[:, 0] * 1.5, R[:, 1] * 0.8, strength=[1] * 3),
        "area ellipse": AreaLight([0.3, 0.2, 0.8], R[:, 0] * 1.5, R[:, 1] * 0.8, strength=[1] * 3, ellipse=True),
        "area rectangle spread 60": AreaLight([0.3, 0.2, 0.8], R[:, 0] * 1.5, R[:, 1] * 0.8, strength=[1] * 3,
                                              spread_deg=60.0),
        "area ellipse spread 60": AreaLight([0.3, 0.2, 0.8], R[:, 0] * 1.5, R[:, 1] * 0.8, strength=[1] * 3,
                                            ellipse=True, spread_deg=60.0),
    }


@pytest.mark.parametrize("name", list(hittable_lamps()))
def test_lamp_sampling_matches_its_pdf(name):
    """sample() from a point near the lamp against pdf_hit(): the returned pdf and distance
    are what pdf_hit() and intersect() give the sampled direction, and the directions follow
    pdf_hit() (chi-square on (cos theta, phi) about the lamp's centre)."""
    lamp = hittable_lamps()[name]
    p = np.array([0.0, 0.0, 0.1])
    rng = np.random.default_rng(3)
    n = 20000
    o = np.tile(p, (n, 1))
    wl, dist, Li, pdf = lamp.sample(o, rng.random((n, 2)))
    ok = pdf > 0
    assert ok.mean() > 0.3
    hit, t = lamp.intersect(o[ok], wl[ok], np.full(ok.sum(), np.inf))
    assert hit.all()
    if np.all(np.isfinite(dist)):
        np.testing.assert_allclose(t, dist[ok], rtol=1e-9)
    np.testing.assert_allclose(lamp.pdf_hit(o[ok], wl[ok], t), pdf[ok], rtol=1e-9)
    np.testing.assert_allclose(lamp.eval_hit(o[ok], wl[ok], t), Li[ok], rtol=1e-12)
    axis = lamp.toward if hasattr(lamp, "toward") else lamp.position - p
    result = chi2_test(LampAsSampler(lamp, p, axis), [0.0, 0.0, 1.0], n=200_000, res=(24, 24),
                       binning="cosine", seed=5)
    assert result.passed, result


def test_the_pdf_check_catches_a_wrong_solid_angle():
    """...and has power: a sphere lamp whose pdf_hit() is that of a sphere 3 % larger fails."""
    from bake.tracer.lights import PointLight
    lamp = PointLight([0.3, 0.2, 1.0], strength=[1] * 3, radius=0.6, soft_falloff=False)
    wrong = PointLight([0.3, 0.2, 1.0], strength=[1] * 3, radius=0.618, soft_falloff=False)
    sampler = LampAsSampler(lamp, [0.0, 0.0, 0.1], [0.3, 0.2, 0.9])
    sampler.pdf = LampAsSampler(wrong, [0.0, 0.0, 0.1], [0.3, 0.2, 0.9]).pdf
    assert not chi2_test(sampler, [0.0, 0.0, 1.0], n=200_000, res=(24, 24), binning="cosine", seed=5).passed


# ------------------------------------------------------------------------ the validate exporter

def test_validate_exports_every_lamp_as_cycles_renders_it(tmp_path):
    """A scene with one lamp of each type (a seen point with a radius, a scaled spot, a sun
    with an angle, a mirrored ellipse with a spread and Normalize off, colour and exposure),
    exported by the validate exporter and rendered by the tracer, matches Cycles' Diffuse render
    of the same scene; what the tracer cannot render is refused, not dropped."""
    import tomllib
    cs.bpy_or_skip()
    from blender_addon.artist import validate
    from bake.plumbing.scene_samplers import scene_samplers
    from bake.tracer.scene import load_scene
    lamps = [point(0.3, camera=True, z=0.8, energy=20.0)[0], spot(0.2, scale=(1.0, 0.6, 1.0), energy=40.0)[0],
             sun(10.0, energy=1.0)[0],
             area("ELLIPSE", 90.0, size=(0.6, 0.9), scale=(-1.5, 1.0, 1.0), energy=10.0, color=(1.0, 0.7, 0.4),
                  exposure=0.5, normalize=False)[0]]
    sc = cycles_scene(lamps, sphere=True, spp=128)
    cs.persp_camera(sc, distance=6.0, fov_deg=22.0)
    path, notes = validate.export_scene(sc, str(tmp_path / "v"), [], N, N, "unused.toml")
    data = tomllib.loads(open(path).read())
    assert sorted(l["type"] for l in data["light"]) == ["area", "environment", "point", "spot", "sun"]
    cyc, var_c = cycles_stats(sc, 8)
    scene = load_scene(path)
    ref, var_t, _ = render(scene, scene_samplers(scene, "cosine", log=lambda s: None), spp=512, seed=2)
    z, ratio, se = agreement(cyc, var_c, ref, var_t)
    assert_agree(z, ratio, se, "exported scene")

    import bpy
    lamp = next(o for o in sc.objects if o.type == "LIGHT" and o.data.type == "SPOT")
    for setting, value, problem in (("use_shadow", False, "casts no shadow"),
                                    ("use_square", True, "square spot"),
                                    ("diffuse_factor", 0.5, "diffuse_factor")):
        setattr(lamp.data, setting, value)
        with pytest.raises(validate.ExportError, match=problem):
            validate.export_scene(sc, str(tmp_path / "v"), [], N, N, "unused.toml")
        setattr(lamp.data, setting, not value if isinstance(value, bool) else 1.0)
    lamp.light_linking.receiver_collection = bpy.data.collections.new("lit")
    with pytest.raises(validate.ExportError, match="light or shadow linking"):
        validate.export_scene(sc, str(tmp_path / "v"), [], N, N, "unused.toml")


def test_validate_exports_a_default_area_lamp(tmp_path):
    """Blender's default spread (180 deg, stored as float32 pi = 180.000005 deg) exports as
    180, which the tracer accepts (it refused the scene of any default area lamp)."""
    cs.bpy_or_skip()
    from blender_addon.artist import validate
    from bake.tracer.scene import load_scene
    sc = cycles_scene([("AREA", {"location": LOC, "rotation_euler": ROT}, {"energy": 10.0})])
    cs.persp_camera(sc, distance=6.0, fov_deg=22.0)
    assert math.degrees(next(o for o in sc.objects if o.type == "LIGHT").data.spread) > 180.0
    path, _ = validate.export_scene(sc, str(tmp_path / "v"), [], N, N, "unused.toml")
    assert [type(lamp).__name__ for lamp in load_scene(path).lamps] == ["AreaLight"]
