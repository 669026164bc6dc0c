"""The render probe: the Learned BSDF's fit back end renders in Cycles exactly the closure fit
numpy states (bake.export.closure_fit.eval_fit), per colour channel, at directions spanning
the hemisphere.

The scene: a grid of flat quads, each at a known orientation and its projection one cell of
CELL x CELL pixels of an orthographic camera looking down -z (so no quad hides another), lit
by a Sun lamp of angle 0 and strength E only (no world, no bounces: direct light of the
closures alone, no shadows: the quads cast none). A sun of angle 0 is a delta light: every
sample of a pixel inside a flat quad is the same, f(wi, wo) cos(theta_o) E with wi toward the
camera and wo toward the sun in the quad's local frame, so the box filter's interior pixels
are exact and no Monte Carlo error enters. Renders with the sun at several zenith angles, the
quads' normals at view angles on the fit's knots and between them (the node interpolates in
x = 1 - cos theta_i) and at 12 azimuths each, span the pairs (wi, wo).

The fits are written here, each as the fit file of a Learned BSDF node (assign_learned_bsdf's
fit_path) bound to small baked tables of a Lambertian, which the fit back end does not read
(bound to missing tables it renders the fit too: test_missing_tables_render_the_fit). They are: isotropic lobes only (view_aligned 0);
view-aligned anisotropic lobes (a > 0 and a < 0, 0 at normal view); one whose anisotropy is not
0 at normal view (as fits of measured files have it), seen exactly head-on (where the view
tangent vanishes: no NaN); lobes along the material's tangent (anisotropic tables' fit, FIT_VERSION
9: the node's Tangent input); and a rough lobe stretched beyond alpha 1, which Cycles clamps to 1 and eval_fit too
(test_alphas_beyond_1_render_as_eval_fit_states: found by this probe). Each is rendered with
Cycles' SVM and with OSL (its nodes as OSL shaders).

Mutations this probe catches (each made by hand, the test run, reverted): eval_fit's
anisotropy sign swapped or its tangent turned 90 deg; params_at lerping alpha instead of r;
the node's view tangent unlinked, turned 90 deg, or without its 1e-6 nudge (NaN head-on); Layer
Weight's blend 0.4 (Facing 1 - |cos|^0.8); the lobes' roughness or anisotropy outputs mixed up.
"""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

import cycles_scenes as cs
from bake.export.closure_fit import FIT_VERSION, eval_fit

bpy = cs.bpy_or_skip(need_osl=False)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))     # blender_addon (not installed)
from blender_addon.render import fit_nodes, node as lb  # noqa: E402
from blender_addon.render.svm import VIEW_TANGENT_NUDGE  # noqa: E402

E = 2.0                 # the sun's strength: its irradiance at normal incidence
CELL = 4                # pixels per quad side (the inner 2 x 2 are wholly inside it)
KNOTS_DEG = (0.0, 30.0, 60.0, 75.0, 90.0)
ON_KNOTS_DEG = (0.0, 30.0, 60.0, 75.0)
BETWEEN_DEG = (0.5, 2.0, 15.0, 45.0, 52.0, 68.0, 82.0, 87.0)
AZIMUTHS = 12
SUN_ZENITH_DEG = (0.0, 15.0, 30.0, 50.0, 70.0, 90.0, 110.0, 130.0, 150.0, 170.0)
TOLERANCE = 1e-3        # the acceptance: within 1e-3 relative at >= 99 % of the directions
SHARE = 0.99


def _fit(diffuse, specular, roughness, anisotropy, view_aligned):
    """A fit file's dict (closure_fit.fit_closures' keys) over KNOTS_DEG."""
    n = len(KNOTS_DEG)
    return {"format": "flowbsdf-closure-fit", "version": FIT_VERSION, "model": "hand-written",
            "view_aligned": view_aligned, "x": [float(1.0 - np.cos(np.radians(d))) for d in KNOTS_DEG],
            "theta_deg": list(KNOTS_DEG), "diffuse": diffuse, "specular": specular, "roughness": roughness,
            "anisotropy": anisotropy, "rel_error": [0.0] * n, "cv": [[0.0, 0.0, 1.0]] * n}


def _lobes(*per_lobe):
    """Per knot the lobes' values: per_lobe[j][k] -> out[k][j]."""
    return [list(v) for v in zip(*per_lobe)]


# Isotropic lobes only (as a fit of anisotropic tables): colours, roughness changing per knot.
ISOTROPIC = _fit(
    diffuse=[[0.20, 0.15, 0.10], [0.25, 0.12, 0.08], [0.10, 0.20, 0.05], [0.05, 0.10, 0.15], [0.02, 0.05, 0.08]],
    specular=_lobes(
        [[0.30, 0.20, 0.10], [0.20, 0.30, 0.10], [0.40, 0.10, 0.20], [0.10, 0.10, 0.40], [0.20, 0.20, 0.20]],
        [[0.10, 0.20, 0.30], [0.30, 0.10, 0.20], [0.05, 0.05, 0.10], [0.20, 0.40, 0.10], [0.10, 0.30, 0.30]],
        [[0.02, 0.03, 0.04], [0.04, 0.02, 0.01], [0.06, 0.05, 0.02], [0.03, 0.06, 0.05], [0.08, 0.04, 0.06]]),
    roughness=_lobes([0.30, 0.45, 0.60, 0.50, 0.40], [0.70, 0.55, 0.40, 0.35, 0.30], [0.15, 0.20, 0.25, 0.20, 0.18]),
    anisotropy=[[0.0, 0.0, 0.0]] * 5, view_aligned=0)

# Two view-aligned lobes, stretched across the plane of incidence (a > 0) and along it (a < 0),
# isotropic at normal view; the third isotropic. A little diffuse: the lobes dominate.
ANISOTROPIC = _fit(
    diffuse=[[0.03, 0.04, 0.05], [0.04, 0.03, 0.02], [0.02, 0.05, 0.03], [0.03, 0.03, 0.06], [0.05, 0.02, 0.04]],
    specular=_lobes(
        [[0.40, 0.30, 0.20], [0.30, 0.40, 0.20], [0.50, 0.20, 0.30], [0.20, 0.30, 0.50], [0.30, 0.30, 0.30]],
        [[0.20, 0.30, 0.40], [0.40, 0.20, 0.30], [0.10, 0.20, 0.20], [0.30, 0.50, 0.20], [0.20, 0.40, 0.40]],
        [[0.03, 0.02, 0.05], [0.05, 0.03, 0.02], [0.04, 0.06, 0.03], [0.02, 0.05, 0.06], [0.06, 0.04, 0.05]]),
    roughness=_lobes([0.30, 0.40, 0.50, 0.45, 0.40], [0.50, 0.55, 0.60, 0.55, 0.50], [0.20, 0.20, 0.25, 0.20, 0.20]),
    anisotropy=_lobes([0.0, 0.30, 0.60, 0.50, 0.40], [0.0, -0.20, -0.40, -0.35, -0.30], [0.0] * 5),
    view_aligned=2)

# Anisotropic at normal view too (fits of measured files are: closure_fit's docstring), where
# the view tangent vanishes: the head-on quad must render a finite value, some orientation of
# the lobes.
HEAD_ON = _fit(
    diffuse=[[0.05, 0.05, 0.05]] * 5,
    specular=_lobes([[0.5, 0.4, 0.3]] * 5, [[0.3, 0.4, 0.5]] * 5, [[0.0, 0.0, 0.0]] * 5),
    roughness=_lobes([0.35] * 5, [0.5] * 5, [0.3] * 5),
    anisotropy=_lobes([0.6] * 5, [-0.5] * 5, [0.0] * 5),
    view_aligned=2)


# A rough lobe stretched beyond alpha 1 (0.64 / (1 - 0.6) = 1.6 from 30 deg on): Cycles clamps
# alpha_x and alpha_y to [0, 1] (bsdf_microfacet_ggx_setup: saturatef), closure_fit.alphas_xy
# does not (test_alphas_beyond_1_render_as_eval_fit_states).
CLAMPED = _fit(
    diffuse=[[0.0, 0.0, 0.0]] * 5,
    specular=_lobes([[0.6, 0.5, 0.4]] * 5, [[0.0, 0.0, 0.0]] * 5, [[0.0, 0.0, 0.0]] * 5),
    roughness=_lobes([0.8] * 5, [0.5] * 5, [0.5] * 5),
    anisotropy=_lobes([0.0, 0.6, 0.6, 0.6, 0.6], [0.0] * 5, [0.0] * 5),
    view_aligned=2)


def _tan(*degs):
    return [float(np.tan(np.radians(d))) for d in degs]


# FIT_VERSION 7: four lobes (three view-aligned, the 4th isotropic), each closure with its own
# Normal N + t T / |T| (T the view tangent): GGX tilts of both signs up to 4 deg (-3 deg near
# the grazing knot, where the mirror direction about the tilted normal comes close to the
# surface), a Diffuse tilted up to 20 deg (Cycles' bump shadowing then shades it), all 0 at
# normal view (where T is the nudged 0: a tilt of 0 gives N exactly, no NaN) and lerped in x
# from there (tilts of hundredths of a degree at 0.5 deg).
TILTED = dict(_fit(
    diffuse=[[0.10, 0.08, 0.06], [0.12, 0.10, 0.05], [0.08, 0.12, 0.10], [0.10, 0.06, 0.12], [0.05, 0.05, 0.05]],
    specular=_lobes(
        [[0.30, 0.20, 0.10], [0.20, 0.30, 0.10], [0.40, 0.20, 0.20], [0.10, 0.20, 0.40], [0.20, 0.20, 0.20]],
        [[0.10, 0.20, 0.30], [0.30, 0.10, 0.20], [0.05, 0.10, 0.10], [0.20, 0.40, 0.10], [0.10, 0.30, 0.30]],
        [[0.05, 0.04, 0.03], [0.04, 0.05, 0.02], [0.06, 0.05, 0.04], [0.03, 0.06, 0.05], [0.08, 0.04, 0.06]],
        [[0.04, 0.03, 0.05], [0.06, 0.02, 0.03], [0.02, 0.06, 0.05], [0.05, 0.03, 0.02], [0.04, 0.04, 0.04]]),
    roughness=_lobes([0.30, 0.35, 0.45, 0.40, 0.40], [0.55, 0.50, 0.45, 0.40, 0.35], [0.20, 0.25, 0.25, 0.22, 0.20],
                     [0.60, 0.65, 0.70, 0.60, 0.50]),
    anisotropy=_lobes([0.3, 0.40, 0.60, 0.50, 0.40], [-0.2, -0.30, -0.40, -0.35, -0.30], [0.0, 0.2, 0.1, 0.0, 0.0],
                      [0.0] * 5),
    view_aligned=3),
    tilt=_lobes(_tan(0.0, 2.0, 1.0, -1.0, 0.0), _tan(0.0, -3.0, -2.0, -3.0, 0.0), _tan(0.0, 4.0, 0.5, 1.5, 0.0),
                _tan(0.0, 1.0, -4.0, -0.5, 0.0)),
    diffuse_tilt=_tan(0.0, 10.0, -15.0, 20.0, 0.0))
# ... and the same without tilts, as a FIT_VERSION 6 fit (the node still renders those: a .blend
# made before the add-on refits it), which renders at normal view exactly what TILTED does
UNTILTED = {k: (6 if k == "version" else v) for k, v in TILTED.items() if k not in ("tilt", "diffuse_tilt")}

# FIT_VERSION 9, anisotropic tables: three lobes along the MATERIAL's tangent (the node's Tangent
# input, unlinked here: world x, which Cycles projects onto each quad as the exact back ends do),
# turned about the normal by tangent_turn, stretched either way and at normal view too, the 4th
# isotropic; no tilts.
MATERIAL = dict(_fit(
    diffuse=[[0.04, 0.05, 0.06], [0.05, 0.04, 0.03], [0.03, 0.06, 0.04], [0.04, 0.04, 0.07], [0.06, 0.03, 0.05]],
    specular=_lobes(
        [[0.40, 0.30, 0.20], [0.30, 0.40, 0.20], [0.50, 0.20, 0.30], [0.20, 0.30, 0.50], [0.30, 0.30, 0.30]],
        [[0.20, 0.30, 0.40], [0.40, 0.20, 0.30], [0.10, 0.20, 0.20], [0.30, 0.50, 0.20], [0.20, 0.40, 0.40]],
        [[0.05, 0.04, 0.03], [0.04, 0.05, 0.02], [0.06, 0.05, 0.04], [0.03, 0.06, 0.05], [0.08, 0.04, 0.06]],
        [[0.03, 0.02, 0.05], [0.05, 0.03, 0.02], [0.04, 0.06, 0.03], [0.02, 0.05, 0.06], [0.06, 0.04, 0.05]]),
    roughness=_lobes([0.25, 0.30, 0.35, 0.30, 0.30], [0.45, 0.50, 0.55, 0.50, 0.45], [0.30, 0.30, 0.35, 0.30, 0.25],
                     [0.60, 0.65, 0.70, 0.60, 0.50]),
    anisotropy=_lobes([0.75, 0.70, 0.60, 0.65, 0.70], [-0.50, -0.60, -0.40, -0.45, -0.50], [0.30, 0.20, 0.10, 0.20, 0.30],
                      [0.0] * 5),
    view_aligned=0), material_aligned=3, tangent_turn=0.6, anisotropic=True)

FITS = {"isotropic": ISOTROPIC, "anisotropic": ANISOTROPIC, "head-on": HEAD_ON, "clamped": CLAMPED,
        "tilted": TILTED, "untilted": UNTILTED, "material": MATERIAL}
MATTE = {"kind": "analytic", "model": "lambert", "albedo": [0.8, 0.7, 0.6]}


def _normal(theta_deg, phi):
    t = np.radians(theta_deg)
    return np.array([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)])


def _quads(fits):
    """[(fit name, theta_i in degrees, on a knot, normal)]: per fit every view angle at
    AZIMUTHS azimuths (offset per angle, so that the angles meet the sun at different ones),
    head-on once; "head-on" only head-on."""
    out = []
    for name in fits:
        degs = (0.0,) if name in ("head-on", "untilted") else sorted(ON_KNOTS_DEG + BETWEEN_DEG)
        for i, deg in enumerate(degs):
            offset = (i * 0.618034) % 1.0
            for k in range(AZIMUTHS if deg > 0 else 1):
                out.append((name, deg, deg in ON_KNOTS_DEG, _normal(deg, 2 * np.pi * (k + offset) / AZIMUTHS)))
    return out


def _scene(tables, fit_files, quads, osl=False):
    """The probe's scene: quads[q] in cell q (row-major) of a square grid, each fit's Learned
    BSDF node bound to `tables` and its fit file; the fit back end. Returns (scene, grid side in
    cells, sun object, {fit name: (status as assigned, status with the fit back end)})."""
    side = int(np.ceil(np.sqrt(len(quads))))
    sc = cs.reset(side * CELL, side * CELL, spp=4, osl=osl)
    sc.cycles.max_bounces = 0               # direct light only
    sc.cycles.pixel_filter_type = 'BOX'     # (one pixel wide): an inner pixel sees one quad
    sc.cycles.light_sampling_threshold = 0.0
    sc.render.use_persistent_data = True    # the renders differ by the sun's direction only
    cam = cs.ortho_camera(sc, distance=60.0, scale=float(side))    # a cell is 1 x 1
    cam.data.clip_end = 200.0
    names = list(fit_files)
    materials = [bpy.data.materials.new(name) for name in names]
    nodes = [lb.assign_learned_bsdf(mat, name, tables, fit_path=fit_files[name]) for mat, name in zip(materials, names)]
    assigned = [lb.node_status(node, sc) for node in nodes]
    verts, faces, index = [], [], []
    for q, (name, _, _, n) in enumerate(quads):
        row, col = divmod(q, side)
        x0, y1 = col - side / 2, side / 2 - row
        cx, cy = x0 + 0.5, y1 - 0.5
        start = len(verts)
        for x, y in ((x0, y1 - 1), (x0 + 1, y1 - 1), (x0 + 1, y1), (x0, y1)):
            verts.append((x, y, -(n[0] * (x - cx) + n[1] * (y - cy)) / n[2]))    # the plane through the centre
        faces.append(tuple(range(start, start + 4)))
        index.append(names.index(name))
    mesh = bpy.data.meshes.new("quads")
    mesh.from_pydata(verts, [], faces)
    mesh.polygons.foreach_set("material_index", index)
    mesh.polygons.foreach_set("use_smooth", [False] * len(faces))
    for mat in materials:
        mesh.materials.append(mat)
    ob = bpy.data.objects.new("quads", mesh)
    ob.visible_shadow = False               # (a tilted quad would shade its neighbours)
    sc.collection.objects.link(ob)
    sun = cs.add_lamp(sc, 'SUN', (0.0, 0.0, 10.0), energy=E, angle=0.0)
    lb.set_backend(sc, "fit")
    status = {name: (a, lb.node_status(node, sc)) for name, a, node in zip(names, assigned, nodes)}
    return sc, side, sun, status


def _aim(sun, zenith_deg):
    """Point the sun from zenith angle `zenith_deg` in the xz plane; returns the direction toward
    it as Cycles gets it (the object's z axis)."""
    from mathutils import Vector
    z = np.radians(zenith_deg)
    sun.rotation_euler = Vector((np.sin(z), 0.0, np.cos(z))).to_track_quat('Z', 'Y').to_euler()
    bpy.context.view_layer.update()
    return np.array(sun.matrix_world.col[2][:3], float)


def _cells(img, side):
    """Per cell (row-major) the mean of its inner (CELL - 2)^2 pixels, and their spread."""
    inner = img.reshape(side, CELL, side, CELL, 3)[:, 1:-1, :, 1:-1]
    inner = inner.transpose(0, 2, 1, 3, 4).reshape(side * side, -1, 3)
    return inner.mean(1), np.ptp(inner, axis=1).max(-1)


def _local(n, v, l, tangent=None):
    """wi, wo in a frame of normal n, its x along v's projection (head-on: along the node's
    fallback tangent n x VIEW_TANGENT_NUDGE), or along `tangent`'s where given (the tables'
    frame of a material-aligned fit)."""
    t = v if tangent is None else tangent
    t = t - (t @ n) * n
    if np.linalg.norm(t) < 1e-12:
        t = np.cross(n, VIEW_TANGENT_NUDGE)
    t /= np.linalg.norm(t)
    frame = np.stack([t, np.cross(n, t), n])
    return frame @ v, frame @ (l / np.linalg.norm(l))


def probe(folder, tables, fits=FITS, osl=False, zeniths=SUN_ZENITH_DEG):
    """Render the probe (the fits written to `folder`, their nodes bound to `tables`) under a
    sun at each zenith angle. Returns a dict: "quads" (_quads), "status" (_scene), per sun
    and quad "got" (rendered, RGB), "ref" (E cos(theta_o) eval_fit), "wi" and "wo" (local
    frame: _local), "spread" (the largest difference of a cell's inner pixels)."""
    files = {}
    for name, fit in fits.items():
        files[name] = Path(folder) / f"{name}.fit.json"
        files[name].write_text(json.dumps(fit))
    quads = _quads(fits)
    sc, side, sun, status = _scene(tables, files, quads, osl)
    assert bool(sc.cycles.shading_system) == osl
    out = {"quads": quads, "status": status, "got": [], "ref": [], "wi": [], "wo": [], "spread": []}
    view = np.array([0.0, 0.0, 1.0])
    for zenith in zeniths:
        toward_sun = _aim(sun, zenith)
        cells, spread = _cells(cs.render(sc), side)
        out["got"].append(cells[:len(quads)])
        out["spread"].append(spread[:len(quads)])
        wi, wo = zip(*(_local(n, view, toward_sun, np.array(lb.TANGENT) if fits[name].get("material_aligned") else None)
                       for name, *_, n in quads))
        out["ref"].append([E * max(o[2], 0.0) * eval_fit(fits[name], i, o[None])[0]
                           for (name, *_), i, o in zip(quads, wi, wo)])
        out["wi"].append(wi)
        out["wo"].append(wo)
    return {k: (v if k in ("quads", "status") else np.array(v, float)) for k, v in out.items()}


@pytest.fixture(scope="module", params=["svm", pytest.param("osl", marks=pytest.mark.slow)])   # (OSL: -m slow)
def rendered(request, tmp_path_factory):
    """The probe rendered with Cycles' SVM, and with its OSL shading system (the fit's closures
    then run as OSL nodes): fits on small baked tables of a Lambertian (the node's tables: the
    fit back end does not read them)."""
    import _cycles
    if request.param == "osl" and not _cycles.with_osl:
        pytest.skip("this bpy build has no OSL")
    folder = tmp_path_factory.mktemp("fit_render")
    lb.register()
    try:
        yield probe(folder, cs.small_tables(MATTE, "matte", folder), osl=request.param == "osl")
    finally:
        lb.unregister()


def _of(result, name, key=("got", "ref", "wi", "wo")):
    """The fit's rows of result[k] for k in `key`, each (suns, quads of the fit, ...)."""
    mask = np.array([q[0] == name for q in result["quads"]])
    return tuple(result[k][:, mask] for k in key)


def _relative(got, ref):
    """Per channel |got - ref| / ref where ref > 0 (flattened)."""
    lit = ref > 0
    return np.abs(got - ref)[lit] / ref[lit]


@pytest.mark.parametrize("name", ["isotropic", "anisotropic", "tilted", "material"])
def test_fit_renders_what_eval_fit_states(rendered, name):
    """Within 1e-3 relative at >= 99 % of the directions, on the knots and between them
    (measured: all within 4.4e-4, median 2e-7 (isotropic) / 7e-7 (anisotropic); the largest
    next to a specular peak of the sharpest lobe, r 0.15-0.2, where Cycles' float 1 - cos^2
    of the half vector rounds)."""
    _, now = rendered["status"][name]
    assert now.startswith("Fit") and now.endswith("(Back End: Fit). Set Back End to Auto"), now
    got, ref, wi, wo = _of(rendered, name)
    assert np.all(np.isfinite(got))
    spread, = _of(rendered, name, ("spread",))
    assert np.all(spread <= 1e-4 * np.maximum(got.max(-1), 1e-6))      # a cell's pixels agree
    dark = ref == 0                             # the sun below the quad's horizon
    assert dark.any() and np.all(got[dark] == 0.0)
    on = np.array([q[2] for q in rendered["quads"] if q[0] == name])
    for where, sel in (("on the knots", on), ("between the knots", ~on)):
        rel = _relative(got[:, sel], ref[:, sel])
        within = np.mean(rel < TOLERANCE)
        assert within >= SHARE, f"{name} {where}: {within:.4f} within {TOLERANCE} (max {rel.max():.3g})"
        assert np.median(rel) < 1e-5, f"{name} {where}: median relative error {np.median(rel):.3g}"
    # The directions span the hemisphere: the (tilted) quads meet the sun in every cell of
    # cos theta_o in fifths x azimuth about wi's in sixths (measured: 8 or more each); the
    # material-aligned fit's views, every sixth of azimuth about its tangent.
    lit = ref[..., 0] > 0
    tilted = np.hypot(wi[..., 0], wi[..., 1]) > 0
    cos_o = wo[..., 2][lit & tilted]
    phi_i = np.arctan2(wi[..., 1], wi[..., 0])
    phi_o = np.abs(np.angle(np.exp(1j * (np.arctan2(wo[..., 1], wo[..., 0]) - phi_i))))[lit & tilted]
    counts = np.histogram2d(cos_o, phi_o, bins=(5, 6), range=((0, 1), (0, np.pi)))[0]
    assert counts.min() >= 5, counts
    if name == "material":
        views = np.histogram(np.abs(phi_i[lit & tilted]), bins=6, range=(0, np.pi))[0]
        assert views.min() >= 5, views


def test_head_on_view_renders_a_finite_lobe(rendered):
    """Anisotropic lobes seen exactly head-on (fits of measured files have them), where
    the view tangent is 0: no NaN, and some orientation of the lobes (within eval_fit's range
    over the tangent's azimuth): the node's fallback tangent n x VIEW_TANGENT_NUDGE (measured:
    within 3.5e-7 of eval_fit with that tangent)."""
    got, ref, wi, wo = _of(rendered, "head-on")
    assert np.all(np.isfinite(got)) and np.all(got >= 0.0)
    np.testing.assert_allclose(wi, np.broadcast_to([0.0, 0.0, 1.0], wi.shape), atol=1e-12)
    assert np.all(got[ref == 0] == 0.0)
    turns = np.linspace(0.0, np.pi, 181)
    for g, w in zip(got[:, 0], wo[:, 0]):
        if w[2] <= 0:
            continue
        c, s = np.cos(turns), np.sin(turns)
        spun = np.stack([c * w[0] - s * w[1], s * w[0] + c * w[1], np.full_like(c, w[2])], -1)
        f = E * w[2] * eval_fit(HEAD_ON, np.array([0.0, 0.0, 1.0]), spun)
        lo, hi = f.min(0) * (1 - TOLERANCE), f.max(0) * (1 + TOLERANCE)
        assert np.all((lo <= g) & (g <= hi)), (g, lo, hi)
    lit = ref > 0
    assert np.max(np.abs(got - ref)[lit] / ref[lit]) < TOLERANCE


def test_tilts_render_as_eval_fit_states_and_none_at_normal_view(rendered):
    """The tilted fit (FIT_VERSION 7: test_fit_renders_what_eval_fit_states[tilted]) per closure
    kind: its Diffuse tilt is seen (the tilted fit's ref differs from the untilted model's where
    the Diffuse dominates), and at normal view, where every tilt is 0, it renders bitwise what
    the same fit without tilts (a FIT_VERSION 6 fit) renders."""
    got, ref, wi, wo = _of(rendered, "tilted")
    untilted_ref = np.array([[E * max(o[2], 0.0) * eval_fit(UNTILTED, i, o[None])[0] for i, o in zip(a, b)]
                             for a, b in zip(wi, wo)])
    lit = ref > 0
    moved = np.abs(ref - untilted_ref)[lit] / ref[lit]
    assert np.mean(moved > 10 * TOLERANCE) > 0.3, np.median(moved)       # the tilts are seen ...
    rel = _relative(got, ref)
    assert np.mean(rel < TOLERANCE) >= SHARE and np.median(rel) < 1e-5, (np.mean(rel < TOLERANCE), np.median(rel))
    head_on = np.array([q[1] == 0.0 for q in rendered["quads"] if q[0] == "tilted"])
    plain, plain_ref, _, _ = _of(rendered, "untilted")
    assert head_on.sum() == 1 and plain.shape[1] == 1
    assert np.all(np.isfinite(got)) and np.array_equal(got[:, head_on], plain), (got[:, head_on], plain)
    lit = plain_ref > 0
    assert np.max(np.abs(plain - plain_ref)[lit] / plain_ref[lit]) < TOLERANCE
    _, now = rendered["status"]["untilted"]
    assert now.startswith("Fit"), now


def test_alphas_beyond_1_render_as_eval_fit_states(rendered):
    got, ref, _, _ = _of(rendered, "clamped")
    rel = _relative(got, ref)
    assert np.mean(rel < TOLERANCE) >= SHARE, f"{np.mean(rel < TOLERANCE):.3f} within, median {np.median(rel):.3g}"


def test_missing_tables_render_the_fit(tmp_path):
    """The node bound to tables that do not exist renders its fit (and says why)."""
    lb.register()
    try:
        fits = {"anisotropic": ANISOTROPIC}
        result = probe(tmp_path, tmp_path / "missing.exr", fits=fits, zeniths=(30.0, 110.0))
    finally:
        lb.unregister()
    assigned, now = result["status"]["anisotropic"]
    assert assigned.startswith("Fit") and "(tables missing). Bake the Material" in assigned, assigned
    rel = _relative(result["got"], result["ref"])
    assert np.mean(rel < TOLERANCE) >= SHARE


# ------------------------------------------------------------------ EEVEE's own output

def _upstream(socket):
    """The nodes feeding `socket` (in its tree, not inside groups)."""
    seen, todo = [], [socket]
    while todo:
        for link in todo.pop().links:
            if link.from_node not in seen:
                seen.append(link.from_node)
                todo.extend(link.from_node.inputs)
    return seen


# A fit with its EEVEE fit (FIT_VERSION 8: closure_fit's "eevee", isotropic lobes)
WITH_EEVEE = dict(ANISOTROPIC, error=0.1, l1_of="file", eevee=dict(ISOTROPIC, model="hand-written EEVEE fit", error=0.2))


def test_eevee_output_takes_the_eevee_fit(tmp_path):
    """The material gets two Material Outputs: target Cycles fed by the node's BSDF (the back
    ends), target EEVEE by its EEVEE output, which holds the EEVEE fit's closures alone: its own
    fit group, isotropic Glossy BSDFs (no Anisotropy or Tangent linked). A fit without an EEVEE
    fit (FIT_VERSION 7) feeds EEVEE the fit's closures; assigning again adds no output. The
    node's status in EEVEE gives the EEVEE fit's error, in Cycles the fit's."""
    lb.register()
    try:
        sc = cs.reset(8, 8)
        for name, fit in (("with", WITH_EEVEE), ("without", dict(ANISOTROPIC, version=7))):
            path = tmp_path / f"{name}.fit.json"
            path.write_text(json.dumps(fit))
            mat = bpy.data.materials.new(name)
            for _ in range(2):
                node = lb.assign_learned_bsdf(mat, name, tmp_path / "missing.exr", fit_path=path)
            outputs = {n.target: n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"}
            assert sorted(outputs) == ["CYCLES", "EEVEE"]
            assert outputs["CYCLES"].inputs["Surface"].links[0].from_socket == node.outputs["BSDF"]
            assert outputs["EEVEE"].inputs["Surface"].links[0].from_socket == node.outputs["EEVEE"]
            group_out = next(n for n in node.node_tree.nodes if n.bl_idname == "NodeGroupOutput")
            cycles, eevee = (_upstream(group_out.inputs[s]) for s in ("BSDF", "EEVEE"))
            fit_groups = [[n.node_tree.name for n in nodes if n.bl_idname == "ShaderNodeGroup"] for nodes in (cycles, eevee)]
            glossies = [n for n in eevee if n.bl_idname == "ShaderNodeBsdfAnisotropic"]
            assert len(glossies) == 3
            if name == "with":
                assert fit_groups == [[fit_nodes.fit_group(WITH_EEVEE).name],
                                      [fit_nodes.fit_group(WITH_EEVEE["eevee"]).name]]
                assert not any(n.inputs["Anisotropy"].is_linked or n.inputs["Tangent"].is_linked for n in glossies)
                assert all(n.inputs["Anisotropy"].default_value == 0.0 for n in glossies)
                assert not set(map(id, cycles)) & set(map(id, eevee))
                lb.set_backend(sc, "fit")
                assert lb.node_status(node, sc).startswith("Fit, ~10 % off the measured material")
                sc.render.engine = _eevee()
                assert lb.node_status(node, sc).startswith("Fit, ~20 % off the measured material")
                sc.render.engine = "CYCLES"
            else:
                assert fit_groups[1] == [fit_nodes.fit_group(dict(ANISOTROPIC, version=7)).name]
                assert group_out.inputs["EEVEE"].links[0].from_node in cycles   # the fit's closures, shared
    finally:
        lb.unregister()


EEVEE_RED = dict(ISOTROPIC, diffuse=[[0.8, 0.05, 0.05]] * 5, specular=_lobes(*[[[0.0] * 3] * 5] * 3))
CYCLES_GREEN = dict(ISOTROPIC, diffuse=[[0.05, 0.8, 0.05]] * 5, specular=_lobes(*[[[0.0] * 3] * 5] * 3),
                    eevee=EEVEE_RED)


def test_eevee_renders_the_eevee_fit_and_cycles_the_fit(tmp_path):
    """A sphere under a white world whose fit is a green Diffuse and its EEVEE fit a red one:
    Cycles renders it green, EEVEE red (each engine its own Material Output)."""
    lb.register()
    try:
        sc = cs.reset(16, 16, spp=4, osl=False)
        cs.ortho_camera(sc, scale=2.2)
        cs.set_world(sc, (1.0, 1.0, 1.0))
        path = tmp_path / "green.fit.json"
        path.write_text(json.dumps(CYCLES_GREEN))
        mat = bpy.data.materials.new("m")
        lb.assign_learned_bsdf(mat, "m", tmp_path / "missing.exr", fit_path=path)
        cs.add_sphere(sc, mat, segments=32, rings=16)
        lb.set_backend(sc, "fit")
        _, hit = cs.sphere_view(16, 16, 2.2)
        means = {}
        for engine in ("CYCLES", _eevee()):
            sc.render.engine = engine
            means[engine] = cs.render(sc)[hit].mean(0)
        (r, g, _), (er, eg, _) = means.values()
        assert g > 4 * r and er > 4 * eg, means
    finally:
        lb.unregister()


def _eevee():
    """EEVEE's engine id: BLENDER_EEVEE_NEXT in 4.2-4.5, BLENDER_EEVEE before and from 5.0."""
    ids = [e.identifier for e in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items]
    return "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in ids else "BLENDER_EEVEE"
