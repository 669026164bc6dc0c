"""Issue 51's "No rings": the Learned BSDF's fit back end (closure_fit: per view-angle knot a
Diffuse and 3 GGX lobes, lerped between knots) draws no concentric rings on a sphere.

A fit whose per-knot parameters jump between knots shades each view angle unlike its
neighbours; on a sphere seen by an orthographic camera the view angle is constant on rings
about the sphere's centre (theta_i = arcsin of the ring's radius), so the jumps draw rings. The
test renders the sphere with the fit back end and with the exact OSL back end (the tables), same
scene, and takes the RADIAL PROFILE of their relative difference: per ring one pixel wide,
sum(Y_fit) / sum(Y_osl) - 1 (Y luminance: the OSL image's weighted mean of the pixels' relative
difference, which dark pixels do not blow up), the whole rings within 0.95 of the radius (no
silhouette pixels: 22 rings, 0-66 deg; the knots beyond, 70-89.5 deg, lie within the outer 2
pixels, where no ring could show at this size). The fit's overall error changes smoothly with
the view angle: a cubic in the ring radius takes it out. What is left, its rms over the K rings,
holds the rings and the Monte Carlo noise, whose part (the per-ring standard error of the
profile, sigma, from PARTS renders of disjoint samples, independent with hashed u on camera
rays; a seed of its own per render would compile the OSL shader anew, 3-5 s each) is taken out
in quadrature:

    rings = sqrt(max(mean(residual^2) - mean(sigma^2) (K - 4) / K, 0))

The scenes, 48^2, 4 parts of 16 spp: an area lamp near the camera over a black world, and a Sky
Texture world with its sun 33 deg off the view axis (an HDRI-like world: the sun disc and the
dome, Cycles' world importance sampling). The material: small baked tables (16 x 16 cells) of a
coloured GGX (alpha 0.15) at 11 view angles as a bake has them (cycles_scenes.SMALL_BINS' 5 are
too coarse here: between their 0 and 30 deg bins the tables are a blend of two lobes that no
GGX fits, and the fit's difference from them swings +-30 % over 40 deg: the tables' structure,
not the fit's). The ringing fit: the shipped fit with each lobe's roughness x1.3 at even knots
and x0.7 at odd ones (ringing_fit), in the same scenes.

Measured (this machine; rms of the residual / noise / rings, in %):
  glossy, lamp: smooth fit 1.60 / 1.79 / 0.0, ringing fit 33.9 / 2.2 / 33.9
  glossy, sky:  smooth fit 0.95 / 1.33 / 0.0, ringing fit 18.7 / 1.6 / 18.6
  the smooth fit at 8 parts of 64 spp: lamp 1.02 / 0.61 / 0.86, sky 0.94 / 0.41 / 0.86 (bumps of
  2-3 % at 6 and 31 deg, next to knots, which the noise hides at the test's samples); fitted with
  closure_fit.STEP_COST = PULL = 0 ("free"): 0.91 (lamp) and 1.06 % (sky) rings: a single GGX
  lobe's fit is as smooth without them
  -m slow, colodur_napoli_4f (a measured paint, 9 bins): smooth 0.86 (lamp) / 0.98 (sky), free
  1.55 / 1.51, ringing 6.29 / 6.34 (noise 0.30 / 0.45)
RINGS_MAX = 3 %: above the smooth fits' 0.86-0.98 % by more than what noise alone can read
(mean(residual^2) over 22 rings less sigma^2 from 4 parts: sd ~0.35 sigma^2, so at 3 sd and
sigma 1.8 %, rings of ~1.9 %), 2x below the measured paint's ringing fit and 6x below the glossy's. A
weaker alternation on the glossy: roughness +-5 % reads 5.6 (lamp) / 2.9 % (sky), +-10 % 11 / 6.0 %,
+-15 % 17 / 9.2 %: the lamp catches +-5 %, the sky +-10 %.
What it does not tell apart: a fit's error that changes with the view angle faster than a cubic
is "rings" to it, knots or not: cc_nothern_aurora (a pearlescent paint the fit misses by 20 %,
its highlight's shape: a brighter centre in a darker disc out to 30 deg) reads 4.4 % (lamp) and
4.35 % (sky), its free fit 4.9 / 4.4 %, its ringing fit 26 / 14 %; and the free fit of the
current search (each knot's lobes from the previous knot's) draws no rings that the smooth one
does not (above): its rings would be a jump this search does not make.

FLOWBSDF_RINGS_IMAGES=<folder> saves the images (OSL, each fit and its difference) as PNGs there.
"""
import copy
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

import cycles_scenes as cs
from bake.export import closure_fit, derived
from conftest import rgl_path

bpy = cs.bpy_or_skip()
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))     # blender_addon (not installed)
from blender_addon.render import binding, node as lb  # noqa: E402

N, SPP, PARTS = 48, 16, 4
SCALE = 2.0             # the orthographic camera's width: the unit sphere fills the image
R_MAX = 0.95            # the rings' reach, in sphere radii (no silhouette pixels)
DEGREE = 3              # the smooth trend taken out of the profile
RINGS_MAX = 0.03        # (module docstring)
NOISE_MAX = 0.025       # the noise under which the test resolves rings of RINGS_MAX
RINGING = 0.3           # the ringing fit: roughness x (1 + RINGING) at even knots, x (1 - RINGING) at odd
BINS_DEG = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 85.0, 89.5)
GLOSSY = {"kind": "analytic", "model": "ggx", "alpha": 0.15, "f0": [0.9, 0.6, 0.3]}
MEASURED = "colodur_napoli_4f_rgb"          # (-m slow: its tables as tests/test_closure_fit.py's, 16^2 cells)
MEASURED_BINS_DEG = (0.0, 10.0, 20.0, 30.0, 45.0, 60.0, 70.0, 80.0, 89.5)
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def baked_tables(source, name, folder, bins_deg=BINS_DEG):
    """16 x 16-cell tables of `source` at `bins_deg` (the ideal tabulation), <folder>/<name>.exr."""
    from bake.core.ideal import IdealSampler
    from bake.core.tabulate import build_tables
    from bake.materials import open_material
    mat = open_material(source)
    tab = build_tables(mat, IdealSampler(mat, resolution=64), np.radians(bins_deg), rows=16, cols=16, grid=96)
    tab.meta["material"] = name
    path = Path(folder) / f"{name}.exr"
    tab.save(path)
    return path


def ringing_fit(fit, amount=RINGING):
    """The fit with each knot's roughness scaled by 1 + amount at even knots and 1 - amount at
    odd ones (at most 1, as Cycles clamps): jumps between knots of the kind a fit made per knot
    alone can have."""
    out = copy.deepcopy(fit)
    out.pop("match_path", None)
    out["roughness"] = [[min(r * (1 + amount if k % 2 == 0 else 1 - amount), 1.0) for r in rs]
                        for k, rs in enumerate(fit["roughness"])]
    return out


def materials(tables, folder, extra_fits=()):
    """{"smooth": the tables' own fit, "ringing": ringing_fit of it, **extra_fits}: the fit
    files and a Learned BSDF material of each, all bound to `tables` (the OSL back end renders
    the tables whatever the fit)."""
    fit = closure_fit.load_fit(derived.ensure_fit(tables))
    fits = {"ringing": ringing_fit(fit), **dict(extra_fits)}
    out = {}
    mat = bpy.data.materials.new("smooth")
    lb.assign_learned_bsdf(mat, "smooth", tables)     # the fit beside the tables, as the node finds it
    out["smooth"] = mat
    for name, f in fits.items():
        path = Path(folder) / f"{name}.fit.json"
        path.write_text(json.dumps(f))
        mat = bpy.data.materials.new(name)
        node = lb.assign_learned_bsdf(mat, name, tables, fit_path=path)
        assert binding.read(node.node_tree)["fit"] == str(path)
        out[name] = mat
    return out


def scene(lighting):
    """The sphere's scene without its material: an orthographic camera down -z, a black world
    and an area lamp near the camera ("lamp"), or a Sky Texture world with its sun 33 deg
    from the view axis ("sky"). Hashed u on camera rays: the parts are independent."""
    sc = cs.reset(N, N, spp=SPP)
    cs.ortho_camera(sc, scale=SCALE)
    setattr(sc, lb.FILM_PROP, False)
    if lighting == "lamp":
        cs.set_world(sc, (0.0, 0.0, 0.0))
        cs.add_lamp(sc, "AREA", (1.5, 1.0, 4.0), energy=150.0, size=1.5)
    else:
        cs.set_sky_world(sc, sun_elevation=1.0, sun_rotation=0.6, strength=0.1)
    return sc


def render_sphere(sc, mats):
    """{"osl": the tables by the OSL back end, name: the fit back end with material `name`}
    for each of `mats`: (PARTS, N, N, 3) each, the sphere the same, its material swapped."""
    sphere = cs.add_sphere(sc, None, segments=64, rings=32)
    out = {}
    for name, backend in [("osl", "osl")] + [(name, "fit") for name in mats]:
        sphere.data.materials.clear()
        sphere.data.materials.append(mats["smooth" if name == "osl" else name])
        lb.set_backend(sc, backend)
        out[name] = cs.render_parts(sc, PARTS)
    return out


def _rings():
    """Per pixel its ring (one pixel of radius wide) and the pixels within R_MAX; the rings'
    radii in sphere radii."""
    n, hit = cs.sphere_view(N, N, SCALE)
    r = np.hypot(n[..., 0], n[..., 1])
    width = SCALE / N
    count = int(R_MAX / width)
    ring = np.floor(r / width).astype(int)
    return ring, hit & (ring < count), (np.arange(count) + 0.5) * width


def radial_profile(fit_img, osl_img):
    """Per ring sum(Y fit) / sum(Y osl) - 1."""
    ring, inside, radii = _rings()

    def sums(img):
        return np.bincount(ring[inside], (img @ LUMINANCE)[inside], len(radii))
    return sums(fit_img) / sums(osl_img) - 1.0


def rings_of(fit_parts, osl_parts):
    """The profile of the parts' means, its residual from a cubic in the radius, the per-ring
    noise (standard error over the parts) and the rings' amplitude (module docstring)."""
    _, _, radii = _rings()
    profile = radial_profile(fit_parts.mean(0), osl_parts.mean(0))
    per_part = np.array([radial_profile(f, o) for f, o in zip(fit_parts, osl_parts)])
    sigma = per_part.std(0, ddof=1) / np.sqrt(len(per_part))
    trend = np.polynomial.polynomial.polyfit(radii, profile, DEGREE)
    resid = profile - np.polynomial.polynomial.polyval(radii, trend)
    k = len(radii)
    rms, noise = np.sqrt(np.mean(resid ** 2)), np.sqrt(np.mean(sigma ** 2))
    rings = np.sqrt(max(rms ** 2 - noise ** 2 * (k - DEGREE - 1) / k, 0.0))
    return {"radii": radii, "profile": profile, "resid": resid, "sigma": sigma, "rms": float(rms),
            "noise": float(noise), "rings": float(rings)}


def save_images(folder, tag, imgs):
    """PNGs of the OSL image, each fit's and its relative difference (red: the fit brighter,
    blue: darker, full at 50 %), each 6x: <folder>/<tag>_<name>.png."""
    from PIL import Image
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    osl = imgs["osl"].mean(0)
    white = np.percentile(osl, 99.5)

    def png(rgb, name):
        Image.fromarray(rgb).resize((6 * N, 6 * N), Image.NEAREST).save(folder / f"{tag}_{name}.png")

    def tone(img):
        return (np.clip(img / white, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    png(tone(osl), "osl")
    y_osl = osl @ LUMINANCE
    for name, parts in imgs.items():
        if name == "osl":
            continue
        img = parts.mean(0)
        png(tone(img), name)
        rel = np.clip((img @ LUMINANCE - y_osl) / np.maximum(y_osl, 0.02 * y_osl.max()) / 0.5, -1, 1)
        diff = np.stack([rel.clip(0), np.zeros_like(rel), (-rel).clip(0)], -1) ** 0.7
        png((diff * 255).astype(np.uint8), f"{name}_difference")


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    """tables(material) -> its baked tables (made once): "glossy" or the measured file."""
    made = {}

    def get(material):
        if material not in made:
            folder = tmp_path_factory.mktemp(material)
            made[material] = (baked_tables(GLOSSY, material, folder) if material == "glossy" else
                              baked_tables(str(rgl_path(material)), material, folder, MEASURED_BINS_DEG))
        return made[material]
    return get


@pytest.fixture(scope="module", params=[("glossy", "lamp"), ("glossy", "sky"),
                                        pytest.param((MEASURED, "lamp"), marks=pytest.mark.slow),
                                        pytest.param((MEASURED, "sky"), marks=pytest.mark.slow)],
                ids=lambda p: "-".join(p))
def rendered(request, tables):
    """(material, lighting, {"osl", "smooth", "ringing"} -> parts (render_sphere))."""
    material, lighting = request.param
    path = tables(material)
    lb.register()
    try:
        sc = scene(lighting)
        imgs = render_sphere(sc, materials(path, path.parent))
    finally:
        lb.unregister()
    if os.environ.get("FLOWBSDF_RINGS_IMAGES"):
        save_images(os.environ["FLOWBSDF_RINGS_IMAGES"], f"{material}_{lighting}", imgs)
    return material, lighting, imgs


def _report(case, name, r):
    return (f"{case} {name}: rings {r['rings']:.4f} (residual rms {r['rms']:.4f}, noise {r['noise']:.4f}); "
            f"residual per ring {np.round(r['resid'], 3).tolist()}")


def test_smooth_fit_draws_no_rings(rendered):
    material, lighting, imgs = rendered
    r = rings_of(imgs["smooth"], imgs["osl"])
    print(_report(f"{material} {lighting}", "smooth", r))
    assert r["noise"] < NOISE_MAX, _report(f"{material} {lighting}", "smooth", r)
    assert r["rings"] < RINGS_MAX, _report(f"{material} {lighting}", "smooth", r)


def test_ringing_fit_is_caught(rendered):
    """The metric sees a ringing fit's rings in the same renders (measured: 19-34 % on the
    glossy GGX, 6.3 % on the paint: module docstring)."""
    material, lighting, imgs = rendered
    r = rings_of(imgs["ringing"], imgs["osl"])
    print(_report(f"{material} {lighting}", "ringing", r))
    assert r["rings"] > 1.5 * RINGS_MAX, _report(f"{material} {lighting}", "ringing", r)
    if material == "glossy":
        assert r["rings"] > 5 * RINGS_MAX, _report(f"{material} {lighting}", "ringing", r)
