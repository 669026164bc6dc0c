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
node interpolates kd, ks_j, r_j and a_j linearly in x.

At each knot the fit keeps the baked albedo exactly per channel (kd + sum_j ks_j A_j =
albedo(theta_i), A_j the lobe's albedo) and minimizes the L1 error of f cos over the
hemisphere (weights per channel: an exact non-negative least-squares solve, reweighted for L1;
Monte Carlo over a mixture of the tables', the cosine's and a GGX mixture's samplers, fixed
seed; the lobes' albedos at the knots from ggx_albedo.npz). The lobes' (alpha, a) are searched
on a grid: all of it at normal view, then knot by knot from the previous knot's lobes, moving a
lobe costing in proportion to its share of the albedo, the weights pulled toward the previous
knot's, and the next knot's lobes chosen by the error at the knot plus half-way back
(_next_knot): each lobe keeps its identity and its parameters vary smoothly with the view
angle (a fit made per knot alone jumps between knots, and a sphere renders concentric rings). Recorded per knot: the relative L2 error of f cos
against the tables (`rel_error`, which the SVM back end's matching reads) and the albedo the
closures reach (`fit_albedo`, equal to `albedo`); per view angle (knots and midpoints up to
88 deg) the relative L1 error of luminance f cos against the measured material when the bake
has it, else the tables (`l1`, `l1_of`), and its median (`error`: the node's status).

Anisotropic tables: the fit is made at phi_i = 0 (wi in the xz plane, the tables' tangent
along x) and its lobes are isotropic (a = 0): what it fits is the tables' cut at phi_i = 0.

Per knot also the control variate (`cv`: beta_d, beta_s in [0, 1] and a portal share s,
`cv_scales`): the SVM back end renders f_cv = beta_d kd / pi + beta_s sum_j ks_j f_ggx_j as
Cycles closures (which Cycles lights with its own lamp and world sampling, MIS included) with
probability 1 - s, weight 1 / (1 - s), else the rest, f - f_cv, through its Ray Portal with
weight (f - f_cv) cos / (q s) at the portal's direction: unbiased for any beta and s. The
betas keep the rest nowhere negative and minimise the noise for a small bright light from any
direction.

`principled_params(fit)` maps a fit to one view-independent Principled BSDF (the
baseline the acceptance script compares against).
"""
import json
import itertools
from pathlib import Path

import numpy as np

from ..core.geometry import LUMINANCE, luminance
from ..core.tables import MixedTables, open_tables
from ..errors import FlowBSDFError
from ..materials.analytic import ggx_ndf, ggx_lambda, ggx_reflection_pdf, ggx_sample_reflection
from ..plumbing.exrio import write_rgba_exr
from ..plumbing.files import atomic_path, file_hash

FIT_VERSION = 6
MODEL = "diffuse+view-aligned-ggx"
MATCH_N = 16        # the match image's nodes per axis (match_ratios)
MATCH_MAX = 2.0     # its ratios' bound (blender_addon/svm.py matches only where the fit is within 10 %)
MATCH_KEY = "flowbsdf_match"
CV_BETAS = np.linspace(0.0, 1.0, 11)
CV_LIGHT_SHARE = 0.5    # the portal mixture's probability of drawing a bright light (cv_scales)
KNOTS_DEG = (0.0, 15.0, 30.0, 40.0, 50.0, 58.0, 65.0, 70.0, 74.0, 78.0, 81.0, 84.0, 86.0, 88.0, 89.5)
LOBES = 3           # GGX lobes; the first VIEW_ALIGNED with the view's tangent and anisotropy
VIEW_ALIGNED = 2
ALPHAS = np.geomspace(0.002, 1.0, 37)                 # alpha = r^2, Cycles' roughness r <= 1
ANISOTROPY = np.round(np.linspace(-0.4, 0.8, 13), 6)  # Cycles' Anisotropy input; 0 at index 4
PULL = 0.02         # the weights' pull toward the previous knot's (_Knot.solve), relative to the Gram
STEP_COST = 0.004   # added to the relative L1 per grid step a lobe of all the albedo moves (_descend)
STIFF = 5.0         # _next_knot's stiffer descent: STIFF x STEP_COST
L1_MAX_DEG = 88.0   # the error's view angles: knots and their midpoints up to here


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


def _stratified(n, rng):
    side = int(np.sqrt(n))
    g = (np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
         + rng.random((side * side, 2))) / side
    return g


def _cosine(u):
    r = np.sqrt(u[:, 0])
    phi = 2 * np.pi * u[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - r * r))], axis=1)


def _view(theta):
    return np.array([np.sin(theta), 0.0, np.cos(theta)])


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


def _ggx_albedos(theta, alphas, anisos, n=1024, seed=0, cache=True):
    """ggx_albedo at wi = (sin theta, 0, cos theta) of lobes (alphas[i], anisos[i]): from the
    table at the knots, else computed together (n samples each) and kept."""
    if cache and not _ALBEDOS:
        _albedo_table()
    keys = [(float(theta), float(a), float(b)) for a, b in zip(alphas, anisos)]
    missing = sorted(set(k for k in keys if k not in _ALBEDOS)) if cache else keys
    out = {}
    for start in range(0, len(missing), 64):        # (bounded memory)
        part = missing[start:start + 64]
        _, al, an = np.array(part).T
        wi = _view(theta)
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


def ggx_albedo(wi, alpha, aniso=0.0, n=1024, seed=0):
    """The albedo of Cycles' Glossy GGX (colour 1, tangent x) at wi: its own VNDF sampling."""
    theta = float(np.arctan2(np.hypot(wi[0], wi[1]), wi[2]))
    return float(_ggx_albedos(theta, [alpha], [aniso], n=n, seed=seed)[0])


class _Knot:
    """One view angle's Monte Carlo quadrature of the hemisphere: directions drawn from the
    tables, the cosine and a mixture of GGX lobes over ALPHAS (so that a lobe of any width has
    samples), their weights 1 / (n q) for the mixture's density q, and the baked f cos there."""

    def __init__(self, tables, theta, n=1024, seed=0):
        rng = np.random.default_rng(seed)
        self.theta, self.wi = float(theta), _view(theta)
        wi = self.wi
        wt = tables.sample(wi, _stratified(n, rng))[0]
        wc = _cosine(_stratified(n, rng))
        u = _stratified(n, rng)
        pick = ALPHAS[rng.integers(len(ALPHAS), size=len(u))]
        wg = ggx_sample_reflection(wi, pick, pick, u)
        draws = len(wt) + len(wc) + len(wg)
        wo = np.concatenate([wt, wc, wg])
        wo = wo[wo[:, 2] > 0]
        q = (tables.pdf(wi, wo) + wo[:, 2] / np.pi
             + np.mean([ggx_reflection_pdf(wi, wo, a, a) for a in ALPHAS], axis=0)) / 3.0
        self.wo, self.w = wo, 1.0 / (q * draws)
        self.g = tables.eval(wi, wo) * wo[:, 2:3]
        self.albedo = baked_albedo(tables, np.cos(theta))
        self._row = {(-1, -1): 0}                   # grid point -> row of _vals; row 0 the diffuse
        self._vals = (wo[:, 2] / np.pi)[None]       # (rows, N) f cos of the diffuse and each lobe
        self._albs = np.ones(1)
        # their weighted inner products (what least squares needs), grown with the rows
        self._gram = (self._vals * self.w) @ self._vals.T
        self._rhs = (self._vals * self.w) @ self.g

    def rows(self, keys):
        """The rows of lobes (ia, ja) (ALPHAS[ia], ANISOTROPY[ja]) in the knot's arrays of f cos
        values and albedos, the missing ones computed together."""
        missing = sorted({k for k in keys if k not in self._row})
        if missing:
            ia, ja = np.array(missing).T
            new = ggx_fcos(self.wi, self.wo, ALPHAS[ia][:, None], ANISOTROPY[ja][:, None])
            cross = (new * self.w) @ self._vals.T
            self._gram = np.block([[self._gram, cross.T], [cross, (new * self.w) @ new.T]])
            self._rhs = np.concatenate([self._rhs, (new * self.w) @ self.g])
            self._vals = np.concatenate([self._vals, new])
            self._albs = np.concatenate([self._albs, _ggx_albedos(self.theta, ALPHAS[ia], ANISOTROPY[ja])])
            base = len(self._row)
            self._row.update((k, base + i) for i, k in enumerate(missing))
        return np.array([self._row[k] for k in keys], int)

    def albedos(self, keys):
        rows = self.rows(keys)
        return self._albs[rows]

    def solve(self, candidates, prev=None, irls=1):
        """Best weights of each candidate set of lobes [[(ia, ja), ...], ...] (diffuse first):
        (weights (C, K, 3), relative L1 of luminance f cos (C,)). `prev` (K, 3): the previous
        knot's weights, which a small Tikhonov term pulls toward where the error is flat (a rough
        lobe and the diffuse trade places at little cost: left free they swap between knots)."""
        idx = self.rows([(-1, -1)] + [p for cand in candidates for p in cand])[1:].reshape(len(candidates), -1)
        idx = np.concatenate([np.zeros((len(idx), 1), int), idx], 1)                # (C, K)
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
    for m in range(1, kk + 1):
        for idx in itertools.combinations(range(kk), m):
            idx = list(idx)
            sys = np.zeros((c, h, m + 1, m + 1))
            sys[..., :m, :m] = gram[..., idx, :][..., idx] + ridge * np.eye(m)
            sys[..., :m, m] = a[:, None, idx]
            sys[..., m, :m] = a[:, None, idx]
            b = np.concatenate([rhs[..., idx], np.broadcast_to(albedo, (c, h))[..., None]], -1)
            sol = np.linalg.solve(sys, b[..., None])[..., :m, 0]
            k = np.zeros((c, h, kk))
            k[..., idx] = np.maximum(sol, 0.0)
            obj = 0.5 * np.einsum("chk,chkl,chl->ch", k, gram, k) - np.einsum("chk,chk->ch", rhs, k)
            ok = np.all(sol >= -1e-9 * np.abs(albedo)[None, :, None], -1) & (obj < best)
            best = np.where(ok, obj, best)
            out = np.where(ok[..., None], k, out)
    # The equality exactly (the clamp above moved a feasible solution by < 1e-9 at most).
    fit_alb = np.einsum("ck,chk->ch", a, out)
    return out * np.where(fit_alb > 0, albedo / np.where(fit_alb > 0, fit_alb, 1.0), 0.0)[..., None]


def _neighbours(p, lobe, aniso, coarse=None):
    """The grid points a lobe at p may move to at the next knot: any alpha (every third where
    `coarse` is None, else within two steps of `coarse`); the anisotropy within two steps (one
    of `coarse`) for the first `aniso` lobes (the view-aligned ones; 0: none moves it)."""
    ia, ja = p if coarse is None else coarse
    if coarse is None:
        alphas, reach = range(0, len(ALPHAS), 3), 2
    else:
        alphas, reach = range(max(ia - 2, 0), min(ia + 2, len(ALPHAS) - 1) + 1), 1
    jas = (range(max(ja - reach, 0), min(ja + reach, len(ANISOTROPY) - 1) + 1)
           if lobe < aniso else [ja])
    return [(i, j) for i in alphas for j in jas]


def _descend(knot, lobes, aniso, prev=None, sweeps=2, step_cost=STEP_COST):
    """Coordinate descent over the lobes' grid points from the previous knot's: the relative
    L1 plus, per lobe, STEP_COST times its share of the previous knot's albedo times the grid
    steps it moved (a lobe that carries little may jump; one that carries much moves smoothly)."""
    start = list(lobes)
    share = np.zeros(LOBES)
    if prev is not None:
        albs = knot.albedos(start)
        lum = luminance(np.asarray(prev))
        share = lum[1:] * albs / max(float(lum[0] + lum[1:] @ albs), 1e-300)

    def cost(sets, l1):
        steps = np.array([[abs(p[0] - s[0]) + abs(p[1] - s[1]) for p, s in zip(c, start)] for c in sets])
        return l1 + step_cost * (steps @ share)
    lobes = list(lobes)
    best = cost([lobes], knot.solve([lobes], prev)[1])[0]
    for _ in range(sweeps):
        moved = False
        for j in range(LOBES):
            coarse = None
            for _ in range(2):          # every third alpha, then around the best of those
                sets = [lobes[:j] + [p] + lobes[j + 1:] for p in _neighbours(lobes[j], j, aniso, coarse)]
                c = cost(sets, knot.solve(sets, prev)[1])
                i = int(np.argmin(c))
                coarse = sets[i][j]
                if c[i] < best * (1 - 1e-4):
                    best, lobes, moved = float(c[i]), sets[i], True
        if not moved:
            break
    return lobes


def _first_knot(knot, view_aligned):
    """Normal view: isotropic lobes chosen greedily over the whole alpha grid, then refined by
    coordinate descent over it, the view-aligned ones' anisotropy too."""
    zero = int(np.argmin(np.abs(ANISOTROPY)))
    lobes = []
    for _ in range(LOBES):
        sets = [lobes + [(i, zero)] for i in range(len(ALPHAS))]
        lobes = sets[int(np.argmin(knot.solve(sets)[1]))]
    return _descend(knot, lobes, aniso=view_aligned)


def _next_knot(tables, knot, fit, lobes, prev, view_aligned, n, seed):
    """(lobes, weights) at the next knot: of the descent from the previous knot's lobes, the
    same made stiffer (STIFF times the cost of moving), and the previous lobes kept (weights
    alone refitted), the one whose error at this knot plus half-way from the previous knot
    (the node lerps the parameters between them) is least."""
    mid = _Knot(tables, 0.5 * (knot.theta + np.radians(fit["theta_deg"][-1])), n=n // 2, seed=seed + 7)
    options = [_descend(knot, lobes, view_aligned, prev),
               _descend(knot, lobes, view_aligned, prev, step_cost=STIFF * STEP_COST),
               list(lobes)]
    best = None
    for option in options:
        k, l1 = knot.solve([option], prev, irls=4)
        k = k[0]
        pair = {key: fit[key][-1:] for key in ("x", "diffuse", "specular", "roughness", "anisotropy")}
        pair["x"] = pair["x"] + [float(1.0 - np.cos(knot.theta))]
        pair["diffuse"] = pair["diffuse"] + [k[0]]
        pair["specular"] = pair["specular"] + [k[1:]]
        pair["roughness"] = pair["roughness"] + [[np.sqrt(ALPHAS[i]) for i, _ in option]]
        pair["anisotropy"] = pair["anisotropy"] + [[ANISOTROPY[j] for _, j in option]]
        ff = eval_fit(pair, mid.wi, mid.wo) * mid.wo[:, 2:3]
        l1_mid = float(mid.w @ np.abs(luminance(ff - mid.g)) / max(float(mid.w @ luminance(mid.g)), 1e-300))
        if best is None or l1[0] + l1_mid < best[0]:
            best = (l1[0] + l1_mid, option, k)
    return best[1], best[2]


def fit_closures(tables, knots_deg=KNOTS_DEG, n=1024, seed=0, material=None, view_aligned=VIEW_ALIGNED):
    """The fit as a JSON-able dict (module docstring): per knot x = 1 - cos theta_i, kd (RGB),
    per lobe ks (RGB), Cycles roughness r = sqrt(alpha) and anisotropy, the relative L2 error
    of f cos, the albedos and the control variate; per view angle the L1 error against
    `material` (the measured file) when given, else the tables."""
    view_aligned = 0 if tables.anisotropic else view_aligned
    out = {"format": "flowbsdf-closure-fit", "version": FIT_VERSION, "model": MODEL,
           "view_aligned": view_aligned, "anisotropic": bool(tables.anisotropic),
           "x": [], "theta_deg": [], "diffuse": [], "specular": [], "roughness": [], "anisotropy": [],
           "rel_error": [], "albedo": [], "fit_albedo": [], "cv": []}
    lobes = prev = None
    # Knots ascending in x = 1 - cos theta (Facing), i.e. ascending theta.
    for deg in sorted(knots_deg):
        knot = _Knot(tables, np.radians(deg), n=n, seed=seed)
        if lobes is None:
            lobes = _first_knot(knot, view_aligned)
            k = knot.solve([lobes], None, irls=4)[0][0]
        else:
            lobes, k = _next_knot(tables, knot, out, lobes, prev, view_aligned, n, seed)
        prev = k
        kd, ks = k[0], k[1:]
        alpha = np.array([ALPHAS[i] for i, _ in lobes])
        aniso = np.array([ANISOTROPY[j] for _, j in lobes])
        fit_albedo = kd + knot.albedos(lobes) @ ks
        resid = knot.g - _fit_fcos_at(knot.wi, knot.wo, kd, ks, alpha, aniso)
        rel = np.sqrt(np.sum(knot.w[:, None] * resid ** 2) / max(np.sum(knot.w[:, None] * knot.g ** 2), 1e-300))
        out["x"].append(float(1.0 - np.cos(np.radians(deg))))
        out["theta_deg"].append(float(deg))
        out["diffuse"].append([float(v) for v in kd])
        out["specular"].append([[float(v) for v in row] for row in ks])
        out["roughness"].append([float(np.sqrt(a)) for a in alpha])
        out["anisotropy"].append([float(a) for a in aniso])
        out["rel_error"].append(float(rel))
        out["albedo"].append([float(v) for v in knot.albedo])
        out["fit_albedo"].append([float(v) for v in fit_albedo])
        # (anisotropic tables: no control variate; the fit is made at phi_i = 0 only, its rest
        # at other phi_i unchecked)
        out["cv"].append([0.0, 0.0, 1.0] if tables.anisotropic else
                         list(cv_scales(tables, knot.theta, kd, ks, alpha, aniso, seed=seed)))
    # The node clamps Facing to the knots' range: extend to x = 1 (grazing) with the last knot.
    if out["x"][-1] < 1.0:
        for key in ("diffuse", "specular", "roughness", "anisotropy", "rel_error", "albedo", "fit_albedo", "cv"):
            out[key].append(out[key][-1])
        out["x"].append(1.0)
        out["theta_deg"].append(90.0)
    degs = [d for d in sorted(knots_deg) if d <= L1_MAX_DEG]
    degs = sorted(degs + [0.5 * (a + b) for a, b in zip(degs, degs[1:])])
    out["l1_theta_deg"] = degs
    out["l1"] = [float(v) for v in fit_error(out, tables, degs, material, seed=seed + 1)]
    out["l1_of"] = "file" if material is not None else "tables"
    out["error"] = float(np.median(out["l1"]))
    return out


def fit_error(fit, tables, degs, target=None, n=1024, seed=1):
    """Relative L1 of luminance f cos between the fit and `target` (a material; the tables when
    None) at each view angle (degrees): int |Y(f_fit) - Y(f)| cos / int Y(f) cos, importance
    sampled as the fit's knots are (the tables lead the samples to the material's lobes)."""
    out = []
    for deg in degs:
        knot = _Knot(tables, np.radians(deg), n=n, seed=seed)
        f = knot.g if target is None else target.eval(knot.wi, knot.wo) * knot.wo[:, 2:3]
        ff = eval_fit(fit, knot.wi, knot.wo) * knot.wo[:, 2:3]
        out.append(float(knot.w @ np.abs(luminance(ff - f)) / max(float(knot.w @ luminance(f)), 1e-300)))
    return out


def _fit_fcos_at(wi, wo, kd, ks, alpha, aniso):
    """f_fit cos (RGB) at wi in the xz plane: the diffuse and the lobes (tangent x)."""
    spec = sum(np.asarray(ks[j])[None, :] * ggx_fcos(wi, wo, float(alpha[j]), float(aniso[j]))[:, None]
               for j in range(len(alpha)))
    return np.asarray(kd)[None, :] * (np.maximum(wo[:, 2:3], 0.0) / np.pi) + spec


def _hemisphere_grid(n_theta=96, n_phi=192):
    """Midpoints of an equal-area (cos theta, phi) grid over the upper hemisphere."""
    c = (np.arange(n_theta) + 0.5) / n_theta
    phi = (np.arange(n_phi) + 0.5) / n_phi * 2 * np.pi
    c, phi = np.meshgrid(c, phi, indexing="ij")
    s = np.sqrt(1 - c * c)
    return np.stack([s * np.cos(phi), s * np.sin(phi), c], -1).reshape(-1, 3)


_HEMISPHERE = _hemisphere_grid()


def cv_scales(tables, theta, kd, ks, alpha, aniso, n=1 << 15, seed=0, betas=CV_BETAS):
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
    kd = np.asarray(kd, float)
    dcos = kd[None, :] * (c / np.pi)
    gcos = _fit_fcos_at(wi, wo, np.zeros(3), ks, alpha, aniso)     # the lobes together
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


def eval_fit(fit, wi, wo):
    """f of the fit (RGB, no cosine) for one wi (3,) and wo (N, 3): what the node renders (the
    view-aligned lobes' tangent along wi's azimuth)."""
    wo = np.atleast_2d(np.asarray(wo, float))
    wi = np.asarray(wi, float)
    kd, ks, alpha, aniso = params_at(fit, wi[2])
    phi = np.arctan2(wi[1], wi[0]) if np.hypot(wi[0], wi[1]) > 0 else 0.0
    c, s = np.cos(phi), np.sin(phi)
    turn = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])     # wi's azimuth to 0
    wi_v, wo_v = turn @ wi, wo @ turn.T
    with np.errstate(divide="ignore", invalid="ignore"):
        f = _fit_fcos_at(wi_v, wo_v, kd, ks, alpha, aniso) / wo_v[:, 2:3]
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


def ensure_fit(tables_path, material=None, log=None):
    """The fit file of a table file (<stem>.fit.json beside it), rebuilt when missing, of an
    older version or made from other table contents; written atomically. Returns its path.
    `material` (the measured file the tables were baked from): the fit's error is measured
    against it (else against the tables)."""
    tables_path = Path(tables_path)
    digest = file_hash(tables_path)
    path = fit_path(tables_path)
    try:
        if load_fit(path).get("tables_hash") == digest:
            return path
    except FlowBSDFError:
        pass
    tables = open_tables(tables_path)
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
    if log:
        log(f"[fit] wrote {path} (relative L1 of f cos against the {fit['l1_of']}: median "
            f"{fit['error']:.3f}, max {max(fit['l1']):.3f})")
    return path
