"""Cycles closures fitted to baked tables: the Learned BSDF node's fit back end.

Per view angle (knots in x = 1 - cos theta_i, what Cycles' Layer Weight "Facing" gives),
the baked BSDF f (Tables.eval) is approximated by what Cycles renders on every device and
in EEVEE:

    f_fit = kd / pi  +  sum_j ks_j f_ggx(alpha_j, a_j)

kd, ks_j RGB; f_ggx Cycles' Glossy BSDF with the GGX distribution and colour 1 (Smith
height-correlated G2, no Fresnel), roughness r_j (alpha_j = r_j^2) and Anisotropy a_j, which
Cycles maps to alpha_x = alpha (1 - a), alpha_y = alpha / (1 - a) (a >= 0; a < 0 the other way
round), x along the closure's Tangent. The first VIEW_ALIGNED lobes take as their tangent the
view direction projected onto the surface: measured "isotropic" lobes are wider across the
plane of incidence than along it, which isotropic lobes cannot follow. At normal view too: the
files' lobes there are not round (cc_nothern_aurora at theta_i = 0: their f cos over 2-20 deg
varies 2.1x with the azimuth from the view's), and the exact back ends render that azimuth
from the same projected tangent, so the view-aligned lobes stay anisotropic there (its zero
at exactly normal view is nudged, svm.VIEW_TANGENT_NUDGE). The last lobe is isotropic. Between knots the
node interpolates kd, ks_j, r_j, a_j and the tilts linearly in x.

Tilts (FIT_VERSION 7): each closure has its own Normal N' = N + t V (V the unit view tangent,
t = tan of the tilt toward the view, in the plane of incidence; t = 0 gives N exactly, so
Cycles' bump corrections, which it skips where N' equals N, stay off). A tilted Glossy lobe
reflects 2 t nearer the normal (measured lobes' peaks sit off the mirror direction by tenths of
a degree), a tilted Diffuse leans toward or away from the view (Cycles then multiplies it by its
bump shadowing G1: diffuse_tilt_fcos). GGX tilts within TILT_GGX_DEG (+-4 deg), none at normal
view (the view tangent is arbitrary there), and above tilt_limit: the mirror direction about
the tilted normal stays above the surface by more than Cycles' ensure_valid_specular_reflection
threshold over every knot interval, so that correction never fires and eval_fit is what
Cycles renders (ensure_valid_reflection models it anyway). The Diffuse's within +-20 deg.
A tilted lobe's albedo is the table's untilted one times the tilted / untilted ratio of
estimates from common samples (_ggx_tilt_albedos, within 1 %); the tilted Diffuse's a
quadrature (diffuse_tilt_albedo). Fits of FIT_VERSION 6 (no "tilt" keys) evaluate untilted.

At each knot the fit keeps the baked albedo exactly per channel (kd + sum_j ks_j A_j =
albedo(theta_i), A_j the lobe's albedo) and minimizes the L1 error of f cos over the
hemisphere (weights per channel: an exact non-negative least-squares solve, reweighted for L1;
Monte Carlo over a mixture of the tables', the cosine's and a GGX mixture's samplers, fixed
seed; the lobes' albedos at the knots from ggx_albedo.npz). The lobes' (alpha, a) are searched
on a grid: all of it at normal view, then knot by knot from the previous knot's lobes, moving a
lobe (a tilt: TILT_STEP) costing in proportion to its share of the albedo, the weights pulled toward the previous
knot's, and the next knot's lobes chosen by the error at the knot plus half-way back
(_next_knot), among the descents' results each also relabelled (which of the previous knot's
lobes each continues: where a lobe must take a new shape, the one that carried little should,
else the node's lerp half-way fits neither shape; irid_flake_paint1 at 82.5 deg, between
knots 81 and 84: 0.278 -> 0.145): each lobe keeps its identity and its parameters vary
smoothly with the view angle (lobes that trade identities or jump between knots fit neither
half-way, and a sphere renders concentric rings: test_crossed_lobes_jump_between_knots). Recorded per knot: the relative L2 error of f cos
against the tables (`rel_error`, which the SVM back end's matching reads) and the albedo the
closures reach (`fit_albedo`, equal to `albedo`); per view angle (knots and midpoints up to
88 deg) the relative L1 error of luminance f cos against the measured material when the bake
has it, else the tables (`l1`, `l1_of`), and its median (`error`: the node's status).

Anisotropic tables (FIT_VERSION 9): the first VIEW_ALIGNED lobes lie along the MATERIAL's
tangent (the tables' x: the node's Tangent input, which Cycles projects onto the surface as the
exact back ends do, turned about the normal by the fit's tangent_turn, found at normal view:
a material turned 37 deg gets 37.03), their anisotropy either way on ANISOTROPY_MATERIAL (up to
45:1), the last isotropic; no tilts; the control variate (FIT_VERSION 10) over the view azimuths. Each knot's quadrature, albedo and error
run over PHI_VIEWS view azimuths over the tables' phi_i period (view_azimuths), and so does
`l1`. brushed_steel's default bake (GGX 0.3 x 0.02): median L1 against the material 1.360 ->
0.034 (the former fit: isotropic lobes at phi_i = 0, worse than black), fit 10 s CPU at load
12. Its EEVEE fit (isotropic lobes anywhere on the alpha grid) stays at 1.37: no isotropic
lobe follows a 15:1 streak, and EEVEE renders no anisotropy (the status says how far EEVEE is).

Per knot also the control variate (`cv`: beta_d, beta_s in [0, 1] and a portal share s,
`cv_scales`): the SVM back end renders f_cv = beta_d kd / pi + beta_s sum_j ks_j f_ggx_j as
Cycles closures (which Cycles lights with its own lamp and world sampling, MIS included) with
probability 1 - s, weight 1 / (1 - s), else the rest, f - f_cv, through its Ray Portal with
weight (f - f_cv) cos / (q s) at the portal's direction: unbiased for any beta and s. The
betas keep the rest nowhere negative and minimise the noise for a small bright light from any
direction.

EEVEE (FIT_VERSION 8: the fit's "eevee", itself a fit of the same keys, read by eval_fit and the
node alike): EEVEE renders no anisotropy (its Glossy BSDF drops the input: an anisotropic lobe
renders as the isotropic lobe of the same alpha), so the node's EEVEE output takes closures of
its own, per knot the fit's with every lobe isotropic, each lobe's alpha searched within
EEVEE_REACH grid steps of its fit lobe's (one lobe at a time, the others kept) and the weights
solved anew as the fit's are (albedo kept, L1 of f cos, pulled toward the previous knot's);
tilts as the fit's. Its `l1` against the same target as the fit's, at the same view angles.
Against the files (median L1; the fit's anisotropy dropped -> the EEVEE fit): cm_military_green
0.255 -> 0.247, satin_rosaline 0.120 -> 0.108, vch_golden_yellow 0.249 -> 0.238 (the fit 0.10,
0.07, 0.12), at ~5 % of the fit's time (timed inside the same runs). A coordinate descent of
its lobes over the whole grid (_descend, one sweep) reached 0.218 on cm_military_green at +36 %
of the fit's time; a free isotropic fit (view_aligned 0) 0.212 at a whole fit's time.

`principled_params(fit)` maps a fit to one view-independent Principled BSDF (the
baseline the acceptance script compares against).

One file of ~1000 lines: one algorithm (per-knot lobes, their path across knots, the albedo
kept, the EEVEE variant, the error against the file) whose steps share the GGX albedo table,
the knots and the lobe grid; its file side (path, read, write) is the exporter contract's.
"""
import json
import itertools
from pathlib import Path

import numpy as np

from ..core.mixed_tables import MixedTables
from ..errors import FlowBSDFError
from ..formats import FIT_VERSION, READABLE_FIT_VERSIONS, fit_current
from ..io.exrio import write_rgba_exr
from ..io.files import atomic_path
from ..io.threads import parallel
from ..materials.analytic import ggx_ndf, ggx_lambda, ggx_reflection_pdf, ggx_sample_reflection
from ..maths.fasttables import one_blas_thread
from ..maths.geometry import LUMINANCE, luminance

READABLE_VERSIONS = READABLE_FIT_VERSIONS   # load_fit / eval_fit (bake/formats.py)
MODEL = "diffuse+view-aligned-ggx+tilt"
MODEL_MATERIAL = "diffuse+material-aligned-ggx"     # anisotropic tables' fit
MATCH_N = 16        # the match image's nodes per axis (match_ratios)
MATCH_MAX = 2.0     # its ratios' bound (blender_addon/render/svm/ matches only where the fit is within 10 %)
MATCH_KEY = "flowbsdf_match"
CV_BETAS = np.linspace(0.0, 1.0, 11)
CV_LIGHT_SHARE = 0.5    # the portal mixture's probability of drawing a bright light (cv_scales)
KNOTS_DEG = (0.0, 15.0, 30.0, 40.0, 50.0, 58.0, 65.0, 70.0, 74.0, 78.0, 81.0, 84.0, 86.0, 88.0, 89.5)
LOBES = 4           # GGX lobes; the first VIEW_ALIGNED with the view's tangent and anisotropy
VIEW_ALIGNED = 3
ALPHAS = np.geomspace(0.002, 1.0, 37)                 # alpha = r^2, Cycles' roughness r <= 1
ANISOTROPY = np.round(np.linspace(-0.4, 0.8, 13), 6)  # Cycles' Anisotropy input; 0 at index 4
ISO = int(np.argmin(np.abs(ANISOTROPY)))              # that index: an isotropic lobe
# Anisotropic tables' lobes lie along the material's tangent (module docstring): their anisotropy
# either way, its steps equal in log(alpha_y / alpha_x) (ratio 1.41 a step, as ALPHAS' 1.19 per
# axis), up to a ratio of 45.
ANISOTROPY_MATERIAL = np.round(np.concatenate([-(1 - 1.189 ** -np.arange(11, 0, -1.0)), [0.0],
                                               1 - 1.189 ** -np.arange(1, 12.0)]), 6)
PHI_VIEWS = 8       # anisotropic tables: the view azimuths per knot (over the tables' phi period)
PULL = 0.02         # the weights' pull toward the previous knot's (_Knot.solve), relative to the Gram
STEP_COST = 0.004   # added to the relative L1 per grid step a lobe of all the albedo moves (_descend)
STIFF = 5.0         # _next_knot's stiffer descent: STIFF x STEP_COST
L1_MAX_DEG = 88.0   # the error's view angles: knots and their midpoints up to here
# Tilts (FIT_VERSION 7): each closure's Normal N' = N + t V (V the unit view tangent, t = tan of
# the tilt angle toward the view, in the plane of incidence), lerped in x like the rest.
TILT_GGX_DEG = np.array([-4.0, -3.0, -2.2, -1.5, -1.0, -0.7, -0.45, -0.3, -0.15, -0.07, 0.0,
                         0.07, 0.15, 0.3, 0.45, 0.7, 1.0, 1.5, 2.2, 3.0, 4.0])
TILT_DIFFUSE_DEG = np.array([-20.0, -15.0, -11.0, -8.0, -6.0, -4.0, -2.5, -1.5, -0.7, 0.0,
                             0.7, 1.5, 2.5, 4.0, 6.0, 8.0, 11.0, 15.0, 20.0])
TILT_REACH = 3      # grid steps a tilt may move per descent move
TILT_STEP = 0.5     # _descend's cost of a tilt grid step, in alpha / anisotropy grid steps
RELABEL = True      # _next_knot: each option's lobes also relabelled (_next_knot, _relabellings)
RELABEL_SOLVED = 3  # _next_knot: the relabelled options solved again (the best so many ranked)
NEXT_TILT_ONLY = True   # _next_knot's 4th option: the previous lobes' shapes kept, their tilts descended
TILT_GGX = True     # (switches for the ablation: scripts/fit_acceptance.py --variant)
TILT_DIFFUSE = True
DIFFUSE_TILT_SHARE = 0.0    # the Diffuse tilts only where it carries this share of the albedo (else none: a
                            # tilt it hardly shows, which EEVEE, without Cycles' G1, renders otherwise). 0.1
                            # measured: acceptance median 0.147 -> 0.150, mean 0.199 -> 0.201 (a Diffuse of
                            # a few % tilted 20 deg shapes the grazing views of malachite, mint, ilm)
EEVEE_REACH = 4     # alpha grid steps an EEVEE lobe's alpha may lie from its fit lobe's (_isotropic)
R_MIN = 0.02        # a GGX lobe's tilt keeps the view's mirror direction above cos theta R_MIN (> Cycles'
                    # ensure_valid_specular_reflection threshold 0.01: its correction never fires)


def alphas_xy(alpha, aniso):
    """Cycles' Glossy BSDF (svm closure.h): alpha = r^2 and Anisotropy a -> (alpha_x along the
    tangent, alpha_y across it), each at most 1 (bsdf_microfacet_ggx_setup saturates them)."""
    alpha = np.asarray(alpha, float)
    a = np.clip(np.asarray(aniso, float), -0.99, 0.99)
    return (np.minimum(np.where(a < 0, alpha / (1 + a), alpha * (1 - a)), 1.0),
            np.minimum(np.where(a < 0, alpha * (1 + a), alpha / (1 - a)), 1.0))


def ggx_fcos(wi, wo, alpha, aniso=0.0):
    """Cycles' Glossy BSDF (GGX, colour 1, its tangent along x) times cos theta_o; wi (3,),
    wo (N, 3); alpha and aniso scalars, or (C, 1) for C lobes at once ((C, N) values)."""
    wi = np.broadcast_to(np.asarray(wi, float), wo.shape)
    ax, ay = alphas_xy(alpha, aniso)
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    h = wi + wo
    h = h / np.maximum(np.sqrt(np.einsum("nk,nk->n", h, h))[:, None], 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        g2 = 1.0 / (1.0 + ggx_lambda(wi, ax, ay) + ggx_lambda(wo, ax, ay))
        v = ggx_ndf(h, ax, ay) * g2 / (4.0 * wi[:, 2])
    return np.where(ok, v, 0.0)


def ensure_valid_reflection(wi, n):
    """Cycles' ensure_valid_specular_reflection (closure/bsdf_util.h) with Ng = z: the Glossy
    closure's normal n, raised toward Ng until wi's mirror direction about it is at least
    min(0.9 wi.z, 0.01) above the surface (the material's Bump Map Correction, on by default;
    maybe_ensure_valid_specular_reflection skips it where n equals Ng: the node's zero tilt)."""
    n = np.asarray(n, float)
    r = 2.0 * (n @ wi) * n - wi
    iz = float(wi[2])
    thr = min(0.9 * iz, 0.01)
    if r[2] >= thr:
        return n
    x = n - n[2] * np.array([0.0, 0.0, 1.0])
    lx = np.linalg.norm(x)
    x = x / lx if lx > 0 else n
    ix = float(wi @ x)
    a = ix * ix + iz * iz
    b = 2.0 * (a + iz * thr)
    c = (thr + iz) ** 2
    disc = np.sqrt(max(b * b - 4.0 * a * c, 0.0))
    nz2 = 0.25 * (b + disc) / a if ix < 0 else 0.25 * (b - disc) / a
    return np.sqrt(max(1.0 - nz2, 0.0)) * x + np.sqrt(max(nz2, 0.0)) * np.array([0.0, 0.0, 1.0])


def tilted_normal(t, tb=0.0):
    """The closure Normal the node builds, N + t V + tb B (V = x the view tangent, B = z x V = y),
    normalised (Cycles normalises a closure's Normal input: svm/closure.h)."""
    n = np.array([t, tb, 1.0])
    return n / np.linalg.norm(n)


def ggx_tilt_frame(wi, t, tb=0.0):
    """Rows: the tilted Glossy closure's frame (X, Y, N'') at wi in the xz plane: N'' the tilted
    normal after ensure_valid_reflection, X the view tangent x made orthogonal to it
    (make_orthonormals_tangent: Y = normalize(N'' x T), X = Y x N'')."""
    n = ensure_valid_reflection(wi, tilted_normal(t, tb))
    y = np.cross(n, [1.0, 0.0, 0.0])
    y /= np.linalg.norm(y)
    return np.stack([np.cross(y, n), y, n])


def ggx_tilt_fcos(wi, wo, alpha, aniso, t, tb=0.0):
    """ggx_fcos of a Glossy closure whose Normal is tilted by t (tan, toward the view) and tb
    (across): what Cycles renders with the geometric normal z (f cos about the closure's own
    normal, 0 where wo is under the surface: bsdf.h bump_shadowing_term, bsdf_microfacet.h)."""
    if t == 0.0 and tb == 0.0:
        return ggx_fcos(wi, wo, alpha, aniso)
    m = ggx_tilt_frame(wi, t, tb)
    v = ggx_fcos(m @ wi, wo @ m.T, alpha, aniso)
    return np.where(wo[:, 2] > 0, v, 0.0)


def diffuse_tilt_fcos(wo, t, tb=0.0):
    """A Diffuse closure (colour 1) with its Normal tilted by t, tb, times cos theta_o about z:
    max(N'.wo, 0) / pi, 0 under the surface, times Cycles' bump shadowing G1 of GGX with
    alpha^2 = min(tan^2 d / 8, 1), d the tilt (bsdf.h bump_shadowing_term: a tilted Diffuse)."""
    if t == 0.0 and tb == 0.0:
        return np.maximum(wo[:, 2], 0.0) / np.pi
    n = tilted_normal(t, tb)
    v = np.maximum(wo @ n, 0.0) / np.pi
    a2 = min(0.125 * (1.0 / n[2] ** 2 - 1.0), 1.0)
    ci = np.clip(np.abs(wo[:, 2]), 1e-12, 1.0)
    g1 = 2.0 / (1.0 + np.sqrt(1.0 + a2 * (1.0 / (ci * ci) - 1.0)))
    return np.where(wo[:, 2] >= 1e-6, v * g1, 0.0)


_HEMI_DIFFUSE = {}


def diffuse_tilt_albedo(t):
    """The tilted Diffuse's albedo (view independent): a dense quadrature of the hemisphere."""
    t = float(t)
    if t not in _HEMI_DIFFUSE:
        _HEMI_DIFFUSE[t] = 1.0 if t == 0.0 else float(2 * np.pi * np.mean(diffuse_tilt_fcos(_HEMISPHERE, t)))
    return _HEMI_DIFFUSE[t]


def tilt_limit(theta_next):
    """The least tan-tilt (away from the view: < 0) a GGX lobe may take at a knot whose interval
    ends at theta_next (rad): the mirror direction at theta + 2 |tilt| stays above cos R_MIN
    there, and so over the interval (theta + 2 |tilt| is convex in x along the node's lerp)."""
    room = 0.5 * (np.arccos(R_MIN) - float(theta_next))
    return -float(np.tan(max(room, 0.0)))


def _stratified(n, rng):
    side = int(np.sqrt(n))
    g = (np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
         + rng.random((side * side, 2))) / side
    return g


def _cosine(u):
    r = np.sqrt(u[:, 0])
    phi = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - r * r))], axis=1)


def _view(theta, phi=0.0):
    if phi == 0.0:
        return np.array([np.sin(theta), 0.0, np.cos(theta)])
    return np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def _spin(angle):
    """The rotation by `angle` about z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def view_azimuths(tables):
    """The view azimuths an anisotropic fit is made and measured at (PHI_VIEWS over the tables'
    phi_i period, from 0: the material's tangent); None for isotropic tables."""
    if not tables.anisotropic:
        return None
    period = float(getattr(tables, "phi_period", 2 * np.pi))
    count = max(2, int(round(PHI_VIEWS * period / (2 * np.pi))))
    return period * np.arange(count) / count


def baked_albedo(tables, cos_i, phi=0.0):
    """Exact albedo (RGB) of the baked BSDF for a view at cos theta_i (and azimuth phi): E[W] =
    sum m W over the interpolated table (what a furnace render of the OSL back end converges to)."""
    theta = float(np.arccos(np.clip(cos_i, -1.0, 1.0)))
    wi = _view(theta, phi)[None]
    if isinstance(tables, MixedTables):        # the part theta_i falls in
        tables = tables.parts[tables.part_at(theta)]
    bins, _ = tables._bins(wi)
    m = tables._lerp(tables._m, bins)[0]
    w = tables._lerp(tables._w.astype(np.float64), bins)[0]
    return np.einsum("rc,rck->k", m, w)


_ALBEDOS = {}       # (theta, alpha, a) -> ggx_albedo: the same for every material's knots
ALBEDO_TABLE = Path(__file__).with_name("ggx_albedo.npz")   # scripts/ggx_albedo_table.py writes it
ALBEDO_TABLE_N = 1 << 14


def _albedo_table():
    """The lobes' albedos at the knots (KNOTS_DEG x ALPHAS x ANISOTROPY, ALBEDO_TABLE_N samples
    each: within ~0.2 %) from ALBEDO_TABLE into _ALBEDOS, where its grid is the current one."""
    try:
        with np.load(ALBEDO_TABLE) as z:
            grid = (z["knots_deg"], z["alphas"], z["anisotropy"])
            if not all(np.array_equal(a, b) for a, b in zip(grid, (np.array(KNOTS_DEG), ALPHAS, ANISOTROPY))):
                return
            table = z["albedo"]
    except (OSError, KeyError):
        return
    for i, deg in enumerate(KNOTS_DEG):
        theta = float(np.radians(deg))
        _ALBEDOS.update(((theta, float(al), float(an)), float(table[i, j, k]))
                        for j, al in enumerate(ALPHAS) for k, an in enumerate(ANISOTROPY))


def write_albedo_table(path=ALBEDO_TABLE):
    thetas = np.radians(KNOTS_DEG)
    al, an = np.repeat(ALPHAS, len(ANISOTROPY)), np.tile(ANISOTROPY, len(ALPHAS))
    table = np.stack([_ggx_albedos(float(t), al, an, n=ALBEDO_TABLE_N, seed=1, cache=False) for t in thetas])
    np.savez(path, knots_deg=np.array(KNOTS_DEG), alphas=ALPHAS, anisotropy=ANISOTROPY,
             albedo=table.reshape(len(thetas), len(ALPHAS), len(ANISOTROPY)))


def _ggx_albedos(theta, alphas, anisos, n=1024, seed=0, cache=True, phi=0.0):
    """ggx_albedo at wi = (sin theta cos phi, sin theta sin phi, cos theta) of lobes (alphas[i],
    anisos[i]), tangent x: from the table at the knots (phi 0), else computed together (n
    samples each) and kept. (A lobe along x has the same albedo at phi, -phi and pi - phi.)"""
    if cache and not _ALBEDOS:
        _albedo_table()
    phi = float(np.arctan2(abs(np.sin(phi)), abs(np.cos(phi))))
    tail = () if phi < 1e-12 else (phi,)
    keys = [(float(theta), float(a), float(b)) + tail for a, b in zip(alphas, anisos)]
    missing = sorted(set(k for k in keys if k not in _ALBEDOS)) if cache else keys
    out = {}
    for start in range(0, len(missing), 64):        # (bounded memory)
        part = missing[start:start + 64]
        al, an = np.array(part).T[1:3]
        wi = _view(theta, phi if tail else 0.0)
        u = _stratified(n, np.random.default_rng(seed))
        ax, ay = alphas_xy(np.repeat(al, len(u)), np.repeat(an, len(u)))
        wo = ggx_sample_reflection(wi, ax, ay, np.tile(u, (len(al), 1)))
        p = ggx_reflection_pdf(wi, wo, ax, ay).reshape(len(al), -1)
        v = ggx_fcos(wi, wo, np.repeat(al, len(u)), np.repeat(an, len(u))).reshape(len(al), -1)
        est = np.mean(np.where(p > 0, v / np.where(p > 0, p, 1.0), 0.0), axis=1)
        out.update(zip(part, (float(e) for e in est)))
    if not cache:
        return np.array([out[k] for k in keys])
    _ALBEDOS.update(out)
    return np.array([_ALBEDOS[k] for k in keys])


_TILT_EST = {}      # (theta, alpha, a, t) -> the lobe's albedo estimate from TILT_ALBEDO_N common samples
TILT_ALBEDO_N = 256


def _ggx_tilt_albedos(theta, alphas, anisos, t, n=TILT_ALBEDO_N, seed=0):
    """Albedos of tilted lobes: the untilted lobe's (_ggx_albedos: the table at the knots) times
    the ratio of the tilted and untilted lobes' estimates from the same n stratified samples,
    each lobe sampled in its own frame (common numbers: the ratio's noise is far below either
    estimate's; its part under the surface, which Cycles drops, is lost), kept."""
    base = _ggx_albedos(theta, alphas, anisos)
    if t == 0.0:
        return base
    keys = [(float(theta), float(a), float(b)) for a, b in zip(alphas, anisos)]
    wi = _view(theta)
    m = ggx_tilt_frame(wi, t)
    u = _stratified(n, np.random.default_rng(seed))
    for frame, tt in ((None, 0.0), (m, float(t))):
        missing = sorted(set(k for k in keys if k + (tt,) not in _TILT_EST))
        w_in = wi if frame is None else m @ wi
        for start in range(0, len(missing), 64):
            part = missing[start:start + 64]
            _, al, an = np.array(part).T
            ax, ay = alphas_xy(np.repeat(al, len(u)), np.repeat(an, len(u)))
            lo = ggx_sample_reflection(w_in, ax, ay, np.tile(u, (len(al), 1)))
            p = ggx_reflection_pdf(w_in, lo, ax, ay)
            v = ggx_fcos(w_in, lo, np.repeat(al, len(u)), np.repeat(an, len(u)))
            if frame is not None:
                v = np.where((lo @ frame)[:, 2] > 0, v, 0.0)
            est = np.mean(np.where(p > 0, v / np.where(p > 0, p, 1.0), 0.0).reshape(len(al), -1), axis=1)
            _TILT_EST.update(((k + (tt,)), float(e)) for k, e in zip(part, est))
    ratio = [(_TILT_EST[k + (float(t),)] / _TILT_EST[k + (0.0,)]) if _TILT_EST[k + (0.0,)] > 0 else 1.0 for k in keys]
    return base * np.array(ratio)


def ggx_albedo(wi, alpha, aniso=0.0, n=1024, seed=0):
    """The albedo of Cycles' Glossy GGX (colour 1, tangent x) at wi: its own VNDF sampling."""
    theta = float(np.arctan2(np.hypot(wi[0], wi[1]), wi[2]))
    return float(_ggx_albedos(theta, [alpha], [aniso], n=n, seed=seed)[0])


class _Knot:
    """One view angle's Monte Carlo quadrature of the hemisphere: directions drawn from the
    tables, the cosine and a mixture of GGX lobes over ALPHAS (so that a lobe of any width has
    samples), their weights 1 / (n q) for the mixture's density q, and the baked f cos there."""

    def __init__(self, tables, theta, n=1024, seed=0, phis=None, turn=0.0):
        rng = np.random.default_rng(seed)
        if phis is not None and theta == 0.0:
            phis = phis[:1]             # (every azimuth is the same view)
        self.theta, self.phis = float(theta), phis
        # the views: one (azimuth 0), or for anisotropic tables one per azimuth in `phis`, each
        # with n / len(phis) samples of each kind; the knot's sums run over all of them
        views = [_view(theta)] if phis is None else [_view(theta, float(p)) for p in phis]
        each = n if phis is None else max(n // len(views), 64)
        wos, ws, wis, self.views = [], [], [], []
        for wi in views:
            wt = tables.sample(wi, _stratified(each, rng))[0]
            wc = _cosine(_stratified(each, rng))
            u = _stratified(each, rng)
            pick = ALPHAS[rng.integers(len(ALPHAS), size=len(u))]
            wg = ggx_sample_reflection(wi, pick, pick, u)
            draws = len(wt) + len(wc) + len(wg)
            wo = np.concatenate([wt, wc, wg])
            wo = wo[wo[:, 2] > 0]
            q = (tables.pdf(wi, wo) + wo[:, 2] / np.pi
                 + np.mean([ggx_reflection_pdf(wi, wo, a, a) for a in ALPHAS], axis=0)) / 3.0
            start = sum(len(x) for x in wos)
            self.views.append((wi, slice(start, start + len(wo))))
            wos.append(wo)
            ws.append(1.0 / (q * draws))
            wis.append(np.broadcast_to(wi, wo.shape))
        self.wi = views[0]
        self.wo, self.w = np.concatenate(wos), np.concatenate(ws)
        # each sample's own view (the knot's one wi where it has one)
        self.wi_s = self.wi if phis is None else np.concatenate(wis)
        self.g = np.concatenate([tables.eval(wi, self.wo[sl]) for wi, sl in self.views]) * self.wo[:, 2:3]
        # the albedo the closures keep: the views' mean
        self.albedo = np.mean([baked_albedo(tables, np.cos(theta), 0.0 if phis is None else float(p))
                               for p in ([0.0] if phis is None else phis)], axis=0)
        # the lobes' anisotropy grid: the view's tangent's, or the material's (anisotropic tables),
        # the lobes' tangent then at azimuth `turn` in the tables' frame (tangent_turn)
        self.anisos = ANISOTROPY if phis is None else ANISOTROPY_MATERIAL
        self.turn = float(turn)
        if phis is not None:
            spin = _spin(-self.turn)
            self._wi_lobe, self._wo_lobe = self.wi_s @ spin.T, self.wo @ spin.T
        self.iso = int(np.argmin(np.abs(self.anisos)))
        # grid point -> row of _vals: GGX lobes (ia, ja, it) (ALPHAS[ia], ANISOTROPY[ja], tilt
        # TILT_GGX_DEG[it]), the Diffuse (-1, 0, it) (tilt TILT_DIFFUSE_DEG[it])
        self._row = {}
        cap = 256                                   # (storage grown by doubling)
        self._vals = np.zeros((cap, len(self.wo)))  # (rows, N) f cos of the diffuse and each lobe
        self._albs = np.zeros(cap)
        # their weighted inner products (what least squares needs), grown with the rows
        self._gram = np.zeros((cap, cap))
        self._rhs = np.zeros((cap, 3))
        self.tilt_min = -np.inf     # the least GGX tilt (tan) allowed here (fit_closures: tilt_limit)

    def rows(self, keys):
        """The rows of lobes (ia, ja, it) in the knot's arrays of f cos values and albedos, the
        missing ones computed together (per tilt)."""
        missing = sorted({tuple(k) for k in keys if tuple(k) not in self._row})
        if missing:
            groups = {}
            for k in missing:
                groups.setdefault((k[0] < 0, k[2]), []).append(k)
            new, albs, order = [], [], []
            for (diffuse, it), ks in sorted(groups.items()):
                if diffuse:
                    t = float(np.tan(np.radians(TILT_DIFFUSE_DEG[it])))
                    new.append(diffuse_tilt_fcos(self.wo, t)[None])
                    albs.append(np.array([diffuse_tilt_albedo(t)]))
                else:
                    t = float(np.tan(np.radians(TILT_GGX_DEG[it])))
                    ia, ja, _ = np.array(ks).T
                    if self.phis is None:
                        new.append(ggx_tilt_fcos(self.wi, self.wo, ALPHAS[ia][:, None], ANISOTROPY[ja][:, None], t))
                        albs.append(_ggx_tilt_albedos(self.theta, ALPHAS[ia], ANISOTROPY[ja], t))
                    else:                   # (no tilts: the lobes along the material's tangent x)
                        new.append(ggx_fcos(self._wi_lobe, self._wo_lobe, ALPHAS[ia][:, None], self.anisos[ja][:, None]))
                        albs.append(np.mean([_ggx_albedos(self.theta, ALPHAS[ia], self.anisos[ja], phi=float(p) - self.turn)
                                             for p in self.phis], axis=0))
                order += ks
            new = np.concatenate(new)
            base, m = len(self._row), len(new)
            if base + m > len(self._albs):
                cap = max(2 * len(self._albs), base + m)
                grow = lambda a, shape: np.concatenate([a, np.zeros((cap - len(a),) + shape)])  # noqa: E731
                self._vals = grow(self._vals, self._vals.shape[1:])
                self._albs = grow(self._albs, ())
                self._rhs = grow(self._rhs, (3,))
                gram = np.zeros((cap, cap))
                gram[:base, :base] = self._gram[:base, :base]
                self._gram = gram
            nw = new * self.w
            cross = nw @ self._vals[:base].T
            self._gram[base:base + m, :base] = cross
            self._gram[:base, base:base + m] = cross.T
            self._gram[base:base + m, base:base + m] = nw @ new.T
            self._rhs[base:base + m] = nw @ self.g
            self._vals[base:base + m] = new
            self._albs[base:base + m] = np.concatenate(albs)
            self._row.update((k, base + i) for i, k in enumerate(order))
        return np.array([self._row[tuple(k)] for k in keys], int)

    def albedos(self, keys):
        rows = self.rows(keys)
        return self._albs[rows]

    def fcos_of(self, fit):
        """f cos (N, 3) of a fit (or a dict of its per-knot keys) at the knot's samples, each at its view."""
        return np.concatenate([eval_fit(fit, wi, self.wo[sl]) for wi, sl in self.views]) * self.wo[:, 2:3]

    def target_fcos(self, material):
        """f cos (N, 3) of a material at the knot's samples, each at its view."""
        return np.concatenate([material.eval(wi, self.wo[sl]) for wi, sl in self.views]) * self.wo[:, 2:3]

    def solve(self, candidates, prev=None, irls=1):
        """Best weights of each candidate set of lobes [[diffuse, (ia, ja, it), ...], ...]:
        (weights (C, K, 3), relative L1 of luminance f cos (C,)). `prev` (K, 3): the previous
        knot's weights, which a small Tikhonov term pulls toward where the error is flat (a rough
        lobe and the diffuse trade places at little cost: left free they swap between knots)."""
        idx = self.rows([p for cand in candidates for p in cand]).reshape(len(candidates), -1)     # (C, K)
        a = self._albs[idx]                                                          # (C, K)
        g, w = self.g, self.w
        delta = 0.05 * np.maximum(self.albedo, 1e-6) / (2 * np.pi)
        for it in range(irls):
            if it == 0:             # least squares: from the knot's inner products, one Gram for the channels
                kk = idx.shape[1]
                gram = np.broadcast_to(self._gram[idx[:, :, None], idx[:, None, :]][:, None], (len(idx), 3, kk, kk))
                rhs = self._rhs[idx].transpose(0, 2, 1)
            else:                   # reweighted for L1, per channel
                basis = self._vals[idx]                                                            # (C, K, N)
                rho = 1.0 / np.maximum(np.abs(g[None] - (k @ basis).transpose(0, 2, 1)), delta)  # (C, N, 3)
                bw = basis[:, None] * (w[None, :, None] * rho).transpose(0, 2, 1)[:, :, None]   # (C, 3, K, N)
                gram = bw @ basis.transpose(0, 2, 1)[:, None]                                  # (C, 3, K, K)
                rhs = (bw @ g.T[None, :, :, None])[..., 0]                                     # (C, 3, K)
            if prev is not None:
                lam = PULL * np.trace(gram, axis1=-2, axis2=-1) / gram.shape[-1]
                gram = gram + lam[..., None, None] * np.eye(gram.shape[-1])
                rhs = rhs + lam[..., None] * np.asarray(prev).T[None]
            k = _simplex_lsq(gram, rhs, a, self.albedo)                                       # (C, 3, K)
        # the relative L1 of luminance: the weights' luminance times the lobes
        resid_y = g @ LUMINANCE - np.einsum("ck,ckn->cn", k.transpose(0, 2, 1) @ LUMINANCE, self._vals[idx])
        l1 = (np.abs(resid_y) @ w) / max(float(w @ luminance(g)), 1e-300)
        return k.transpose(0, 2, 1), l1


def _simplex_lsq(gram, rhs, a, albedo):
    """argmin 1/2 k G k - b k subject to k >= 0 and a . k = albedo, per (candidate, channel):
    G (C, H, K, K), b (C, H, K), a (C, K), albedo (H,). Exact: the optimum's support is one of
    the 2^K - 1 subsets, on which the constraint's KKT system gives it; the best feasible wins."""
    c, h, kk = rhs.shape
    best = np.full((c, h), np.inf)
    out = np.zeros((c, h, kk))
    ridge = 1e-10 * np.trace(gram, axis1=-2, axis2=-1)[..., None, None] + 1e-300
    for m in range(1, kk + 1):      # the subsets of m lobes together (S of them)
        subsets = np.array(list(itertools.combinations(range(kk), m)))              # (S, m)
        s_n = len(subsets)
        sys = np.zeros((c, h, s_n, m + 1, m + 1))
        sys[..., :m, :m] = (gram[:, :, subsets[:, :, None], subsets[:, None, :]]
                            + ridge[..., None, :, :] * np.eye(m))
        sys[..., :m, m] = a[:, subsets][:, None]
        sys[..., m, :m] = a[:, subsets][:, None]
        b = np.concatenate([rhs[:, :, subsets], np.broadcast_to(albedo[None, :, None, None], (c, h, s_n, 1))], -1)
        sol = np.linalg.solve(sys, b[..., None])[..., :m, 0]                        # (C, H, S, m)
        k = np.zeros((c, h, s_n, kk))
        np.put_along_axis(k, np.broadcast_to(subsets, (c, h, s_n, m)), np.maximum(sol, 0.0), -1)
        obj = 0.5 * np.einsum("chsk,chkl,chsl->chs", k, gram, k) - np.einsum("chk,chsk->chs", rhs, k)
        ok = np.all(sol >= -1e-9 * np.abs(albedo)[None, :, None, None], -1)
        obj = np.where(ok, obj, np.inf)
        for si in range(s_n):       # (the order of the former loop: ties go to the first subset)
            better = obj[..., si] < best
            best = np.where(better, obj[..., si], best)
            out = np.where(better[..., None], k[:, :, si], out)
    # The equality exactly (the clamp above moved a feasible solution by < 1e-9 at most).
    fit_alb = np.einsum("ck,chk->ch", a, out)
    return out * np.where(fit_alb > 0, albedo / np.where(fit_alb > 0, fit_alb, 1.0), 0.0)[..., None]


def _neighbours(p, lobe, aniso, coarse=None, n_aniso=len(ANISOTROPY)):
    """The grid points a GGX lobe at p may move its shape to at the next knot (its tilt kept):
    any alpha (every third where `coarse` is None, else within two steps of `coarse`); the
    anisotropy (a grid of n_aniso) within two steps (one of `coarse`) for the first `aniso`
    lobes (the aligned ones; 0: none moves it)."""
    ia, ja = (p if coarse is None else coarse)[:2]
    if coarse is None:
        alphas, reach = range(0, len(ALPHAS), 3), 2
    else:
        alphas, reach = range(max(ia - 2, 0), min(ia + 2, len(ALPHAS) - 1) + 1), 1
    jas = (range(max(ja - reach, 0), min(ja + reach, n_aniso - 1) + 1)
           if lobe < aniso else [ja])
    return [(i, j, p[2]) for i in alphas for j in jas]


def _tilt_neighbours(knot, p):
    """The tilts a lobe (or the Diffuse, p[0] < 0) at p may move to: within TILT_REACH grid
    steps, none at normal view (the view tangent is arbitrary there), a GGX lobe's above the
    knot's tilt_min; [] where that kind of tilt is off."""
    diffuse = p[0] < 0
    if not (TILT_DIFFUSE if diffuse else TILT_GGX) or knot.theta == 0.0 or knot.phis is not None:
        return []
    grid = TILT_DIFFUSE_DEG if diffuse else TILT_GGX_DEG
    its = range(max(p[2] - TILT_REACH, 0), min(p[2] + TILT_REACH, len(grid) - 1) + 1)
    if not diffuse:
        its = [it for it in its if np.tan(np.radians(grid[it])) >= knot.tilt_min - 1e-12]
    return [(p[0], p[1], it) for it in its if it != p[2]]


def _tilt_zero(diffuse):
    """The index of tilt 0 in the Diffuse's or the GGX lobes' grid."""
    return int(np.flatnonzero((TILT_DIFFUSE_DEG if diffuse else TILT_GGX_DEG) == 0.0)[0])


def _clamp_tilts(knot, lobes):
    """The lobes with tilts the knot allows (0 at normal view and for anisotropic tables; a GGX
    lobe's raised to tilt_min)."""
    out = []
    for p in lobes:
        it = p[2]
        if knot.theta == 0.0 or knot.phis is not None or not (TILT_DIFFUSE if p[0] < 0 else TILT_GGX):
            it = _tilt_zero(p[0] < 0)
        elif p[0] >= 0:
            while np.tan(np.radians(TILT_GGX_DEG[it])) < knot.tilt_min - 1e-12:
                it += 1
        out.append((p[0], p[1], it))
    return out


def _descend(knot, lobes, aniso, prev=None, sweeps=2, step_cost=STEP_COST, shapes=True):
    """Coordinate descent over the lobes' grid points from the previous knot's (lobes[0] the
    Diffuse, whose only coordinate is its tilt): the relative L1 plus, per lobe, STEP_COST times
    its share of the previous knot's albedo times the grid steps it moved (a lobe that carries
    little may jump; one that carries much moves smoothly). Per GGX lobe its shape (alpha,
    anisotropy; not when `shapes` is False), then its tilt (a grid step of tilt costs TILT_STEP
    steps)."""
    start = _clamp_tilts(knot, lobes)
    share = np.zeros(len(start))
    if prev is not None:
        albs = knot.albedos(start)
        lum = luminance(np.asarray(prev))
        share = lum * albs / max(float(lum @ albs), 1e-300)
    diffuse_tilts = share[0] >= DIFFUSE_TILT_SHARE
    if not diffuse_tilts:
        start[0] = (start[0][0], start[0][1], _tilt_zero(True))

    def cost(sets, l1):
        steps = np.array([[abs(p[0] - s[0]) + abs(p[1] - s[1]) + TILT_STEP * abs(p[2] - s[2])
                           for p, s in zip(c, start)] for c in sets])
        return l1 + step_cost * (steps @ share)
    lobes = list(start)
    best = cost([lobes], knot.solve([lobes], prev)[1])[0]

    def take(sets):
        nonlocal best, lobes
        c = cost(sets, knot.solve(sets, prev)[1])
        i = int(np.argmin(c))
        if c[i] < best * (1 - 1e-4):
            best, lobes = float(c[i]), sets[i]
            return True, sets[i]
        return False, sets[i]
    for _ in range(sweeps):
        moved = False
        for j in range(len(lobes)):
            if j > 0 and shapes:
                coarse = None
                for _ in range(2):          # every third alpha, then around the best of those
                    m, pick = take([lobes[:j] + [p] + lobes[j + 1:]
                                    for p in _neighbours(lobes[j], j - 1, aniso, coarse, len(knot.anisos))])
                    coarse, moved = pick[j], moved or m
            tilts = _tilt_neighbours(knot, lobes[j]) if j > 0 or diffuse_tilts else []
            if tilts:
                m, _ = take([lobes[:j] + [p] + lobes[j + 1:] for p in tilts])
                moved = moved or m
        if not moved:
            break
    return lobes


TURN_STEP = np.radians(7.5)     # tangent_turn's first grid over [0, 90 deg), then halved 4 times


def tangent_turn(tables, n=1024, seed=0):
    """The azimuth (rad, in the tables' frame) of anisotropic tables' lobes' tangent: the lobe
    stretched along x at psi is the one stretched along y at psi + 90 deg (the anisotropy's sign),
    so psi in [0, 90 deg); brushed metals have theirs along the tables' x or y (psi 0), a material
    turned 37 deg its own. Chosen at normal view, where the lobes' orientation is all there is to
    see: by the error of the best Diffuse + one aligned lobe (every third alpha, every other
    anisotropy) on a grid of TURN_STEP, then refined around the best by halving steps."""
    phis = view_azimuths(tables)[:1]
    errors = {}

    def error(psi):
        psi = float(np.mod(psi, np.pi / 2))
        if psi not in errors:
            knot = _Knot(tables, 0.0, n=n, seed=seed, phis=phis, turn=psi)
            flat = _tilt_zero(False)
            sets = [[(-1, 0, _tilt_zero(True)), (i, ja, flat)]
                    for i in range(0, len(ALPHAS), 3) for ja in range(0, len(knot.anisos), 2)]
            errors[psi] = float(np.min(knot.solve(sets)[1]))
        return errors[psi]
    best = min(np.arange(0.0, np.pi / 2 - 1e-9, TURN_STEP), key=error)
    step = TURN_STEP
    for _ in range(4):
        step /= 2
        best = min((best - step, best, best + step), key=error)
    return float(np.mod(best, np.pi / 2))


def _first_knot(knot, aligned):
    """Normal view: isotropic lobes chosen greedily over the whole alpha grid, then refined by
    coordinate descent over it, the aligned ones' anisotropy too (no tilts here). Anisotropic
    tables (lobes along the material's tangent: anisotropic at normal view too): the aligned
    lobes chosen greedily over every other alpha and every anisotropy, the rest isotropic."""
    lobes = [(-1, 0, _tilt_zero(True))]
    flat = _tilt_zero(False)
    for j in range(LOBES):
        if knot.phis is not None and j < aligned:
            shapes = [(i, ja) for i in range(0, len(ALPHAS), 2) for ja in range(len(knot.anisos))]
        else:
            shapes = [(i, knot.iso) for i in range(len(ALPHAS))]
        sets = [lobes + [(i, ja, flat)] for i, ja in shapes]
        lobes = sets[int(np.argmin(knot.solve(sets)[1]))]
    return _descend(knot, lobes, aniso=aligned)


def _knot_params(knot, lobes, k):
    """The fit's per-knot entries of lobes (diffuse first) with weights k (K, 3)."""
    return {"x": float(1.0 - np.cos(knot.theta)), "diffuse": [float(v) for v in k[0]],
            "specular": [[float(v) for v in row] for row in k[1:]],
            "roughness": [float(np.sqrt(ALPHAS[p[0]])) for p in lobes[1:]],
            "anisotropy": [float(knot.anisos[p[1]]) for p in lobes[1:]],
            "tilt": [float(np.tan(np.radians(TILT_GGX_DEG[p[2]]))) for p in lobes[1:]],
            "diffuse_tilt": float(np.tan(np.radians(TILT_DIFFUSE_DEG[lobes[0][2]])))}


PARAM_KEYS = ("x", "diffuse", "specular", "roughness", "anisotropy", "tilt", "diffuse_tilt")


def _relabellings(view_aligned, n):
    """The orders of a knot's n closures that exchange the labels of two lobes of a kind (two
    view-aligned GGX lobes, 1 .. view_aligned, or two isotropic ones), the Diffuse first; the
    identity first. (All permutations, 3 or 4 lobes of a kind, measured no better on the ten
    shared files and cost 1.26x the fit on anisotropic tables, whose 4 lobes are all isotropic.)"""
    out = [list(range(n))]
    for lo, hi in ((1, 1 + view_aligned), (1 + view_aligned, n)):
        for i, j in itertools.combinations(range(lo, hi), 2):
            order = list(range(n))
            order[i], order[j] = j, i
            out.append(order)
    return out


def _next_knot(knot, mid, fit, lobes, prev, aligned):
    """(lobes, weights) at the next knot: of the descent from the previous knot's lobes, the
    same made stiffer (STIFF times the cost of moving), the previous lobes kept (weights
    alone refitted) and kept but for their tilts (NEXT_TILT_ONLY), each also relabelled
    (RELABEL: which of the previous knot's lobes each continues, _relabellings), the one whose
    error at this knot plus half-way from the previous knot (the node lerps the parameters
    between them: a lobe that changes its shape while it carries much fits neither knot
    there) is least. Relabelled options are ranked with their weights permuted (the same
    error at the knot); the RELABEL_SOLVED best of them are solved again (weights pulled
    toward the previous knot's of their new labels: near-twin lobes then split their weight
    otherwise) and measured again before they compete. `mid`: the _Knot half-way from the
    previous knot (fit_closures' quadratures)."""
    norm = max(float(mid.w @ luminance(mid.g)), 1e-300)

    def between(option, k):         # the relative L1 half-way, the parameters lerped
        this = _knot_params(knot, option, k)
        pair = {key: fit[key][-1:] + [this[key]] for key in PARAM_KEYS}
        pair.update(material_aligned=fit.get("material_aligned", 0), tangent_turn=fit.get("tangent_turn", 0.0))
        return float(mid.w @ np.abs(luminance(mid.fcos_of(pair) - mid.g)) / norm)
    options = [_descend(knot, lobes, aligned, prev),
               _descend(knot, lobes, aligned, prev, step_cost=STIFF * STEP_COST),
               _clamp_tilts(knot, lobes)]
    if NEXT_TILT_ONLY and (TILT_GGX or TILT_DIFFUSE):
        options.append(_descend(knot, lobes, aligned, prev, shapes=False))
    options = [o for i, o in enumerate(options) if o not in options[:i]]
    ks, l1s = knot.solve(options, prev, irls=4)
    scored = [(l1 + between(o, k), o, k) for o, k, l1 in zip(options, ks, l1s)]
    best = min(scored, key=lambda c: c[0])
    if RELABEL:
        seen = {tuple(o) for o in options}
        relabelled = []
        for order in _relabellings(aligned, len(lobes))[1:]:
            for o, k, l1 in zip(options, ks, l1s):
                o, k = [o[i] for i in order], k[order]
                if tuple(o) not in seen:
                    seen.add(tuple(o))
                    relabelled.append((l1 + between(o, k), o))
        relabelled = sorted(relabelled, key=lambda c: c[0])[:RELABEL_SOLVED]
        if relabelled and relabelled[0][0] < best[0]:
            rs = [o for _, o in relabelled]
            ks, l1s = knot.solve(rs, prev, irls=4)
            best = min([best] + [(l1 + between(o, k), o, k) for o, k, l1 in zip(rs, ks, l1s)], key=lambda c: c[0])
    return best[1], best[2]


def _isotropic(knot, lobes, prev):
    """(lobes, weights) of the knot's EEVEE fit (module docstring): the fit's `lobes` made
    isotropic, each formerly anisotropic lobe's alpha the best within EEVEE_REACH steps of
    its own (in turn, the others kept; anywhere on the grid for anisotropic tables: a lobe along
    the material's tangent seen from every azimuth is nothing like the isotropic lobe of its
    alpha); `prev` the previous knot's EEVEE weights (or None)."""
    reach = EEVEE_REACH if knot.phis is None else len(ALPHAS)
    iso = [lobes[0]] + [(p[0], knot.iso, p[2]) for p in lobes[1:]]
    for j, p in enumerate(lobes[1:], 1):
        if p[1] == knot.iso:
            continue
        sets = [iso[:j] + [(i, knot.iso, p[2])] + iso[j + 1:]
                for i in range(max(p[0] - reach, 0), min(p[0] + reach, len(ALPHAS) - 1) + 1)]
        iso = sets[int(np.argmin(knot.solve(sets, prev)[1]))]
    return iso, knot.solve([iso], prev, irls=4)[0][0]


# One OpenBLAS thread: the fit's products are small, and two threads made it 1.7-2.4x slower on the
# loaded 2-core machine (same choices, weights within 1e-13).
@one_blas_thread()
def fit_closures(tables, knots_deg=KNOTS_DEG, n=1024, seed=0, material=None, view_aligned=None):
    """The fit as a JSON-able dict (module docstring): per knot x = 1 - cos theta_i, kd (RGB),
    per lobe ks (RGB), Cycles roughness r = sqrt(alpha), anisotropy and tilt (tan, N' = N + t V),
    the Diffuse's tilt, the relative L2 error of f cos, the albedos and the control variate; per
    view angle the L1 error against `material` (the measured file) when given, else the tables."""
    view_aligned = 0 if tables.anisotropic else (VIEW_ALIGNED if view_aligned is None else view_aligned)
    # anisotropic tables: the first VIEW_ALIGNED lobes along the material's tangent instead
    material_aligned = VIEW_ALIGNED if tables.anisotropic else 0
    aligned = view_aligned or material_aligned
    phis = view_azimuths(tables)
    turn = tangent_turn(tables, n, seed) if tables.anisotropic else 0.0
    out = {"format": "flowbsdf-closure-fit", "version": FIT_VERSION,
           "model": MODEL_MATERIAL if tables.anisotropic else MODEL,
           "view_aligned": view_aligned, "material_aligned": material_aligned, "tangent_turn": turn,
           "anisotropic": bool(tables.anisotropic),
           "x": [], "theta_deg": [], "diffuse": [], "specular": [], "roughness": [], "anisotropy": [],
           "tilt": [], "diffuse_tilt": [], "rel_error": [], "albedo": [], "fit_albedo": [], "cv": []}
    eevee = {key: [] for key in PARAM_KEYS}
    lobes = prev = prev_iso = None
    # Knots ascending in x = 1 - cos theta (Facing), i.e. ascending theta.
    knots = sorted(knots_deg)
    # Each knot's quadrature and the one half-way from the previous knot (_next_knot's) depend on
    # the tables alone: drawn in threads ahead of the fit, which goes knot by knot from the
    # previous knot's lobes (each quadrature from its own seed: the same as drawn in turn).
    quadratures = parallel(lambda q: _Knot(tables, q[0], n=q[1], seed=q[2], phis=phis, turn=turn), [
        q for i, deg in enumerate(knots)
        for q in ([] if i == 0 else [(0.5 * (float(np.radians(deg)) + np.radians(float(knots[i - 1]))), n // 2, seed + 7)])
        + [(np.radians(deg), n, seed)]])
    cv_args = []            # each knot's control variate: from its fit alone, in threads after the fit
    for i, deg in enumerate(knots):
        mid = None if i == 0 else next(quadratures)
        knot = next(quadratures)
        # (anisotropic tables: no tilts)
        knot.tilt_min = 0.0 if tables.anisotropic else tilt_limit(np.radians(knots[i + 1] if i + 1 < len(knots) else 90.0))
        if lobes is None:
            lobes = _first_knot(knot, aligned)
            k = knot.solve([lobes], None, irls=4)[0][0]
        else:
            lobes, k = _next_knot(knot, mid, out, lobes, prev, aligned)
        prev = k
        iso, prev_iso = _isotropic(knot, lobes, prev_iso)
        for key, v in _knot_params(knot, iso, prev_iso).items():
            eevee[key].append(v)
        this = _knot_params(knot, lobes, k)
        kd, ks = k[0], k[1:]
        alpha = np.square(this["roughness"])
        aniso, tilt, dtilt = np.array(this["anisotropy"]), np.array(this["tilt"]), this["diffuse_tilt"]
        fit_albedo = knot.albedos(lobes) @ k
        resid = knot.g - _fit_fcos_at(knot.wi_s, knot.wo, kd, ks, alpha, aniso, tilt, dtilt)
        rel = np.sqrt(np.sum(knot.w[:, None] * resid ** 2) / max(np.sum(knot.w[:, None] * knot.g ** 2), 1e-300))
        for key in PARAM_KEYS:
            out[key].append(this[key])
        out["theta_deg"].append(float(deg))
        out["rel_error"].append(float(rel))
        out["albedo"].append([float(v) for v in knot.albedo])
        out["fit_albedo"].append([float(v) for v in fit_albedo])
        cv_args.append((knot.theta, kd, ks, alpha, aniso, tilt, dtilt))
    out["cv"] = [list(cv) for cv in parallel(lambda a: cv_scales(tables, *a[:5], seed=seed, tilt=a[5], diffuse_tilt=a[6],
                                                                 phis=phis, turn=turn), cv_args)]
    # The node clamps Facing to the knots' range: extend to x = 1 (grazing) with the last knot.
    if out["x"][-1] < 1.0:
        for key in PARAM_KEYS[1:] + ("rel_error", "albedo", "fit_albedo", "cv"):
            out[key].append(out[key][-1])
        for key in PARAM_KEYS[1:]:
            eevee[key].append(eevee[key][-1])
        out["x"].append(1.0)
        out["theta_deg"].append(90.0)
    eevee.update({"format": out["format"], "version": FIT_VERSION, "model": "diffuse+isotropic-ggx+tilt (EEVEE)",
                  "view_aligned": 0, "anisotropic": out["anisotropic"], "x": out["x"], "theta_deg": out["theta_deg"]})
    degs = [d for d in sorted(knots_deg) if d <= L1_MAX_DEG]
    degs = sorted(degs + [0.5 * (a + b) for a, b in zip(degs, degs[1:])])
    l1, l1_eevee = fit_errors([out, eevee], tables, degs, material, seed=seed + 1, phis=phis)
    for f, errors in ((out, l1), (eevee, l1_eevee)):
        f["l1_theta_deg"] = degs
        f["l1"] = [float(v) for v in errors]
        f["l1_of"] = "file" if material is not None else "tables"
        f["error"] = float(np.median(f["l1"]))
    out["eevee"] = eevee
    return out


def fit_error(fit, tables, degs, target=None, n=1024, seed=1, phis=None):
    """Relative L1 of luminance f cos between the fit and `target` (a material; the tables when
    None) at each view angle (degrees): int |Y(f_fit) - Y(f)| cos / int Y(f) cos, importance
    sampled as the fit's knots are (the tables lead the samples to the material's lobes); over
    the view azimuths `phis` together where given (anisotropic tables: view_azimuths)."""
    return fit_errors([fit], tables, degs, target, n, seed, phis)[0]


def fit_errors(fits, tables, degs, target=None, n=1024, seed=1, phis=None):
    """fit_error of each of `fits`, on the same samples (each view angle's drawn once)."""
    def errors(deg):        # (each view angle's samples drawn from its own seed: in threads)
        knot = _Knot(tables, np.radians(deg), n=n, seed=seed, phis=phis)
        f = knot.g if target is None else knot.target_fcos(target)
        norm = max(float(knot.w @ luminance(f)), 1e-300)
        return [float(knot.w @ np.abs(luminance(knot.fcos_of(fit) - f)) / norm) for fit in fits]
    by_deg = list(parallel(errors, degs))
    return [[e[j] for e in by_deg] for j in range(len(fits))]


def _fit_fcos_at(wi, wo, kd, ks, alpha, aniso, tilt=None, diffuse_tilt=0.0):
    """f_fit cos (RGB) at wi in the xz plane: the diffuse and the lobes (tangent x), their
    normals tilted by tilt (per lobe) and diffuse_tilt (tan, toward the view; None / 0: none)."""
    tilt = np.zeros(len(alpha)) if tilt is None else np.asarray(tilt, float)
    spec = sum(np.asarray(ks[j])[None, :] * ggx_tilt_fcos(wi, wo, float(alpha[j]), float(aniso[j]), float(tilt[j]))[:, None]
               for j in range(len(alpha)))
    return np.asarray(kd)[None, :] * diffuse_tilt_fcos(wo, float(diffuse_tilt))[:, None] + spec


def _hemisphere_grid(n_theta=96, n_phi=192):
    """Midpoints of an equal-area (cos theta, phi) grid over the upper hemisphere."""
    c = (np.arange(n_theta) + 0.5) / n_theta
    phi = (np.arange(n_phi) + 0.5) / n_phi * 2 * np.pi
    c, phi = np.meshgrid(c, phi, indexing="ij")
    s = np.sqrt(1 - c * c)
    return np.stack([s * np.cos(phi), s * np.sin(phi), c], -1).reshape(-1, 3)


_HEMISPHERE = _hemisphere_grid()


def cv_scales(tables, theta, kd, ks, alpha, aniso, n=1 << 15, seed=0, betas=CV_BETAS, tilt=None, diffuse_tilt=0.0,
              phis=None, turn=0.0):
    """(beta_d, beta_s, portal share s) at this view angle (module docstring), chosen for a
    small bright light (a sun, a lamp) from a direction l uniform over the hemisphere, whose
    light the portal draws with probability CV_LIGHT_SHARE (its mixture's sun or map share):
    per sample, the closures' part (Cycles' next-event estimation: taken as exact) costs the
    pick's variance b s / (1 - s), b = E_l[(f_cv cos)^2], and the rest a / s, a = E_l[((f -
    f_cv) cos)^2] / CV_LIGHT_SHARE; at the best s = sqrt(a) / (sqrt(a) + sqrt(b)) that is
    a + 2 sqrt(a b), against E_l[(f cos)^2] / CV_LIGHT_SHARE for the portal alone (else no
    control variate: (0, 0, 1)). Betas on a grid in [0, 1], among those whose rest f - f_cv is
    nowhere negative on the tables' samples and a dense hemisphere grid: a negative rest is
    unbiased but renders negative samples, and where the portal finds a sun with them, dark
    speckles that take thousands of samples to fade (seen: paper_white under a sky, 48 px, with
    a bound of 8 albedos on the negative weight: 24 pixels below 0 at 64 spp, 9 at 1024).
    (Cycles' own pick between closures goes by their weights, which for the portal depend on
    its direction: a sun found by the portal's mixture, where its weight is small, would be
    taken rarely and then with a huge weight: hence the graph's own pick with a fixed s.)
    Anisotropic tables (a material-aligned fit: no tilts): over the view azimuths `phis`
    together (view_azimuths; each n / their count of the tables' samples and a share of the
    grid, every count-th of its points), the lobes' tangent at `turn`
    in the tables' frame (tangent_turn): one (beta_d, beta_s, s) for every azimuth of the view."""
    rng = np.random.default_rng(seed)
    views = [_view(theta)] if phis is None else [_view(theta, float(p)) for p in (phis[:1] if theta == 0.0 else phis)]
    spin = _spin(-float(turn))
    kd = np.asarray(kd, float)
    fcos, dcos, gcos, grid = [], [], [], []
    for k, wi in enumerate(views):
        # (each view a share of the samples and of the grid's columns: together the cost of one view)
        wo, p = tables.sample(wi, _stratified(n // len(views), rng))
        hemisphere = _HEMISPHERE[k::len(views)]
        wo = np.concatenate([wo[(wo[:, 2] > 0) & (p > 0)], hemisphere])
        fcos.append(tables.eval(wi, wo) * wo[:, 2:3])
        dcos.append(kd[None, :] * diffuse_tilt_fcos(wo, float(diffuse_tilt))[:, None])
        if phis is None:
            gcos.append(_fit_fcos_at(wi, wo, np.zeros(3), ks, alpha, aniso, tilt))    # the lobes together
        else:
            gcos.append(_fit_fcos_at(spin @ wi, wo @ spin.T, np.zeros(3), ks, alpha, aniso))
        grid.append(np.arange(len(wo)) >= len(wo) - len(hemisphere))       # the hemisphere grid: l uniform
    fcos, dcos, gcos, grid = (np.concatenate(x) for x in (fcos, dcos, gcos, grid))
    alone = float(np.mean(fcos[grid] ** 2)) / CV_LIGHT_SHARE
    # a and b of every (beta_d, beta_s) from the grid's moments (both quadratic in the betas)
    fg, dg, gg = fcos[grid], dcos[grid], gcos[grid]
    m = {k: float(np.mean(x * y)) for k, (x, y) in
         {"ff": (fg, fg), "fd": (fg, dg), "fg": (fg, gg), "dd": (dg, dg), "dg": (dg, gg), "gg": (gg, gg)}.items()}
    bd, bs = (x.ravel() for x in np.meshgrid(betas, betas, indexing="ij"))
    b = bd * bd * m["dd"] + 2 * bd * bs * m["dg"] + bs * bs * m["gg"]
    a = (m["ff"] - 2 * bd * m["fd"] - 2 * bs * m["fg"] + b) / CV_LIGHT_SHARE
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.clip(np.sqrt(a) / (np.sqrt(a) + np.sqrt(b)), 0.02, 0.95)
        cost = np.where(b > 0, a / share + b * share / (1.0 - share), np.inf)
    for k in np.argsort(cost, kind="stable"):
        if not cost[k] < alone:
            break
        cv = bd[k] * dcos + bs[k] * gcos
        if np.all(cv <= fcos):
            return float(bd[k]), float(bs[k]), float(share[k])
    return 0.0, 0.0, 1.0


def params_at(fit, cos_i):
    """(kd (3,), ks (L, 3), alpha (L,), anisotropy (L,)) the node uses at a view angle: each
    linear in x = 1 - cos, the roughness r lerped (alpha = r^2), as the node's graph does."""
    x = float(np.clip(1.0 - float(cos_i), 0.0, 1.0))
    xs = np.asarray(fit["x"])
    i = int(np.clip(np.searchsorted(xs, x, side="right") - 1, 0, len(xs) - 2))
    t = float(np.clip((x - xs[i]) / max(xs[i + 1] - xs[i], 1e-300), 0.0, 1.0))

    def lerp(key):
        v = np.asarray(fit[key], float)
        return (1 - t) * v[i] + t * v[i + 1]
    r = lerp("roughness")
    return lerp("diffuse"), lerp("specular"), r * r, lerp("anisotropy")


def tilts_at(fit, cos_i):
    """(tilt (L,), diffuse tilt) the node uses at a view angle (tan, lerped in x as params_at's);
    zeros for a fit without tilts (FIT_VERSION 6)."""
    n = len(fit["roughness"][0])
    if "tilt" not in fit:
        return np.zeros(n), 0.0
    x = float(np.clip(1.0 - float(cos_i), 0.0, 1.0))
    tilt = np.array([np.interp(x, fit["x"], np.asarray(fit["tilt"], float)[:, j]) for j in range(n)])
    return tilt, float(np.interp(x, fit["x"], fit["diffuse_tilt"]))


def eval_fit(fit, wi, wo):
    """f of the fit (RGB, no cosine) for one wi (3,) and wo (N, 3): what the node renders (the
    view-aligned lobes' tangent along wi's azimuth; a material-aligned fit's along x, the
    tables' tangent)."""
    wo = np.atleast_2d(np.asarray(wo, float))
    wi = np.asarray(wi, float)
    kd, ks, alpha, aniso = params_at(fit, wi[2])
    tilt, dtilt = tilts_at(fit, wi[2])
    if fit.get("material_aligned", 0):      # the lobes' tangent at tangent_turn in the tables' frame
        phi = float(fit.get("tangent_turn", 0.0))
    else:
        phi = np.arctan2(wi[1], wi[0]) if np.hypot(wi[0], wi[1]) > 0 else 0.0
    c, s = np.cos(phi), np.sin(phi)
    turn = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])     # wi's azimuth to 0
    wi_v, wo_v = turn @ wi, wo @ turn.T
    with np.errstate(divide="ignore", invalid="ignore"):
        f = _fit_fcos_at(wi_v, wo_v, kd, ks, alpha, aniso, tilt, dtilt) / wo_v[:, 2:3]
    return np.where((wo_v[:, 2] > 0)[:, None] & (wi_v[2] > 0), f, 0.0)


def principled_params(fit):
    """One view-independent Principled BSDF for a fit (a baseline, not a fit of its own):
    roughness (the lobes' by their weight) and specular colour from normal incidence, base
    colour the diffuse there; metallic when the diffuse part is under 5 % of the albedo."""
    kd = np.asarray(fit["diffuse"][0])
    ks_lobes = np.asarray(fit["specular"][0])
    ks = ks_lobes.sum(0)
    lum = np.array([luminance(k) for k in ks_lobes])
    rough = float(np.average(fit["roughness"][0], weights=lum)) if lum.sum() > 0 else 0.5
    if luminance(kd) < 0.05 * luminance(kd + ks * 0.9):
        return {"Base Color": [float(v) for v in np.clip(ks, 0, 1)], "Metallic": 1.0, "Roughness": rough,
                "IOR": 1.5, "Specular IOR Level": 0.5}
    f0 = float(np.clip(luminance(ks), 0.0, 0.9))
    ior = float((1 + np.sqrt(f0)) / max(1 - np.sqrt(f0), 1e-3)) if f0 > 0 else 1.0
    return {"Base Color": [float(v) for v in np.clip(kd, 0, 1)], "Metallic": 0.0, "Roughness": rough,
            "IOR": float(np.clip(ior, 1.0, 3.0)), "Specular IOR Level": 0.5}


def match_ratios(tables, fit, n=MATCH_N):
    """f / f_fit (RGB, in [0, MATCH_MAX]; 0 where the fit is 0) on a grid (n, n, n, 3): view
    cos theta_v = i / (n - 1), light cos theta_l = j / (n - 1) and |phi_l| = pi k / (n - 1)
    about the view's azimuth (cosines evaluated at >= 0.02: a row on the horizon holds its
    neighbourhood's ratios). What the SVM back end scales the fit's closures by so that
    f_cv = f toward a small light (blender_addon/render/svm/: any scale is unbiased; this one is
    the light's part of the rest ~0), read back by trilinear interpolation."""
    c = np.maximum(np.linspace(0.0, 1.0, n), 0.02)
    cl, phi = np.meshgrid(c, np.linspace(0.0, np.pi, n), indexing="ij")
    sl = np.sqrt(1.0 - cl * cl)
    wo = np.stack([sl * np.cos(phi), sl * np.sin(phi), cl], -1).reshape(-1, 3)

    def view(cv):           # (each view alone: in threads)
        wi = np.array([np.sqrt(1.0 - cv * cv), 0.0, cv])
        f, ff = tables.eval(wi, wo), eval_fit(fit, wi, wo)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.clip(np.where(ff > 0, f / ff, 0.0), 0.0, MATCH_MAX).reshape(n, n, 3)
    return np.stack(list(parallel(view, c)))


def match_image(ratios):
    """The (n, n * n, 4) float32 image of match_ratios: row j (from the top) holds cos theta_l
    j / (n - 1), column i n + k the view i and |phi| k (svm._cv_matched reads it)."""
    n = ratios.shape[0]
    img = np.ones((n, n * n, 4), np.float32)
    img[..., :3] = ratios.transpose(1, 0, 2, 3).reshape(n, n * n, 3)
    return img


def match_path(tables_path):
    tables_path = Path(tables_path)
    return tables_path.with_name(tables_path.stem + ".match.exr")


# ------------------------------------------------------------------------------ files

def fit_path(tables_path):
    tables_path = Path(tables_path)
    return tables_path.with_name(tables_path.stem + ".fit.json")


def load_fit(path):
    path = Path(path)
    try:
        fit = json.loads(path.read_text())
    except FileNotFoundError:
        raise FlowBSDFError("closure fit not found", path) from None
    except (OSError, ValueError) as e:
        raise FlowBSDFError(f"closure fit unreadable ({e})", path) from None
    if fit.get("format") != "flowbsdf-closure-fit" or fit.get("version") not in READABLE_VERSIONS:
        raise FlowBSDFError("not a current FlowBSDF closure fit; re-bake", path)
    if fit.get("match") and path.with_name(fit["match"]).is_file():
        fit["match_path"] = str(path.with_name(fit["match"]))      # (as blender_addon/node.load_fit)
    return fit


# The exporter contract (bake/export/derived.py): the fit file of a table file.
KIND = "fit"


def path(tables_path, digest):
    """<stem>.fit.json beside the tables (its name does not change with their contents)."""
    return fit_path(tables_path)


def read(path):
    """The fit (load_fit)."""
    return load_fit(path)


def is_current(path, digest):
    """Made from tables of this hash by this version of the fit."""
    try:
        old = load_fit(path)
    except FlowBSDFError:
        return False
    return old.get("tables_hash") == digest and fit_current(old.get("version"), old.get("anisotropic", False))


def write(path, tables_path, tables, digest, material=None):
    """Fit the tables (their error measured against `material`, the measured file they were baked
    from, else against the tables), write the match image beside the fit (isotropic tables) and
    the fit; returns the fit's error for the log line."""
    tables_path = Path(tables_path)
    fit = fit_closures(tables, material=material)
    fit["tables_hash"] = digest
    fit["tables"] = tables_path.name
    if not tables.anisotropic:      # (the fit is made at phi_i 0: no matching for anisotropic tables)
        match = match_path(tables_path)
        write_rgba_exr(match, match_image(match_ratios(tables, fit)), MATCH_KEY,
                       {"n": MATCH_N, "tables_hash": digest})
        fit["match"] = match.name
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(fit, indent=1))
    return (f"(relative L1 of f cos against the {fit['l1_of']}: median "
            f"{fit['error']:.3f}, max {max(fit['l1']):.3f})")
