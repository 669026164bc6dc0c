"""What every material is (`Material`: eval, target, fingerprint) and `as_dirs`, the
broadcasting of direction arguments every material and sampler shares."""
import hashlib

import numpy as np

from ..maths.geometry import luminance


def as_dirs(wi, wo):
    """Broadcast wi (3,) or (N,3) against wo (N,3); both float64 (N,3)."""
    wo = np.atleast_2d(np.asarray(wo, dtype=np.float64))
    wi = np.broadcast_to(np.asarray(wi, dtype=np.float64), wo.shape)
    return wi, wo


class Material:
    """A BSDF. `eval(wi, wo)` returns f (RGB, (N,3), no cosine), zero unless both are above the surface.

    Measured data may hold negative values; eval returns them as the data says. Samplers
    target the non-negative density max(lum(f), 0) * cos(theta_o) (see `target`).
    """

    name = "material"
    isotropic = True
    # The rotational symmetry of an anisotropic BSDF: f(R wi, R wo) = f(wi, wo) for R the
    # rotation about the normal by phi_period (2 pi: none). Baked tables bin phi_i over it.
    phi_period = 2.0 * np.pi
    # The incident elevations (radians) the data were measured at, between which eval
    # interpolates (a kink in theta_i at each: planned tables put bins there); None: none.
    measured_theta_i = None

    def eval(self, wi, wo):
        raise NotImplementedError

    def target(self, wi, wo):
        """The unnormalized density every sampler aims for: max(lum(f), 0) * cos(theta_o)."""
        wi, wo = as_dirs(wi, wo)
        return np.maximum(luminance(self.eval(wi, wo)), 0.0) * np.maximum(wo[:, 2], 0.0)

    def fingerprint(self):
        """A content hash: equal fingerprints mean equal BSDFs (used to detect stale caches)."""
        return hashlib.sha256(repr(sorted(vars(self).items())).encode()).hexdigest()

    def __repr__(self):
        return f"<{type(self).__name__} {self.name}>"
