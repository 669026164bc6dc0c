"""Cycles closures fitted to baked tables: the Learned BSDF node's fit back end.

Per view angle (knots in x = 1 - cos theta_i, what Cycles' Layer Weight "Facing" gives),
the baked BSDF f (Tables.eval) is approximated by what Cycles renders everywhere
(isotropic closures: for anisotropic tables the fit is made at phi_i = 0, wi in the xz
plane, like every knot here; not an average over phi_i):

    f_fit = kd / pi  +  ks * f_ggx(alpha)

kd, ks RGB, f_ggx Cycles' Glossy BSDF with the GGX distribution and colour 1 (Smith
height-correlated G2, no Fresnel; Cycles' roughness input r gives alpha = r^2). Between
knots the node interpolates kd, ks and r linearly in x.

At each knot the fit keeps the baked albedo exactly per channel (kd + ks A(alpha) =
albedo(theta_i), A the GGX lobe's albedo) and, over a grid of alpha, minimizes the L2
error of f cos over the hemisphere (Monte Carlo with a mixture of the tables', the
cosine and the GGX lobe's samplers, fixed seed). Recorded per knot: the relative L2
error of f cos (`rel_error`) and the albedo the closures really reach (`fit_albedo`,
equal to `albedo` unless ks or kd hit a bound).

Per knot also the control variate (`cv`: beta_d, beta_s in [0, 1] and a portal share s,
`cv_scales`): the SVM back end renders f_cv = beta_d kd / pi + beta_s ks f_ggx as Cycles
closures (which Cycles lights with its own lamp and world sampling, MIS included) with
probability 1 - s, weight 1 / (1 - s), else the rest, f - f_cv, through its Ray Portal with
weight (f - f_cv) cos / (q s) at the portal's direction: unbiased for any beta and s. The
betas keep the rest nowhere negative and minimise the noise for a small bright light from any
direction.

`principled_params(fit)` maps a fit to one view-independent Principled BSDF (the
baseline the acceptance script compares against).
"""
import functools
import json
from pathlib import Path

import numpy as np

from ..core.geometry import luminance
from ..core.tables import MixedTables, open_tables
from ..errors import FlowBSDFError
from ..materials.analytic import ggx_ndf, ggx_lambda, ggx_reflection_pdf, ggx_sample_reflection
from ..plumbing.exrio import write_rgba_exr
from ..plumbing.files import atomic_path, file_hash

FIT_VERSION = 4
MATCH_N = 16        # the match image's nodes per axis (match_ratios)
MATCH_MAX = 2.0     # its ratios' bound (blender_addon/svm.py matches only where the fit is within 10 %)
MATCH_KEY = "flowbsdf_match"
CV_BETAS = np.linspace(0.0, 1.0, 11)
CV_LIGHT_SHARE = 0.5    # the portal mixture's probability of drawing a bright light (cv_scales)
KNOTS_DEG = (0.0, 15.0, 30.0, 40.0, 50.0, 58.0, 65.0, 70.0, 74.0, 78.0, 81.0, 84.0, 86.0, 88.0, 89.5)
ALPHAS = np.geomspace(0.002, 1.0, 24)


def ggx_fcos(wi, wo, alpha):
    """Cycles' Glossy BSDF (GGX, colour 1) times cos theta_o; wi (3,), wo (N, 3)."""
    wi = np.broadcast_to(np.asarray(wi, float), wo.shape)
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        g2 = 1.0 / (1.0 + ggx_lambda(wi, alpha, alpha) + ggx_lambda(wo, alpha, alpha))
        v = ggx_ndf(h, alpha, alpha) * g2 / (4.0 * wi[:, 2])
    return np.where(ok, v, 0.0)


def _stratified(n, rng):
    side = int(np.sqrt(n))
    g = (np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
         + rng.random((side * side, 2))) / side
    return g


def _cosine(u):
    r = np.sqrt(u[:, 0])
    phi = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - r * r))], axis=1)


def baked_albedo(tables, cos_i):
    """Exact albedo (RGB) of the baked BSDF for a view at cos theta_i: E[W] = sum m W over the
    interpolated table (what a furnace render of the OSL back end converges to)."""
    theta = float(np.arccos(np.clip(cos_i, -1.0, 1.0)))
    wi = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
    if isinstance(tables, MixedTables):        # the part theta_i falls in
        tables = tables.parts[tables.part_at(theta)]
    bins, _ = tables._bins(wi)
    m = tables._lerp(tables._m, bins)[0]
    w = tables._lerp(tables._w.astype(np.float64), bins)[0]
    return np.einsum("rc,rck->k", m, w)


@functools.lru_cache(maxsize=4096)
def _ggx_albedo_at(theta, alpha, seed):
    """ggx_albedo at wi = (sin theta, 0, cos theta): the same for every material's knots (one
    alpha grid), so a bake of several materials computes it once."""
    return ggx_albedo(np.array([np.sin(theta), 0.0, np.cos(theta)]), alpha, seed=seed)


def ggx_albedo(wi, alpha, n=1024, seed=0):
    rng = np.random.default_rng(seed)
    u = _stratified(n, rng)
    wo = ggx_sample_reflection(wi, alpha, alpha, u)
    p = ggx_reflection_pdf(wi, wo, alpha, alpha)
    v = np.where(p > 0, ggx_fcos(wi, wo, alpha) / np.where(p > 0, p, 1.0), 0.0)
    return float(np.mean(v))


def fit_knot(tables, theta, n=2048, seed=0, alphas=ALPHAS):
    """The best (kd, ks, alpha, rel_error, fit albedo, baked albedo) at one view angle."""
    rng = np.random.default_rng(seed)
    wi = np.array([np.sin(theta), 0.0, np.cos(theta)])
    albedo = baked_albedo(tables, np.cos(theta))
    fixed = np.concatenate([tables.sample(wi, _stratified(n, rng))[0], _cosine(_stratified(n, rng))])
    fixed = fixed[fixed[:, 2] > 0]
    fixed_pdf = tables.pdf(wi, fixed) + fixed[:, 2] / np.pi
    fixed_g = tables.eval(wi, fixed) * fixed[:, 2:3]
    best = None
    for alpha in alphas:
        wo_g = ggx_sample_reflection(wi, alpha, alpha, _stratified(n, rng))
        wo_g = wo_g[wo_g[:, 2] > 0]
        wo = np.concatenate([fixed, wo_g])
        q = (np.concatenate([fixed_pdf, tables.pdf(wi, wo_g) + wo_g[:, 2] / np.pi])
             + ggx_reflection_pdf(wi, wo, alpha, alpha)) / 3.0
        w = 1.0 / (q * 3 * n)                  # MC weights of integrals over the hemisphere
        g = np.concatenate([fixed_g, tables.eval(wi, wo_g) * wo_g[:, 2:3]])     # (N, 3) baked f cos
        ed = wo[:, 2] / np.pi
        es = ggx_fcos(wi, wo, alpha)
        a_ggx = _ggx_albedo_at(float(theta), float(alpha), seed)
        z = es - a_ggx * ed
        r0 = g - albedo[None, :] * ed[:, None]
        zz = np.sum(w * z * z)
        rz = np.sum(w[:, None] * r0 * z[:, None], axis=0)
        ks = np.clip(rz / max(zz, 1e-300), 0.0, albedo / max(a_ggx, 1e-12))
        kd = np.maximum(albedo - ks * a_ggx, 0.0)
        resid = g - kd[None, :] * ed[:, None] - ks[None, :] * es[:, None]
        err = float(np.sum(w[:, None] * resid ** 2))
        norm = float(np.sum(w[:, None] * g ** 2))
        if best is None or err < best[0]:
            best = (err, kd, ks, alpha, np.sqrt(err / max(norm, 1e-300)), kd + ks * a_ggx)
    _, kd, ks, alpha, rel, fit_albedo = best
    return kd, ks, float(alpha), float(rel), fit_albedo, albedo


def fit_closures(tables, knots_deg=KNOTS_DEG, n=2048, seed=0):
    """The fit as a JSON-able dict: per knot x = 1 - cos theta_i, kd, ks (RGB), Cycles roughness
    r = sqrt(alpha), the relative L2 error of f cos and the albedos."""
    out = {"format": "flowbsdf-closure-fit", "version": FIT_VERSION, "model": "diffuse+ggx",
           "x": [], "theta_deg": [], "diffuse": [], "specular": [], "roughness": [], "alpha": [],
           "rel_error": [], "albedo": [], "fit_albedo": [], "cv": []}
    # Knots ascending in x = 1 - cos theta (Facing), i.e. ascending theta.
    for deg in sorted(knots_deg):
        theta = np.radians(deg)
        kd, ks, alpha, rel, fit_albedo, albedo = fit_knot(tables, theta, n=n, seed=seed)
        out["x"].append(float(1.0 - np.cos(theta)))
        out["theta_deg"].append(float(deg))
        out["diffuse"].append([float(v) for v in kd])
        out["specular"].append([float(v) for v in ks])
        out["alpha"].append(alpha)
        out["roughness"].append(float(np.sqrt(alpha)))
        out["rel_error"].append(rel)
        out["albedo"].append([float(v) for v in albedo])
        out["fit_albedo"].append([float(v) for v in fit_albedo])
        # (anisotropic tables: no control variate; the fit is made at phi_i = 0 only, its rest
        # at other phi_i unchecked)
        out["cv"].append([0.0, 0.0, 1.0] if tables.anisotropic else list(cv_scales(tables, theta, kd, ks, alpha,
                                                                                  seed=seed)))
    # The node clamps Facing to the knots' range: extend to x = 1 (grazing) with the last knot.
    if out["x"][-1] < 1.0:
        for key in ("diffuse", "specular", "roughness", "alpha", "rel_error", "albedo", "fit_albedo", "cv"):
            out[key].append(out[key][-1])
        out["x"].append(1.0)
        out["theta_deg"].append(90.0)
    return out


def _hemisphere_grid(n_theta=96, n_phi=192):
    """Midpoints of an equal-area (cos theta, phi) grid over the upper hemisphere."""
    c = (np.arange(n_theta) + 0.5) / n_theta
    phi = (np.arange(n_phi) + 0.5) / n_phi * 2 * np.pi
    c, phi = np.meshgrid(c, phi, indexing="ij")
    s = np.sqrt(1 - c * c)
    return np.stack([s * np.cos(phi), s * np.sin(phi), c], -1).reshape(-1, 3)


_HEMISPHERE = _hemisphere_grid()


def cv_scales(tables, theta, kd, ks, alpha, n=1 << 15, seed=0, betas=CV_BETAS):
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
    taken rarely and then with a huge weight: hence the graph's own pick with a fixed s.)"""
    wi = np.array([np.sin(theta), 0.0, np.cos(theta)])
    rng = np.random.default_rng(seed)
    wo, p = tables.sample(wi, _stratified(n, rng))
    wo = np.concatenate([wo[(wo[:, 2] > 0) & (p > 0)], _HEMISPHERE])
    c = wo[:, 2:3]
    fcos = tables.eval(wi, wo) * c
    kd, ks = np.asarray(kd, float), np.asarray(ks, float)
    dcos = kd[None, :] * (c / np.pi)
    gcos = ks[None, :] * ggx_fcos(wi, wo, alpha)[:, None]
    grid = slice(len(wo) - len(_HEMISPHERE), None)      # the hemisphere grid: l uniform
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
    """(kd, ks, alpha) the node uses at a view angle (linear in x = 1 - cos, roughness lerped)."""
    x = np.clip(1.0 - np.asarray(cos_i, float), 0.0, 1.0)
    xs = np.asarray(fit["x"])
    kd = np.stack([np.interp(x, xs, np.asarray(fit["diffuse"])[:, c]) for c in range(3)], -1)
    ks = np.stack([np.interp(x, xs, np.asarray(fit["specular"])[:, c]) for c in range(3)], -1)
    r = np.interp(x, xs, fit["roughness"])
    return kd, ks, r * r


def eval_fit(fit, wi, wo):
    """f of the fit (RGB, no cosine) for one wi (3,) and wo (N, 3): what the node renders."""
    wo = np.atleast_2d(wo)
    kd, ks, alpha = params_at(fit, wi[2])
    with np.errstate(divide="ignore", invalid="ignore"):
        spec = np.where(wo[:, 2] > 0, ggx_fcos(wi, wo, float(alpha)) / wo[:, 2], 0.0)
    return np.where((wo[:, 2] > 0)[:, None], kd / np.pi + ks * spec[:, None], 0.0)


def principled_params(fit):
    """One view-independent Principled BSDF for a fit (a baseline, not a fit of its own):
    roughness and specular colour from normal incidence, base colour the diffuse there;
    metallic when the diffuse part is under 5 % of the albedo."""
    kd = np.asarray(fit["diffuse"][0])
    ks = np.asarray(fit["specular"][0])
    rough = float(fit["roughness"][0])
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
    f_cv = f toward a small light (blender_addon/svm.py: any scale is unbiased; this one is
    the light's part of the rest ~0), read back by trilinear interpolation."""
    c = np.maximum(np.linspace(0.0, 1.0, n), 0.02)
    cl, phi = np.meshgrid(c, np.linspace(0.0, np.pi, n), indexing="ij")
    sl = np.sqrt(1.0 - cl * cl)
    wo = np.stack([sl * np.cos(phi), sl * np.sin(phi), cl], -1).reshape(-1, 3)
    out = np.zeros((n, n, n, 3))
    for i, cv in enumerate(c):
        wi = np.array([np.sqrt(1.0 - cv * cv), 0.0, cv])
        f, ff = tables.eval(wi, wo), eval_fit(fit, wi, wo)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[i] = np.clip(np.where(ff > 0, f / ff, 0.0), 0.0, MATCH_MAX).reshape(n, n, 3)
    return out


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
    if fit.get("format") != "flowbsdf-closure-fit" or fit.get("version") != FIT_VERSION:
        raise FlowBSDFError("not a current FlowBSDF closure fit; re-bake", path)
    if fit.get("match") and path.with_name(fit["match"]).is_file():
        fit["match_path"] = str(path.with_name(fit["match"]))      # (as blender_addon/node.load_fit)
    return fit


def ensure_fit(tables_path, log=None):
    """The fit file of a table file (<stem>.fit.json beside it), rebuilt when missing or made
    from other table contents; written atomically. Returns its path."""
    tables_path = Path(tables_path)
    digest = file_hash(tables_path)
    path = fit_path(tables_path)
    try:
        if load_fit(path).get("tables_hash") == digest:
            return path
    except FlowBSDFError:
        pass
    tables = open_tables(tables_path)
    fit = fit_closures(tables)
    fit["tables_hash"] = digest
    fit["tables"] = tables_path.name
    if not tables.anisotropic:      # (the fit is made at phi_i 0: no matching for anisotropic tables)
        match = match_path(tables_path)
        write_rgba_exr(match, match_image(match_ratios(tables, fit)), MATCH_KEY,
                       {"n": MATCH_N, "tables_hash": digest})
        fit["match"] = match.name
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(fit, indent=1))
    if log:
        log(f"[fit] wrote {path} (max relative error {max(fit['rel_error']):.3f})")
    return path
