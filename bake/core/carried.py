"""Tables of a measured RGL file blended along the file's own coordinates: each of the two
incident bins' tables carried to wi at fixed s, then mixed (issue 22, item 4). The numpy
reference (the warp in C: rgl.WarpedCoords); Cycles' OSL back end: blender_addon/render/osl/carried.h.

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
-> 21x), so each interval between bins carries or not (`carry`, one flag per interval of
theta_bins; tables.meta["carried"]): `choose_intervals` measures both blends at each interval's
cos-midpoint and keeps the better.

`flowbsdf bake` flags the intervals of a measured file's tables (plan_tables' settings.carry) and
`as_rendered` gives the sampler OSL renders. The sampler is exact (sample and pdf agree, nothing
lost where W_wi reaches every s), but not invertible: the mixture's choice takes part of the first
uniform.
"""
import numpy as np

from ..errors import FlowBSDFError
from ..materials.rgl import RGLMaterial, WarpedCoords
from ..maths.geometry import spherical_dir, theta_phi
from .mixed_tables import MixedTables


def check_carriable(material):
    """FlowBSDFError unless the material has coordinates of its own to carry tables along."""
    if not isinstance(material, RGLMaterial) or not material.isotropic:
        raise FlowBSDFError("carried tables need an isotropic RGL material (its own coordinates)")


def as_rendered(tables, material):
    """The tables as Cycles' OSL back end renders them: carried (CarriedTables) where their meta says
    which intervals carry (`flowbsdf bake` of a measured file), else the tables themselves."""
    return tables if tables.meta.get("carried") is None else CarriedTables(tables, material)


class CarriedTables:
    name = "tables-carried"
    normalized = True

    def __init__(self, tables, material, carry=None):
        """carry: per interval of tables.theta_bins, whether it carries (default: the table file's
        flags, tables.meta["carried"], else every interval)."""
        check_carriable(material)
        if getattr(tables, "anisotropic", False):
            raise FlowBSDFError("carried tables blend isotropic tables")
        self.tables, self.material = tables, material
        self.warp = WarpedCoords(material, horizon=True, stored=True)
        if carry is None:
            carry = tables.meta.get("carried", [True] * (len(tables.theta_bins) - 1))
        self.carry = np.asarray(carry, bool)
        if self.carry.shape != (max(len(tables.theta_bins) - 1, 0),):
            raise FlowBSDFError(f"carried: one flag per interval of the tables' {len(tables.theta_bins)} bins, "
                                f"not {self.carry.shape}")

    @property
    def nbytes(self):
        """The tables' bytes and the file's stored warp data, which carrying needs at render time."""
        return self.tables.nbytes + self.material.warp_nbytes

    def _parts(self, wi, n):
        """(part, index of its first bin among tables.theta_bins, the samples it serves) for the
        parts of MixedTables (the tables themselves otherwise); wi as (n, 3)."""
        wi = np.broadcast_to(np.asarray(wi, np.float64), (n, 3))
        if not isinstance(self.tables, MixedTables):
            return [(self.tables, 0, np.arange(n))], wi
        which = self.tables.part_at(theta_phi(wi)[0])
        starts = np.cumsum([0] + [len(q.theta_bins) for q in self.tables.parts])
        return [(q, starts[p], np.flatnonzero(which == p)) for p, q in enumerate(self.tables.parts)], wi

    def _interval(self, part, start, wi):
        """Per sample: its two bins' angles (n, 2), their weights (n, 2) and whether it carries."""
        theta, phi = theta_phi(wi)
        bins = np.asarray(part.theta_bins)
        if len(bins) == 1:
            return np.repeat(bins[:1], 2)[None].repeat(len(wi), 0), np.tile([1.0, 0.0], (len(wi), 1)), \
                np.ones(len(wi), bool), phi
        k = np.clip(np.searchsorted(bins, theta, side="right") - 1, 0, len(bins) - 2)
        c = np.cos(bins)
        t = np.clip((c[k] - np.cos(theta)) / (c[k] - c[k + 1]), 0.0, 1.0)
        return np.stack([bins[k], bins[k + 1]], 1), np.stack([1.0 - t, t], 1), self.carry[start + k], phi

    def _carry_back(self, wi, wo, value, shape=()):
        """sum_j w_j value(part, wi_j, wo_j) J_j / J_wi, wo_j = W_j^-1(W_wi(wo)): a density of the
        bins (pdf, or f cos: shape (3,)) carried to wi; where the interval does not carry, value at
        wi itself."""
        wo = np.atleast_2d(np.asarray(wo, np.float64))
        out = np.zeros((len(wo),) + shape)
        parts, wi = self._parts(wi, len(wo))
        for part, start, idx in parts:
            thetas, weights, carries, phi = self._interval(part, start, wi[idx])
            plain, car = idx[~carries], idx[carries]
            if len(plain):
                out[plain] = value(part, wi[plain], wo[plain])
            if not len(car):
                continue
            s, jac = self.warp.to_s(wi[car], wo[car])
            for j in (0, 1):
                w = weights[carries, j]
                sel = np.flatnonzero(w > 0)
                wi_j = spherical_dir(thetas[carries, j][sel], phi[carries][sel])
                wo_j, jac_j = self.warp.from_s(wi_j, s[sel])
                ok = (jac_j > 0) & np.isfinite(jac[sel])
                if ok.any():
                    ratio = (w[sel][ok] * jac_j[ok] / jac[sel][ok]).reshape((-1,) + (1,) * len(shape))
                    out[car[sel[ok]]] += value(part, wi_j[ok], wo_j[ok]) * ratio
        return out

    def pdf(self, wi, wo):
        wo = np.atleast_2d(np.asarray(wo, np.float64))
        pdf = self._carry_back(wi, wo, lambda part, wi_j, wo_j: part.pdf(wi_j, wo_j))
        return np.where(wo[:, 2] > 0, pdf, 0.0)

    def eval(self, wi, wo):
        """The tables' baked f (RGB) carried like the pdf, as f cos (sum_j w_j f_j(wo_j) cos_j J_j /
        J_wi / cos theta_o): what a renderer that samples these tables weighs its samples by (eval
        cos / pdf), as Tables.eval is for the fixed-cell blend."""
        wo = np.atleast_2d(np.asarray(wo, np.float64))
        fcos = self._carry_back(wi, wo, lambda part, wi_j, wo_j: part.eval(wi_j, wo_j) * wo_j[:, 2:3], (3,))
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(wo[:, 2:3] > 0, fcos / wo[:, 2:3], 0.0)

    def sample(self, wi, u):
        u = np.atleast_2d(np.asarray(u, np.float64))
        wo, pdf = np.empty((len(u), 3)), np.empty(len(u))
        carried = np.zeros(len(u), bool)
        parts, wi = self._parts(wi, len(u))
        for part, start, idx in parts:
            thetas, weights, carries, phi = self._interval(part, start, wi[idx])
            plain, car = idx[~carries], idx[carries]
            carried[car] = True
            if len(plain):
                wo[plain], pdf[plain] = part.sample(wi[plain], u[plain])
            if not len(car):
                continue
            # bin j of the two by the first uniform, split by the weights (and rescaled)
            w0, v = weights[carries, 0], u[car].copy()
            first = v[:, 0] < w0
            with np.errstate(divide="ignore", invalid="ignore"):
                v[:, 0] = np.where(first, v[:, 0] / w0, (v[:, 0] - w0) / (1.0 - w0))
            v[:, 0] = np.clip(v[:, 0], 0.0, np.nextafter(1.0, 0.0))
            wi_j = spherical_dir(np.where(first, thetas[carries, 0], thetas[carries, 1]), phi[carries])
            wo_j, _ = part.sample(wi_j, v)
            s, _ = self.warp.to_s(wi_j, wo_j)
            wo[car], _ = self.warp.from_s(wi[car], s)
        # The pdf from wo as pdf() computes it (not from s and the bins' densities already at hand):
        # the round trip s -> wo -> s is exact only to ~1e-9, and MIS needs pdf(wo) itself.
        if carried.any():
            pdf[carried] = self.pdf(wi[carried], wo[carried])
        return wo, pdf


def choose_intervals(material, tables, ideal, side=128, seed=0):
    """Per interval of tables.theta_bins: True where carrying reaches a lower rv than the fixed-cell
    blend at its cos-midpoint (metrics.ReferencePoints: side² of the ideal's draws there). Intervals
    of no width (a layout group's boundary, never blended) carry."""
    from ..io.threads import parallel
    from .metrics import ReferencePoints
    bins = np.asarray(tables.theta_bins)
    carried = CarriedTables(tables, material, carry=[True] * (len(bins) - 1))

    def better(k):
        if bins[k + 1] <= bins[k]:
            return True
        mid = float(np.arccos(0.5 * (np.cos(bins[k]) + np.cos(bins[k + 1]))))
        draws = ReferencePoints(material, spherical_dir(mid, 0.0), ideal, side, seed)
        return draws.rv(carried)[0] <= draws.rv(tables)[0]
    return [bool(b) for b in parallel(better, range(len(bins) - 1))]
