"""Tables of a measured RGL file blended along the file's own coordinates: each of the two
incident bins' tables carried to wi at fixed s, then mixed (numpy; issue 22, item 4).

Tables (tables.py) blend their two nearest bins at fixed cell coordinates. Where f·cos has a
feature that moves with theta_i faster than the bins follow, the blend half-way holds two
half-features where the target has one: chm_mint's bins 0.53 deg apart lose 2.5x the ideal
tabulation's rv at 84.9 deg, and the mixture of the two bins' exact targets over the half vector
2.06x (scripts/blend_probe.py): no placement of cells helps. An RGL file blends its measured
slices at fixed s (rgl.WarpedCoords: where eval reads its `rgb` table), so its features stay put
over s; carried there, the bins' tables meet them:

    sample:  bin j of the two with its weight (the first uniform split by the weights), wo_j
             from bin j's own table at wi_j = (theta_j, phi_i), s = W_j(wo_j), wo = W_wi^-1(s),
    pdf:     sum_j w_j p_j(W_j^-1(W_wi(wo))) J_j / J_wi,

W the file's coordinates at that incident direction with s_x over its horizon value
(WarpedCoords horizon=True: a direction above the horizon at wi_j stays above it at wi), of the
warp data as a back end stores it (stored=True: float16, RGLMaterial.stored_warp), J their
d omega / d s, p_j bin j's table at its own angle, the weights the tables' own (linear in
cos theta_i). At a bin this is the bin's table itself. Measured on chm_mint's 2 MB tables (rv
over the ideal's, 512² draws): 85 deg 2.05x -> 0.88x, 30 deg 0.83x -> 0.37x, 60 deg 1.16x -> 0.95x.

Near grazing the file's warp degenerates (its 90 deg slice holds no half vectors facing away from
wi) and carrying can lose to the fixed-cell blend (2 MB tables: colodur_napoli_4f at 89.7 deg 2.6x
-> 21x), so each interval between bins carries or not (`carried`, one flag per interval of
theta_bins; tables.meta["carried"]): `choose_intervals` measures both blends at each interval's
cos-midpoint and keeps the better.

The sampler is exact (sample and pdf agree, nothing lost where W_wi reaches every s), but not
invertible: the mixture's choice takes part of the first uniform.
"""
import numpy as np

from ..errors import FlowBSDFError
from ..materials.base import as_dirs
from ..materials.rgl import RGLMaterial, WarpedCoords
from .geometry import spherical_dir, theta_phi
from .tables import MixedTables


def check_carriable(material):
    """FlowBSDFError unless the material has coordinates of its own to carry tables along."""
    if not isinstance(material, RGLMaterial) or not material.isotropic:
        raise FlowBSDFError("carried tables need an isotropic RGL material (its own coordinates)")


class CarriedTables:
    name = "tables-carried"
    normalized = True

    def __init__(self, tables, material, carried=None):
        """carried: per interval of tables.theta_bins, whether it carries (default:
        tables.meta["carried"], else every interval)."""
        check_carriable(material)
        if getattr(tables, "anisotropic", False):
            raise FlowBSDFError("carried tables blend isotropic tables")
        self.tables, self.material = tables, material
        self._warps = {}
        if carried is None:
            carried = tables.meta.get("carried", [True] * (len(tables.theta_bins) - 1))
        self.carried = np.asarray(carried, bool)
        if self.carried.shape != (max(len(tables.theta_bins) - 1, 0),):
            raise FlowBSDFError(f"carried: one flag per interval of the tables' {len(tables.theta_bins)} bins, "
                                f"not {self.carried.shape}")

    @property
    def nbytes(self):
        """The tables' bytes and the file's stored warp data, which carrying needs at render time."""
        return self.tables.nbytes + self.material.warp_nbytes

    def _warp(self, theta, phi):
        key = (float(theta), float(phi))
        if key not in self._warps:
            if len(self._warps) > 64:
                self._warps.clear()
            self._warps[key] = WarpedCoords(self.material, spherical_dir(theta, phi), horizon=True, stored=True)
        return self._warps[key]

    def _bins(self, theta):
        """(the part of the tables that serves theta, [(theta_j, weight)] of its two bins, whether
        their interval carries)."""
        part, start = self.tables, 0
        if isinstance(part, MixedTables):
            p = int(part.part_at(theta))
            start = sum(len(q.theta_bins) for q in part.parts[:p])
            part = part.parts[p]
        bins = part.theta_bins
        if len(bins) == 1:
            return part, [(bins[0], 1.0)], True
        k = int(np.clip(np.searchsorted(bins, theta, side="right") - 1, 0, len(bins) - 2))
        c = np.cos(bins)
        t = float(np.clip((c[k] - np.cos(theta)) / (c[k] - c[k + 1]), 0.0, 1.0))
        return part, [(bins[k], 1.0 - t), (bins[k + 1], t)], bool(self.carried[start + k])

    def _carry_back(self, theta, phi, wo, value, shape=()):
        """sum_j w_j value(part, wi_j, wo_j) J_j / J_wi, wo_j = W_j^-1(W_wi(wo)): a density of the
        bins (pdf, or f cos: shape (3,)) carried to wi; on an interval that does not carry, value at
        wi itself."""
        part, bins, carries = self._bins(theta)
        if not carries:
            return value(part, spherical_dir(theta, phi), wo)
        s, jac = self._warp(theta, phi).to_s(wo)
        out = np.zeros((len(wo),) + shape)
        for theta_j, w in bins:
            if w <= 0.0:
                continue
            wo_j, jac_j = self._warp(theta_j, phi).from_s(s)
            ok = (jac_j > 0) & np.isfinite(jac)
            if ok.any():
                ratio = (jac_j[ok] / jac[ok]).reshape((-1,) + (1,) * len(shape))
                out[ok] += w * value(part, spherical_dir(theta_j, phi), wo_j[ok]) * ratio
        return out

    def _pdf_one(self, theta, phi, wo):
        pdf = self._carry_back(theta, phi, wo, lambda part, wi, w: part.pdf(wi, w))
        return np.where(wo[:, 2] > 0, pdf, 0.0)

    def _eval_one(self, theta, phi, wo):
        """The baked f carried as f cos: sum_j w_j f_j(wo_j) cos_j J_j / J_wi / cos theta_o."""
        fcos = self._carry_back(theta, phi, wo, lambda part, wi, w: part.eval(wi, w) * w[:, 2:3], (3,))
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(wo[:, 2:3] > 0, fcos / wo[:, 2:3], 0.0)

    def _sample_one(self, theta, phi, u):
        part, bins, carries = self._bins(theta)
        if not carries:
            return part.sample(spherical_dir(theta, phi), u)
        u = u.copy()
        first = np.ones(len(u), bool)
        if len(bins) == 2 and 0.0 < bins[0][1] < 1.0:
            w0 = bins[0][1]
            first = u[:, 0] < w0
            u[:, 0] = np.where(first, u[:, 0] / w0, (u[:, 0] - w0) / (1.0 - w0))
            u[:, 0] = np.clip(u[:, 0], 0.0, np.nextafter(1.0, 0.0))
        elif len(bins) == 2 and bins[0][1] == 0.0:
            first[:] = False
        wo = np.empty((len(u), 3))
        for j, chosen in ((0, first), (1, ~first)):
            if not chosen.any():
                continue
            theta_j = bins[j][0]
            wo_j, _ = part.sample(spherical_dir(theta_j, phi), u[chosen])
            s, _ = self._warp(theta_j, phi).to_s(wo_j)
            wo[chosen], _ = self._warp(theta, phi).from_s(s)
        # The pdf from wo as pdf() computes it (not from s and the bins' densities already at hand):
        # the round trip s -> wo -> s is exact only to ~1e-9, and MIS needs pdf(wo) itself.
        return wo, self._pdf_one(theta, phi, wo)

    def _per_wi(self, fn, wi, x):
        """fn(theta, phi, x of the samples at that wi) for each distinct wi."""
        x = np.atleast_2d(np.asarray(x, np.float64))
        if np.ndim(wi) == 1:
            theta, phi = theta_phi(np.asarray(wi, np.float64)[None])
            return fn(float(theta[0]), float(phi[0]), x)
        wi, _ = as_dirs(wi, np.empty((len(x), 3)))
        theta, phi = theta_phi(wi)
        keys, inverse = np.unique(np.stack([theta, phi], axis=1), axis=0, return_inverse=True)
        inverse = np.ravel(inverse)
        outs = None
        for g, (t, p) in enumerate(keys):
            sel = inverse == g
            got = fn(t, p, x[sel])
            got = got if isinstance(got, tuple) else (got,)
            if outs is None:
                outs = [np.empty((len(x),) + r.shape[1:]) for r in got]
            for o, r in zip(outs, got):
                o[sel] = r
        return tuple(outs) if len(outs) > 1 else outs[0]

    def sample(self, wi, u):
        return self._per_wi(self._sample_one, wi, u)

    def pdf(self, wi, wo):
        return self._per_wi(self._pdf_one, wi, wo)

    def eval(self, wi, wo):
        """The tables' baked f (RGB) carried like the pdf: what a renderer that samples these
        tables weighs its samples by (eval cos / pdf), as Tables.eval is for the fixed-cell blend."""
        return self._per_wi(self._eval_one, wi, wo)


def choose_intervals(material, tables, ideal, side=128, seed=0):
    """Per interval of tables.theta_bins: True where carrying reaches a lower rv than the fixed-cell
    blend at its cos-midpoint (metrics.ReferencePoints: side² of the ideal's draws there). Intervals
    of no width (a layout group's boundary, never blended) carry."""
    from ..quality.metrics import ReferencePoints
    from .tabulate import _parallel
    bins = np.asarray(tables.theta_bins)
    carried = CarriedTables(tables, material, carried=[True] * (len(bins) - 1))

    def better(k):
        if bins[k + 1] <= bins[k]:
            return True
        mid = float(np.arccos(0.5 * (np.cos(bins[k]) + np.cos(bins[k + 1]))))
        draws = ReferencePoints(material, spherical_dir(mid, 0.0), ideal, side, seed)
        return draws.rv(carried)[0] <= draws.rv(tables)[0]
    return [bool(b) for b in _parallel(better, range(len(bins) - 1))]
