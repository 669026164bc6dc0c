"""Synthetic conditional targets with exact closed-form samplers (numpy only).

They stand in for a material when developing and testing the trainer: the training loop
only sees `draw(n, rng) -> (wi (n,3), x1 (n,2) domain coordinates)`; `density(wi, wo)`
(unnormalized, per steradian) lets tests measure the relative variance of a sampler.
"""
import numpy as np

from bake.core.domains import get_domain


class GGXReflection:
    """wo = reflect(wi, m), m ~ D(m) cos(theta_m) of an isotropic GGX lobe, kept if wo.z > 0.

    The lobe follows the mirror direction of wi (position depends on theta_i) and its
    roughness grows with theta_i: alpha(theta_i) = alpha * (1 + alpha_slope * sin(theta_i)).
    With phi_i = 0 the lobe sits at phi_o = pi, straddling phi = ±pi in the spherical domain.
    Density of the kept samples: D(h) cos(theta_h) / (4 wi.h) / A(wi) with A the acceptance
    rate (`density` returns it without the 1/A, enough for the relative variance).
    """

    isotropic = True

    def __init__(self, domain="disk", alpha=0.2, alpha_slope=0.0, theta_max_deg=80.0, theta_grid=None):
        self.domain = get_domain(domain) if isinstance(domain, str) else domain
        self.alpha, self.alpha_slope = float(alpha), float(alpha_slope)
        self.theta_max = np.radians(theta_max_deg)
        self.theta_grid = None if theta_grid is None else np.asarray(theta_grid, float)

    def describe(self):
        return {"kind": "synthetic-ggx", "alpha": self.alpha, "alpha_slope": self.alpha_slope,
                "theta_max": float(self.theta_max),
                "theta_grid": None if self.theta_grid is None else self.theta_grid.tolist()}

    def alpha_of(self, wi):
        return self.alpha * (1.0 + self.alpha_slope * np.hypot(wi[..., 0], wi[..., 1]))

    def sample_wo(self, wi, rng):
        wi = np.asarray(wi, float)
        wo = np.empty_like(wi)
        todo = np.arange(len(wi))
        while todo.size:
            a = self.alpha_of(wi[todo])
            u = rng.random((todo.size, 2))
            tan2 = a * a * u[:, 0] / (1.0 - u[:, 0])
            ct = 1.0 / np.sqrt(1.0 + tan2)
            st = np.sqrt(np.maximum(0.0, 1.0 - ct * ct))
            ph = 2.0 * np.pi * u[:, 1]
            m = np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=-1)
            w = 2.0 * np.sum(wi[todo] * m, axis=-1, keepdims=True) * m - wi[todo]
            ok = w[:, 2] > 0.0
            wo[todo[ok]] = w[ok]
            todo = todo[~ok]
        return wo

    def draw_wi(self, n, rng):
        if self.theta_grid is not None:
            t = self.theta_grid[rng.integers(0, len(self.theta_grid), n)]
        else:
            t = rng.uniform(0.0, self.theta_max, n)
        return np.stack([np.sin(t), np.zeros(n), np.cos(t)], axis=-1)

    def draw(self, n, rng):
        wi = self.draw_wi(n, rng)
        wo = self.sample_wo(wi, rng)
        return wi, self.domain.from_dir(wo)

    def density(self, wi, wo):
        wi, wo = np.broadcast_arrays(np.asarray(wi, float), np.asarray(wo, float))
        h = wi + wo
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        a = self.alpha_of(wi)
        ct = h[..., 2]
        d = 1.0 / (np.pi * a * a * ct ** 4 * (1.0 + (1.0 - ct * ct) / (ct * ct * a * a)) ** 2)
        ih = np.sum(wi * h, axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            p = d * ct / (4.0 * ih)
        return np.where((wo[..., 2] > 0) & (ih > 0) & (ct > 0), p, 0.0)


class Lambertian:
    """Cosine-weighted directions (the identity flow's target)."""

    isotropic = True

    def __init__(self, domain="disk", theta_max_deg=80.0):
        self.domain = get_domain(domain) if isinstance(domain, str) else domain
        self.theta_max = np.radians(theta_max_deg)

    def describe(self):
        return {"kind": "synthetic-lambert"}

    def draw(self, n, rng):
        t = rng.uniform(0.0, self.theta_max, n)
        wi = np.stack([np.sin(t), np.zeros(n), np.cos(t)], axis=-1)
        u = rng.random((n, 2))
        r, ph = np.sqrt(u[:, 0]), 2.0 * np.pi * u[:, 1]
        wo = np.stack([r * np.cos(ph), r * np.sin(ph), np.sqrt(np.maximum(0.0, 1.0 - r * r))], axis=-1)
        return wi, self.domain.from_dir(wo)

    def density(self, wi, wo):
        return np.maximum(np.asarray(wo)[..., 2], 0.0) / np.pi
