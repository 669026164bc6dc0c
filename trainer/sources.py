"""Training-data sources for real materials: exact samples of max(lum f, 0)·cos from bake.core.ideal.

A source has to provide `draw(n, rng) -> (wi (n,3), x1 (n,2) domain coordinates)`, and may
provide `density(wi, wo)`, the normalized target (the trainer scores the defensive share with it).
`MaterialSource` draws wi from a fixed grid of incident directions (the ideal sampler
builds one table per distinct wi, so a grid keeps that finite) and pre-draws a pool of
exact samples once; `draw` then picks random pool entries (fast, deterministic given rng).
"""
import hashlib

import numpy as np

from bake.core.domains import get_domain
from bake.errors import FlowBSDFError


# domain = "auto": the slope domain when at some incident elevation at least SLOPE_SHARE of
# f·cos has its half vector within SPECULAR_CONE_DEG of the normal (a spike, usually over a
# glow, which the disk domain learns poorly), else disk (a Lambertian is its identity flow).
SPECULAR_CONE_DEG = 5.0
SLOPE_SHARE = 0.1


def specular_share(sampler, thetas_deg=(0.0, 30.0, 60.0), n=1 << 15, seed=0):
    """Largest share over thetas_deg of f·cos whose half vector is within SPECULAR_CONE_DEG of
    the normal, from exact samples of `sampler` (the ideal tabulation)."""
    rng = np.random.default_rng([seed, 31337])
    cos_cone = np.cos(np.radians(SPECULAR_CONE_DEG))
    share = 0.0
    for t in np.radians(thetas_deg):
        wi = np.array([np.sin(t), 0.0, np.cos(t)])
        wo, pdf = sampler.sample(wi, rng.random((n, 2)))
        ok = (pdf > 0) & (wo[:, 2] > 0)
        if not ok.any():
            continue
        h = wo[ok] + wi
        share = max(share, float(np.mean(h[:, 2] / np.linalg.norm(h, axis=1) > cos_cone)))
    return share


def choose_domain(sampler):
    """(domain, share) for manifest domain "auto"."""
    share = specular_share(sampler)
    return ("slope" if share >= SLOPE_SHARE else "disk"), share


def default_theta_grid(n=45, max_deg=89.0):
    """Cell centres of n equal bins of theta_i over [0, max_deg] degrees, in radians."""
    return np.radians((np.arange(n) + 0.5) / n * max_deg)


class MaterialSource:
    def __init__(self, material, domain="disk", theta_i=None, phi_i_count=16, resolution=256,
                 supersample=2, pool=1 << 21, seed=0, sampler=None, progress=None):
        from bake.core.ideal import IdealSampler   # numpy only; imported lazily

        self.material = material
        self.domain = get_domain(domain) if isinstance(domain, str) else domain
        self.theta_i = default_theta_grid() if theta_i is None else np.asarray(theta_i, float)
        if self.theta_i.ndim != 1 or len(self.theta_i) == 0 or np.any(self.theta_i < 0) \
                or np.any(self.theta_i >= np.pi / 2):
            raise FlowBSDFError("theta_i grid must be a non-empty list of elevations in [0, 90) degrees")
        if material.isotropic:
            phis = np.zeros(1)
        else:
            phis = (np.arange(phi_i_count) + 0.5) / phi_i_count * 2 * np.pi - np.pi
        t, p = np.meshgrid(self.theta_i, phis, indexing="ij")
        t, p = t.ravel(), p.ravel()
        self.wi_grid = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
        self.sampler = sampler or IdealSampler(material, resolution=resolution, supersample=supersample,
                                               max_tables=max(512, len(self.wi_grid) + 1))
        self.pool_size, self.seed = int(pool), seed
        self.progress = progress
        self._pool = None

    def describe(self):
        fp = getattr(self.material, "fingerprint", lambda: "")()
        grid = hashlib.sha256(self.wi_grid.tobytes()).hexdigest()[:12]
        return {"kind": "ideal", "material": fp, "grid": grid, "n_wi": len(self.wi_grid),
                "resolution": self.sampler.resolution, "pool": self.pool_size}

    def _build_pool(self):
        rng = np.random.default_rng([self.seed, 271828])
        n = self.pool_size
        wi_out, wo_out, have = [], [], 0
        # Equal share per wi (stratified), refilled where samples were lost below the horizon.
        per = int(np.ceil(n / len(self.wi_grid)))
        idx = np.repeat(np.arange(len(self.wi_grid)), per)
        for _ in range(50):
            wi = self.wi_grid[idx]
            wo, pdf = self.sampler.sample(wi, rng.random((len(idx), 2)))
            ok = (pdf > 0) & (wo[:, 2] > 0)
            wi_out.append(wi[ok])
            wo_out.append(wo[ok])
            have += int(ok.sum())
            idx = idx[~ok]
            if idx.size == 0:
                break
        wi = np.concatenate(wi_out)
        wo = np.concatenate(wo_out)
        if len(wi) == 0:
            raise FlowBSDFError(f"material {getattr(self.material, 'name', '?')} reflects nothing "
                                "(max(lum f, 0)·cos is zero): nothing to train")
        self._pool = (wi, self.domain.from_dir(wo))

    def density(self, wi, wo):
        """The normalized target density (per steradian) the samples follow: the ideal tabulation's."""
        return self.sampler.pdf(wi, wo)

    def pool(self):
        """All the pairs draw() picks from: (wi (n, 3), x (n, 2) in the domain's coordinates)."""
        if self._pool is None:
            self._build_pool()
        return self._pool

    def draw(self, n, rng):
        wi, x = self.pool()
        k = rng.integers(0, len(wi), n)
        return wi[k], x[k]
