"""Sampling domains: 2D coordinates x for outgoing directions, with exact maps and Jacobians.

`jacobian(x)` is d(omega)/dx, solid angle per unit domain area, so a density over the
domain converts as p_x(x) = p_omega(wo) * jacobian(x).
"""
import numpy as np

from ..errors import FlowBSDFError


class Disk:
    """Projected hemisphere: x = (wo.x, wo.y) inside the unit disk; d(omega) = dx / cos(theta)."""

    name = "disk"
    periodic = (False, False)

    def to_dir(self, x):
        x = np.asarray(x, float)
        z = np.sqrt(np.maximum(0.0, 1.0 - np.sum(x * x, axis=-1)))
        return np.concatenate([x, z[..., None]], axis=-1)

    def from_dir(self, wo):
        return np.asarray(wo, float)[..., :2].copy()

    def jacobian(self, x):
        r2 = np.sum(np.asarray(x, float) ** 2, axis=-1)
        with np.errstate(divide="ignore"):
            return np.where(r2 < 1.0, 1.0 / np.sqrt(np.maximum(1.0 - r2, 0.0)), np.inf)

    def contains(self, x):
        return np.sum(np.asarray(x, float) ** 2, axis=-1) < 1.0


class Spherical:
    """x = (theta, phi), theta in [0, pi/2], phi in [-pi, pi) and periodic; d(omega) = sin(theta) dx."""

    name = "spherical"
    periodic = (False, True)

    def to_dir(self, x):
        x = np.asarray(x, float)
        s = np.sin(x[..., 0])
        return np.stack([s * np.cos(x[..., 1]), s * np.sin(x[..., 1]), np.cos(x[..., 0])], axis=-1)

    def from_dir(self, wo):
        wo = np.asarray(wo, float)
        theta = np.arctan2(np.hypot(wo[..., 0], wo[..., 1]), wo[..., 2])
        return np.stack([theta, np.arctan2(wo[..., 1], wo[..., 0])], axis=-1)

    def jacobian(self, x):
        return np.sin(np.asarray(x, float)[..., 0])

    def contains(self, x):
        t = np.asarray(x, float)[..., 0]
        return (t >= 0.0) & (t < 0.5 * np.pi)

    @staticmethod
    def wrap_phi(phi):
        """The representative of phi in [-pi, pi)."""
        return np.mod(np.asarray(phi, float) + np.pi, 2.0 * np.pi) - np.pi


# A "slope" flow (bake.core.flow_maps.SlopeMap) takes its training data as disk coordinates of wo: its
# half-vector map depends on wi, so it lives in the flow.
DOMAINS = {"disk": Disk, "spherical": Spherical, "slope": Disk}


def get_domain(name):
    try:
        return DOMAINS[name]()
    except KeyError:
        raise FlowBSDFError(f"unknown domain {name!r}; expected one of {sorted(DOMAINS)}") from None
