"""The reference path tracer: furnace, analytic point-light values, sampler convergence,
MIS vs BSDF-only, scene files and their errors, environment sampling, intersection."""
import struct
from pathlib import Path

import numpy as np
import pytest

from bake import FlowBSDFError
from bake.core.baselines import CosineSampler, GGXSampler
from bake.maths.geometry import LUMINANCE
from bake.core.ideal import FineIdeal
from bake.materials import open_material
from bake.plumbing.manifest import load_manifest
from bake.plumbing.scene_samplers import make_sampler
from bake.tracer import accel
from bake.tracer.integrator import PathTracer, render
from bake.tracer.lights import Environment, read_hdr, sky_image
from bake.tracer.meshes import SHADERBALL, load_obj, load_ply, shaderball_mesh
from bake.tracer.scene import Camera, SceneMaterial, Scene, builtin_scene, load_scene

ROOT = Path(__file__).resolve().parents[1]
PLASTIC = {"kind": "analytic", "model": "plastic", "albedo": [0.7, 0.2, 0.1], "alpha": 0.12}


def ball_scene(material, env=None, width=16, height=16, max_depth=12, lights=None):
    cam = Camera(np.array([0.0, -4.2, 1.9]), np.array([0.0, 0.0, 0.8]), fov=28.0, width=width, height=height)
    lights = lights if lights is not None else [env if env is not None else Environment(sky_image(64, 32))]
    scene = Scene(cam, [SceneMaterial("ball", material, learned=True)], lights, max_depth=max_depth)
    scene.add_lathe(SHADERBALL, 0)
    return scene.finish()


def block_stats(scene, samplers, mis, passes, seed, blocks=4):
    """Per-pass luminance means over blocks x blocks image regions: passes are independent,
    so their spread gives an honest standard error of each block's mean."""
    tracer = PathTracer(scene, samplers, mis=mis)
    H, W = scene.camera.height, scene.camera.width
    vals = []
    for k in range(passes):
        lum = tracer.render_pass(np.random.default_rng([seed, k])) @ LUMINANCE
        vals.append(lum.reshape(blocks, H // blocks, blocks, W // blocks).mean(axis=(1, 3)).ravel())
    v = np.array(vals)
    return v.mean(axis=0), v.var(axis=0, ddof=1) / passes


def z_scores(a, b):
    return (a[0] - b[0]) / np.sqrt(a[1] + b[1] + 1e-300)


Z_MAX = 4.5     # per block; 16 blocks per comparison: a false alarm has probability ~1e-4


# ------------------------------------------------------------------------ furnace

def test_white_furnace_cosine_is_exact():
    """Lambert albedo 1 in a constant white environment is 1 everywhere, the concave groove
    included; cosine sampling gives weight exactly 1, so every pixel is exactly 1."""
    white = open_material({"kind": "analytic", "model": "lambert", "albedo": 1.0})
    scene = ball_scene(white, env=Environment(np.ones((1, 1, 3))), max_depth=200)
    img, _, _ = render(scene, [CosineSampler()], spp=4, mis=False, seed=3)
    np.testing.assert_allclose(img, 1.0, rtol=0, atol=1e-9)


@pytest.mark.parametrize("which", ["mis-cosine", "ideal", "ggx"])
def test_white_furnace_renders_the_albedo(which):
    """Albedo 1 in a constant environment of radiance 2: every pixel (ball, groove and
    background) has expectation exactly 2, whatever the sampler; these samplers are noisy."""
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 1.0})
    scene = ball_scene(mat, env=Environment(np.full((4, 8, 3), 2.0)), max_depth=200)
    sampler = {"mis-cosine": CosineSampler(), "ideal": FineIdeal(mat, theta_step_deg=5, resolution=24),
               "ggx": GGXSampler(0.4, diffuse=0.5)}[which]
    mean, var = block_stats(scene, [sampler], mis=which == "mis-cosine", passes=24, seed=5)
    noisy = var > 0          # blocks of background only are exact
    assert noisy.sum() >= 8
    np.testing.assert_allclose(mean[~noisy], 2.0, rtol=1e-12)
    z = (mean[noisy] - 2.0) / np.sqrt(var[noisy])
    assert np.all(np.abs(z) < Z_MAX), z
    assert abs(np.mean(mean) - 2.0) < 0.03


def test_white_furnace_fails_for_a_lossy_material():
    """...and the check has power: albedo 0.9 is caught."""
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": 0.9})
    scene = ball_scene(mat, env=Environment(np.full((4, 8, 3), 2.0)), max_depth=200)
    mean, var = block_stats(scene, [GGXSampler(0.4, diffuse=0.5)], mis=False, passes=24, seed=5)
    noisy = var > 0
    assert np.max(np.abs((mean[noisy] - 2.0) / np.sqrt(var[noisy]))) > Z_MAX


def test_workers_do_not_change_the_image(plastic_scene):
    mat, scene = plastic_scene
    one, var1, st1 = render(scene, [GGXSampler(0.15, diffuse=0.5)], spp=6, seed=4)
    two, var2, st2 = render(scene, [GGXSampler(0.15, diffuse=0.5)], spp=6, seed=4, workers=2)
    np.testing.assert_allclose(two, one, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(var2, var1, rtol=1e-9, atol=1e-15)
    assert st2.extra["spp"] == 6 and st2.paths == st1.paths and 0 < st2.sampling_share < 1


# ------------------------------------------------------------------------ point light (analytic)

def _expected_point(scene, shape_normal_at, albedo, light_pos, intensity, sub=8):
    cam = scene.camera
    H, W = cam.height, cam.width
    g = (np.arange(sub) + 0.5) / sub
    jit = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    out = np.zeros((H, W))
    covered = np.zeros((H, W), bool)
    spread = np.zeros((H, W))
    for y in range(H):
        for x in range(W):
            o, d = cam.rays(np.full(len(jit), x), np.full(len(jit), y), jit)
            hit = scene.intersect(o, d)
            p = hit["p"]
            n = shape_normal_at(p)
            v = light_pos - p
            r2 = np.sum(v * v, axis=1)
            cos = np.maximum(np.sum(n * v, axis=1) / np.sqrt(r2), 0.0)
            val = albedo / np.pi * intensity * cos / r2
            out[y, x] = np.mean(np.where(hit["kind"] > 0, val, 0.0))
            covered[y, x] = np.all(hit["kind"] > 0)
            spread[y, x] = np.std(np.where(hit["kind"] > 0, val, 0.0))
    return out, covered, spread


@pytest.mark.parametrize("shape", ["plane", "sphere"])
def test_point_light_on_lambert_matches_the_formula(shape):
    albedo, light, intensity = 0.6, np.array([0.4, -0.3, 2.5]), 7.0
    mat = open_material({"kind": "analytic", "model": "lambert", "albedo": albedo})
    cam = Camera(np.array([0.0, -0.5, 4.0]), np.array([0.0, 0.0, 0.0]), fov=50.0, width=24, height=24)
    from bake.tracer.lights import PointLight
    scene = Scene(cam, [SceneMaterial("m", mat, learned=True)], [PointLight(light, intensity=[intensity] * 3)])
    if shape == "plane":
        scene.add_plane([0, 0, 0], [0, 0, 1], 0)
        normal = lambda p: np.array([[0.0, 0.0, 1.0]])     # noqa: E731
    else:
        scene.add_sphere([0, 0, 0.2], 1.0, 0)
        normal = lambda p: (p - [0, 0, 0.2]) / 1.0          # noqa: E731
    scene.finish()
    img, _, _ = render(scene, [CosineSampler()], spp=400, mis=True, seed=2)
    expected, inside, spread = _expected_point(scene, normal, albedo, light, intensity)
    # Only one bounce reaches the light (nothing else in the scene): the pixel values are the
    # formula averaged over the pixel; the only noise is the pixel jitter (large at the
    # silhouette, where coverage varies), whose standard error is the spread of the formula
    # over the pixel / sqrt(spp).
    assert inside.sum() >= 60
    err = np.abs(img[..., 1] - expected)
    assert np.all(err <= 5 * spread / np.sqrt(400) + 1e-4 * expected.max()), np.max(err / (spread / 20 + 1e-12))
    assert abs(img[..., 1].sum() / expected.sum() - 1) < 0.01
    np.testing.assert_allclose(img[..., 1][inside], expected[inside], rtol=0.06)
    assert expected.max() > 0.1


def test_anisotropic_materials_follow_the_tangent():
    """A brushed lobe on a plane under a point light (one bounce: no sampling noise): the
    lobe turned by 90 deg in a frame whose tangent is x renders exactly as the unturned lobe
    in a frame whose tangent is y; with the tangent swapped the highlight changes."""
    from bake.tracer.lights import PointLight

    def img(angle, tangent):
        mat = open_material({"kind": "analytic", "model": "ggx", "alpha_x": 0.4, "alpha_y": 0.03,
                             "angle": angle, "f0": 0.9})
        cam = Camera(np.array([0.0, -3.0, 2.0]), np.array([0.0, 0.0, 0.0]), fov=60.0, width=16, height=16)
        scene = Scene(cam, [SceneMaterial("m", mat, learned=True)], [PointLight([0.5, 1.5, 1.5], intensity=[5] * 3)])
        scene.add_plane([0, 0, 0], [0, 0, 1], 0, tangent=tangent)
        return render(scene.finish(), [CosineSampler()], spp=2, seed=1)[0]

    a, b, c = img(90, [1, 0, 0]), img(0, [0, 1, 0]), img(0, [1, 0, 0])
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    assert np.abs(a - c).max() > 0.2 * a.max() > 0


# ------------------------------------------------------------------------ convergence

@pytest.fixture(scope="module")
def plastic_scene():
    mat = open_material(PLASTIC)
    return mat, ball_scene(mat)


@pytest.fixture(scope="module")
def plastic_reference(plastic_scene):
    mat, scene = plastic_scene
    return block_stats(scene, [FineIdeal(mat, theta_step_deg=3, resolution=48)], mis=True, passes=64, seed=100)


def _tables_for(mat):
    from bake.core.ideal import IdealSampler
    from bake.core.tabulate import build_tables
    return build_tables(mat, IdealSampler(mat, resolution=64), np.radians([0, 30, 55, 70, 80, 87, 89.5]),
                        rows=24, cols=24, grid=128, lobe_width=0.1)


@pytest.mark.parametrize("which", ["cosine", "ggx", "tables"])
@pytest.mark.parametrize("mis", [True, False])
def test_every_sampler_converges_to_the_same_image(plastic_scene, plastic_reference, which, mis):
    mat, scene = plastic_scene
    sampler = {"cosine": CosineSampler, "ggx": lambda: GGXSampler(0.15, diffuse=0.5),
               "tables": lambda: _tables_for(mat)}[which]()
    got = block_stats(scene, [sampler], mis=mis, passes=64, seed=7)
    z = z_scores(got, plastic_reference)
    assert np.all(np.abs(z) < Z_MAX), z


class _Skewed:
    """A broken sampler: its pdf() disagrees with what sample() draws by a factor."""

    def __init__(self, inner, factor):
        self.inner, self.factor = inner, factor

    def sample(self, wi, u):
        wo, p = self.inner.sample(wi, u)
        return wo, p * self.factor

    def pdf(self, wi, wo):
        return self.inner.pdf(wi, wo) * self.factor


def test_the_convergence_check_catches_a_wrong_pdf(plastic_scene, plastic_reference):
    """The test above has the power to fail: a pdf 15 % off (an image 13 % dark) is flagged."""
    mat, scene = plastic_scene
    got = block_stats(scene, [_Skewed(GGXSampler(0.15, diffuse=0.5), 1.15)], mis=False, passes=64, seed=7)
    assert np.max(np.abs(z_scores(got, plastic_reference))) > Z_MAX


def test_flow_sampler_converges(plastic_scene, plastic_reference, tmp_path):
    torch = pytest.importorskip("torch")
    from trainer.model import FlowNet
    from bake.core.flow import load_model, save_model
    mat, scene = plastic_scene
    torch.manual_seed(3)
    net = FlowNet("disk", True, vel_width=16, vel_depth=2, time_freq=1, base_components=1)
    path = save_model(tmp_path / "m.flow.npz", net.meta(4, material={"name": "x", "fingerprint": "x"}),
                      net.arrays())
    small = ball_scene(mat, width=8, height=8)
    ref = block_stats(small, [FineIdeal(mat, theta_step_deg=3, resolution=48)], mis=True, passes=48, seed=100,
                      blocks=2)
    got = block_stats(small, [load_model(path)], mis=True, passes=48, seed=9, blocks=2)
    z = z_scores(got, ref)
    assert np.all(np.abs(z) < Z_MAX), z


def test_rgl_material_samplers_agree(rgl):
    """A measured material (negative values and all): the ideal tabulation with MIS, and a
    GGX + diffuse lobe without, agree. (Cosine sampling is too heavy-tailed for an honest
    standard error at this sample count: its mean sits low until a rare large sample.)"""
    mat = open_material(rgl("cc_nothern_aurora_rgb"))
    scene = ball_scene(mat, width=8, height=8)
    ideal = block_stats(scene, [FineIdeal(mat, theta_step_deg=3, resolution=48)], mis=True, passes=64,
                        seed=1, blocks=2)
    ggx = block_stats(scene, [GGXSampler(0.1, diffuse=0.3)], mis=False, passes=64, seed=2, blocks=2)
    assert np.all(np.abs(z_scores(ideal, ggx)) < Z_MAX)


# ------------------------------------------------------------------------ MIS vs BSDF-only

def test_mis_and_bsdf_only_agree_with_all_light_kinds(tmp_path):
    (tmp_path / "s.toml").write_text("""
[camera]
position = [0, -4.2, 1.9]
look_at = [0, 0, 0.8]
fov = 40
width = 16
height = 16
[materials.ball]
model = "plastic"
albedo = [0.7, 0.2, 0.1]
alpha = 0.12
sampler = "render"
[materials.floor]
model = "lambert"
albedo = 0.5
[[shape]]
type = "shaderball"
material = "ball"
[[shape]]
type = "plane"
point = [0, 0, 0]
normal = [0, 0, 1]
size = 8
material = "floor"
[[light]]
type = "environment"
sky = { sun_size = 15, sun_strength = 3 }
strength = 0.5
[[light]]
type = "area"
position = [-1, -1, 3]
axis_u = [1, 0, 0]
axis_v = [0, 1.5, 0]
shape = "ellipse"
spread = 100
radiance = [6, 6, 6]
[[light]]
type = "point"
position = [2, -2, 3]
intensity = [5, 5, 5]
[[light]]
type = "point"
position = [-2, 1, 2]
strength = [40, 40, 40]
radius = 0.3
soft_falloff = false
[[light]]
type = "spot"
position = [1, 1, 3]
direction = [-0.3, -0.3, -1]
size = 50
blend = 0.3
radius = 0.2
strength = [200, 200, 200]
[[light]]
type = "sun"
direction = [0.3, 0.5, -1]
angle = 15
strength = [1, 1, 1]
""")
    scene = load_scene(tmp_path / "s.toml")
    from bake.plumbing.scene_samplers import scene_samplers
    samplers = scene_samplers(scene, "cosine", log=lambda s: None)
    a = block_stats(scene, samplers, mis=True, passes=64, seed=11)
    b = block_stats(scene, samplers, mis=False, passes=64, seed=12)
    assert np.all(np.abs(z_scores(a, b)) < Z_MAX)
    # MIS is the lower-noise estimator here (the lamps and the sky's sun are small)
    assert np.sum(a[1]) < np.sum(b[1])


def test_area_light_emits_along_minus_u_cross_v():
    from bake.tracer.lights import AreaLight
    p = np.zeros((4, 3))
    q = AreaLight([0, 0, 2], [2, 0, 0], [0, 2, 0], radiance=[1, 1, 1])        # local -Z = -z: down
    wl, dist, Li, pdf = q.sample(p, np.full((4, 2), 0.5))
    np.testing.assert_allclose(Li, 1.0)
    np.testing.assert_allclose(pdf, 4.0 / 4.0)                        # dist² / (area cos) = 4 / 4
    q = AreaLight([0, 0, 2], [0, 2, 0], [2, 0, 0], radiance=[1, 1, 1])        # emits up
    _, _, Li, pdf = q.sample(p, np.full((4, 2), 0.5))
    assert np.all(Li == 0) and np.all(pdf == 0)                       # the floor sees its back


def test_quad_lights_say_how_to_migrate(tmp_path):
    (tmp_path / "q.toml").write_text(GOOD + '[[light]]\ntype = "quad"\ncorner = [0, 0, 2]\n')
    with pytest.raises(FlowBSDFError, match="replaced by 'area'.*axis_u = edge2"):
        load_scene(tmp_path / "q.toml")


# ------------------------------------------------------------------------ environment

def test_environment_sample_and_pdf_agree():
    env = Environment(sky_image(64, 32), rotate_z=30.0)
    rng = np.random.default_rng(0)
    d, pdf, Li = env.sample_dir(rng.random((20000, 2)))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(pdf, env.pdf(d), rtol=1e-12)
    np.testing.assert_allclose(Li, env.eval(d))
    # pdf integrates to one over the sphere (exactly, per pixel) ...
    omega = (env.z_edges[:-1] - env.z_edges[1:]) * 2 * np.pi / env.W
    assert abs(np.sum(env.lum_over_total * omega[:, None]) - 1) < 1e-12
    # ... and E[L / pdf] over its own samples is the integral of L (uniform quadrature check)
    v = rng.normal(size=(400000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    direct = 4 * np.pi * np.mean(env.eval(v) @ LUMINANCE)
    assert abs(np.mean((Li @ LUMINANCE) / pdf) - direct) < 0.01 * direct


def test_environment_mapping_is_blenders():
    img = np.zeros((4, 8, 3))
    img[2, 4] = 1.0          # just below the horizon, column at u = 0.5..0.625: the +x side
    env = Environment(img)
    assert env.eval(np.array([[1.0, -0.1, -0.2]]) / np.linalg.norm([1.0, -0.1, -0.2]))[0, 0] == 1.0
    assert env.eval(np.array([[-1.0, 0.0, -0.2]]) / np.linalg.norm([1.0, 0.0, 0.2]))[0, 0] == 0.0


def test_hdr_reader_flat_and_rle(tmp_path):
    rgbe = np.array([[[128, 64, 32, 129], [0, 0, 0, 0]]], np.uint8)   # 1 x 2
    path = tmp_path / "a.hdr"
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 2\n" + rgbe.tobytes())
    img = read_hdr(path)
    np.testing.assert_allclose(img[0, 0], [1.0, 0.5, 0.25])
    np.testing.assert_allclose(img[0, 1], 0.0)
    # an RLE scanline of width 8: each channel one run of 8
    W = 8
    line = b"\x02\x02" + struct.pack(">H", W) + b"".join(bytes([128 + W, v]) for v in (128, 64, 32, 130))
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 8\n" + line)
    np.testing.assert_allclose(read_hdr(path)[0], np.tile([2.0, 1.0, 0.5], (W, 1)))
    path.write_bytes(b"P6 not hdr")
    with pytest.raises(FlowBSDFError, match="a.hdr"):
        read_hdr(path)


# ------------------------------------------------------------------------ geometry

def test_bvh_matches_brute_force():
    rng = np.random.default_rng(4)
    c = rng.uniform(-1, 1, (300, 3))
    v0, v1, v2 = c, c + rng.normal(0, 0.15, (300, 3)), c + rng.normal(0, 0.15, (300, 3))
    bvh = accel.TriangleBVH(v0, v1, v2)
    o = rng.uniform(-3, 3, (2000, 3))
    d = rng.uniform(-1, 1, (2000, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = np.full(2000, np.inf)
    tri, _, _ = bvh.intersect(o, d, t)
    # brute force
    best = np.full(2000, np.inf)
    for k in range(300):
        e1, e2 = v1[k] - v0[k], v2[k] - v0[k]
        p = np.cross(d, e2)
        det = p @ e1
        s = o - v0[k]
        u = np.sum(s * p, 1) / det
        q = np.cross(s, e1)
        v = np.sum(d * q, 1) / det
        tt = (q @ e2) / det
        ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (tt > accel.EPS_T)
        best = np.where(ok & (tt < best), tt, best)
    np.testing.assert_allclose(t, best, rtol=1e-9)
    assert np.sum(tri >= 0) > 500
    assert np.all(np.isfinite(t) == (tri >= 0))
    occl = np.full(2000, np.inf)
    bvh.intersect(o, d, occl, any_hit=True)
    assert np.array_equal(np.isfinite(occl), np.isfinite(best))


def test_shaderball_mesh_matches_the_analytic_ball():
    """The procedural mesh (for export) and the analytic pieces describe the same object."""
    mesh = shaderball_mesh(n_phi=128, rings=40)
    bvh = accel.TriangleBVH(*(mesh.vertices[mesh.faces[:, k]] for k in range(3)))
    rng = np.random.default_rng(1)
    target = rng.uniform([-0.5, -0.5, 0.05], [0.5, 0.5, 1.7], (3000, 3))
    o = np.tile([0.3, -5.0, 1.0], (3000, 1))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_mesh = np.full(3000, np.inf)
    bvh.intersect(o, d, t_mesh)
    t_ana = np.full(3000, np.inf)
    accel.intersect_lathe(o, d, SHADERBALL, t_ana)
    both = np.isfinite(t_mesh) & np.isfinite(t_ana)
    assert np.mean(np.isfinite(t_mesh) == np.isfinite(t_ana)) > 0.98
    assert np.median(np.abs(t_mesh[both] - t_ana[both])) < 2e-3


def test_obj_and_ply_loaders(tmp_path):
    (tmp_path / "q.obj").write_text("# quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\n"
                                    "f 1//1 2//1 3//1 4//1\n")
    m = load_obj(tmp_path / "q.obj")
    assert m.faces.shape == (2, 3) and np.allclose(m.normals, [0, 0, 1])
    ply = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
           "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
           "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    (tmp_path / "a.ply").write_text(ply)
    a = load_ply(tmp_path / "a.ply")
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n").encode()
    (tmp_path / "b.ply").write_bytes(header + verts.tobytes() + bytes([4]) + np.array([0, 1, 2, 3], "<i4").tobytes())
    b = load_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.vertices, b.vertices)
    assert a.faces.tolist() == [[0, 1, 2], [0, 2, 3]]


# ------------------------------------------------------------------------ scene files

GOOD = """
[camera]
position = [0, -4, 1]
look_at = [0, 0, 0.5]
width = 8
height = 8
[materials.m]
model = "lambert"
albedo = 0.5
[[shape]]
type = "sphere"
center = [0, 0, 0.5]
radius = 0.5
material = "m"
[[light]]
type = "environment"
constant = [1, 1, 1]
"""


@pytest.mark.parametrize("edit, problem", [
    (lambda s: s.replace("[camera]", "[camra]"), "unknown key 'camra'"),
    (lambda s: s.replace('material = "m"', 'material = "nope"'), "material 'nope' is not defined"),
    (lambda s: s.replace('type = "sphere"', 'type = "cube"'), "type must be one of"),
    (lambda s: s.replace("radius = 0.5", "radius = -1"), "radius: must be > 0"),
    (lambda s: s.replace("width = 8", "width = 0"), "camera.width"),
    (lambda s: s.replace("albedo = 0.5", "albedo = 7"), "albedo"),
    (lambda s: s.replace("constant = [1, 1, 1]", "constant = [1, 1]"), "constant: expected 3"),
    (lambda s: s.replace("constant = [1, 1, 1]", 'file = "missing.exr"'), "not found"),
    (lambda s: s + '[[shape]]\ntype = "mesh"\nfile = "gone.obj"\nmaterial = "m"\n', "not found"),
    (lambda s: s.replace("[[light]]", "[[light]]\nfoo = 1"), "unknown key 'foo'"),
    (lambda s: s.replace("[materials.m]", "[materials.m]\nmanifest = 'x'"), "unknown key"),
    (lambda s: s + "[render]\nmax_depth = 0\n", "max_depth"),
    (lambda s: s.replace("look_at = [0, 0, 0.5]", "look_at = [0, -4, 1]"), "look_at"),
    (lambda s: s[:40], "not valid TOML"),
])
def test_bad_scene_files_name_the_file(tmp_path, edit, problem):
    path = tmp_path / "bad.toml"
    path.write_text(edit(GOOD))
    with pytest.raises(FlowBSDFError, match=problem) as e:
        load_scene(path)
    assert e.value.path is not None and Path(e.value.path).name in ("bad.toml", "missing.exr", "gone.obj")


# ------------------------------------------------------------------------ lamp entries

@pytest.mark.parametrize("lamp, problem", [
    ('type = "point"\nposition = [0, 0, 2]', "needs exactly one of strength, intensity"),
    ('type = "point"\nposition = [0, 0, 2]\nstrength = 1\nintensity = 1', "needs exactly one of strength, intensity"),
    ('type = "point"\nposition = [0, 0, 2]\nstrength = -1', "values must be >= 0"),
    ('type = "point"\nposition = [0, 0, 2]\nstrength = 1\nradius = -0.1', r"radius: must be in \[0"),
    ('type = "point"\nposition = [0, 0, 2]\nstrength = 1\nsoft_falloff = 1', "soft_falloff: expected true or false"),
    ('type = "point"\nposition = [0, 0, 2]\nstrength = 1\nsize = 30', "unknown key 'size'"),
    ('type = "spot"\nposition = [0, 0, 2]\nstrength = 1\nsize = 30\nblend = 0', "exactly one of direction, frame"),
    ('type = "spot"\nposition = [0, 0, 2]\nstrength = 1\nsize = 30\nblend = 2\ndirection = [0, 0, -1]',
     r"blend: must be in \[0, 1\]"),
    ('type = "spot"\nposition = [0, 0, 2]\nstrength = 1\nsize = 30\nblend = 0\nframe = [[1, 0, 0], [0, 1, 0]]',
     "invertible 3x3"),
    ('type = "sun"\ndirection = [0, 0, 0]\nstrength = 1', "direction: must not be zero"),
    ('type = "sun"\ndirection = [0, 0, -1]\nstrength = 1\nangle = 200', r"angle: must be in \[0, 180\]"),
    ('type = "area"\nposition = [0, 0, 2]\naxis_u = [1, 0, 0]\naxis_v = [1, 1, 0]\nstrength = 1', "perpendicular"),
    ('type = "area"\nposition = [0, 0, 2]\naxis_u = [1, 0, 0]\naxis_v = [0, 1, 0]\nstrength = 1\nspread = 0',
     r"spread: must be in \(0, 180\]"),
    ('type = "area"\nposition = [0, 0, 2]\naxis_u = [1, 0, 0]\naxis_v = [0, 1, 0]\nstrength = 1\nshape = "disk"',
     "shape: must be rectangle or ellipse"),
    ('type = "area"\nposition = [0, 0, 2]\naxis_u = [1, 0, 0]\naxis_v = [0, 1, 0]\nstrength = 1\ncamera = "no"',
     "camera: expected true or false"),
    ('type = "lamp"', "type must be environment, point, spot, sun, area"),
])
def test_bad_lamp_entries_say_what_is_wrong(tmp_path, lamp, problem):
    (tmp_path / "s.toml").write_text(GOOD + "[[light]]\n" + lamp + "\n")
    with pytest.raises(FlowBSDFError, match=problem):
        load_scene(tmp_path / "s.toml")


def test_lamp_entries_build_blenders_lamps(tmp_path):
    """Strength and intensity of a point lamp are S and S / 4 pi; a spot's direction is the
    -Z of its frame; an ellipse's area is pi/4 of its extents'."""
    (tmp_path / "s.toml").write_text(GOOD + "[[light]]\n" + """type = "point"
position = [0, 0, 2]
intensity = [1, 2, 3]
[[light]]
type = "spot"
position = [0, 0, 2]
direction = [0, 1, -1]
size = 40
blend = 0.1
strength = 8
[[light]]
type = "area"
position = [0, 0, 2]
axis_u = [2, 0, 0]
axis_v = [0, 1, 0]
shape = "ellipse"
strength = [3, 3, 3]
""")
    _, pt, sp, ar = load_scene(tmp_path / "s.toml").lights
    np.testing.assert_allclose(pt.strength, 4 * np.pi * np.array([1, 2, 3]))
    assert pt.delta and sp.delta and not ar.delta
    axis = np.array([[0.0, 1.0, -1.0]]) / np.sqrt(2)
    assert sp.attenuation(axis)[0] == 1.0 and sp.attenuation(-axis)[0] == 0.0
    np.testing.assert_allclose(ar.area, np.pi / 2)
    np.testing.assert_allclose(ar.radiance, 3 / (np.pi * np.pi / 2))
    np.testing.assert_allclose(ar.normal, [0, 0, -1])


def test_bad_mesh_file_names_the_mesh(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 9\n")
    (tmp_path / "s.toml").write_text(GOOD + '[[shape]]\ntype = "mesh"\nfile = "m.obj"\nmaterial = "m"\n')
    with pytest.raises(FlowBSDFError, match="vertex that does not exist") as e:
        load_scene(tmp_path / "s.toml")
    assert Path(e.value.path).name == "m.obj"


def test_json_scene_and_unknown_manifest_material(tmp_path):
    import json
    import tomllib
    data = tomllib.loads(GOOD)
    (tmp_path / "s.json").write_text(json.dumps(data))
    scene = load_scene(tmp_path / "s.json")
    assert scene.camera.width == 8 and len(scene.spheres) == 1
    data["materials"]["m"] = {"manifest": "no_such_material"}
    (tmp_path / "t.json").write_text(json.dumps(data))
    with pytest.raises(FlowBSDFError, match="no material 'no_such_material'") as e:
        load_scene(tmp_path / "t.json", manifest=load_manifest(ROOT / "manifest.toml"))
    assert Path(e.value.path).name == "t.json"
    with pytest.raises(FlowBSDFError, match="scene files end in"):
        (tmp_path / "s.yaml").write_text("x")
        load_scene(tmp_path / "s.yaml")


def test_environment_from_an_exr_file_and_png_output(tmp_path):
    from bake.tracer.images import false_colour, tonemap, write_exr, write_png
    img = sky_image(32, 16)
    write_exr(tmp_path / "env.exr", img)
    (tmp_path / "s.toml").write_text(GOOD.replace("constant = [1, 1, 1]", 'file = "env.exr"\nstrength = 2'))
    scene = load_scene(tmp_path / "s.toml")
    np.testing.assert_allclose(scene.env.image, 2 * img.astype(np.float32), rtol=1e-7)
    write_png(tmp_path / "a.png", np.concatenate([tonemap(img), false_colour(img[..., 0], 1.0)]))
    pil = pytest.importorskip("PIL.Image")
    back = np.asarray(pil.open(tmp_path / "a.png"))
    assert back.shape == (32, 32, 3)
    np.testing.assert_array_equal(back[:16], tonemap(img))


def test_ambient_shaderball_is_a_furnace():
    """builtin:shaderball-ambient is the ball under a constant white sky: a white Lambertian
    renders 1 everywhere, in the ball's crevices too (interreflections close the furnace)."""
    from bake.materials.analytic import from_spec
    scene = builtin_scene("shaderball-ambient", material=from_spec({"model": "lambert", "albedo": 1.0}),
                          width=16, height=16)
    img, var, _ = render(scene, [CosineSampler()], spp=16, mis=True, seed=3)
    assert abs(img.mean() - 1.0) < 0.01, img.mean()
    assert np.mean(np.abs(img - 1.0) < 4 * np.sqrt(var) + 1e-6) > 0.99


def test_missing_tables_and_models_say_so(tmp_path):
    scene = builtin_scene("shaderball-env", material="red_plastic", manifest=load_manifest(ROOT / "manifest.toml"))
    with pytest.raises(FlowBSDFError, match="no baked tables"):
        make_sampler("tables", scene.materials[0], tables_dir=tmp_path)
    with pytest.raises(FlowBSDFError, match="no trained flow"):
        make_sampler("flow", scene.materials[0], tables_dir=tmp_path)


# ------------------------------------------------------------------------ CLI

def test_cli_render_and_compare(tmp_path, monkeypatch, capsys):
    from bake.plumbing.cli import main
    monkeypatch.chdir(ROOT)
    out = tmp_path / "r.exr"
    assert main(["render", "builtin:shaderball-point", "--material", "matte_white", "--sampler", "cosine",
                 "--spp", "2", "--width", "12", "--height", "12", "--out", str(out)]) == 0
    from bake.tracer.images import read_exr
    img = read_exr(out)
    assert img.shape == (12, 12, 3) and img.max() > 0
    assert "[render] 2/2 spp" in capsys.readouterr().out
    assert main(["compare", "builtin:shaderball-env", "--material", "matte_white", "--samplers", "cosine,ggx",
                 "--reference-sampler", "cosine", "--reference-spp", "8", "--spp", "2", "--width", "8",
                 "--height", "8", "--out", str(tmp_path / "cmp")]) == 0
    names = {p.name for p in (tmp_path / "cmp").iterdir()}
    assert {"reference.exr", "cosine_spp.exr", "ggx_time.exr", "compare.png", "metrics.md", "metrics.csv"} <= names
    assert "| ggx | equal time |" in (tmp_path / "cmp" / "metrics.md").read_text()
    assert main(["render", str(tmp_path / "none.toml"), "--out", str(out)]) == 2
    assert "none.toml: scene file not found" in capsys.readouterr().err
