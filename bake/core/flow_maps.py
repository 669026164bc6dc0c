"""The flow's coordinate maps: flow coordinates y <-> outgoing directions wo (numpy only, float64).

A trained model (flow.py) ends in one of these fixed bijections; MAPS names them by domain.

Flow coordinates y live on an unbounded space (for disk and spherical a bijection onto the
hemisphere, so no sample is ever lost):
  - disk:      y in R², y = x * rho / r with x = (wo.x, wo.y), r = |x| = sin(theta_o),
               rho² = -2 log(1 - r²) = -4 log(cos theta_o).
  - spherical: y = (s, phi) in R x S¹, sin²(theta_o) = Phi(s), cos²(theta_o) = Phi(-s),
               Phi the standard normal CDF.
  - slope:     y = (log tan theta_h, phi_h) in R x S¹ (SlopeMap), h = (wi + wo)/|wi + wo|
               the half vector: a GGX lobe of roughness alpha is a unit-width bump at
               log(alpha) whatever wi, a spike over a glow two bumps; a y whose mirror
               direction is below the horizon is a lost sample (pdf 0).
The disk and spherical maps send the cosine-weighted hemisphere to the standard Gaussian
(times a uniform phi), so for a Lambertian material the ideal flow is the identity with a
standard base, and the target density in y is always f(wi, wo) times a Gaussian weight:
  disk:       d omega / dy          = cos(theta_o) / 2
  spherical:  d omega / (ds dphi)   = N(s) / (2 cos(theta_o))     (N the normal density)
The horizon is at infinity (grazing directions get resolution, like an adaptive
parameterization); in the spherical map the pole is at s = -inf.

Each map has to_dir(y, wi), from_dir(wo, wi), from_domain(x, wi) (from the training data's
domain coordinates, bake/core/domains.py), log_dw_dy(y, wi) (log of the solid angle per unit
flow area) and valid(wo); `periodic` says which coordinates wrap.
"""
import math

import numpy as np

from ..maths.special import SQRT1_2, log_normal_pdf, ndtr, ndtri, wrap_angle
from .domains import Disk

LOG2 = math.log(2.0)


class DiskMap:
    """y in R² <-> wo in the upper hemisphere: y = x rho / r, rho² = -4 log cos(theta_o)."""

    domain = "disk"
    periodic = (False, False)

    @staticmethod
    def to_dir(y, wi=None):
        y = np.asarray(y, dtype=np.float64)
        q = np.sum(y * y, axis=-1)                      # rho²
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(q > 1e-300, np.sqrt(-np.expm1(-0.5 * q) / np.where(q > 1e-300, q, 1.0)),
                             SQRT1_2)                   # r / rho
        z = np.exp(-0.25 * q)
        return np.concatenate([y * ratio[..., None], z[..., None]], axis=-1)

    @staticmethod
    def from_dir(wo, wi=None):
        """Flow coordinates of directions (cos theta_o from wo.z keeps precision near the rim)."""
        wo = np.asarray(wo, dtype=np.float64)
        n2 = np.sum(wo * wo, axis=-1)
        r2 = (wo[..., 0] ** 2 + wo[..., 1] ** 2) / n2
        small = r2 < 0.5
        with np.errstate(divide="ignore", invalid="ignore"):
            # log(cos² theta) from log|z|: z² underflows to 0 (rho = inf, pdf NaN) for z < 1e-154
            log_c2 = 2.0 * np.log(np.abs(wo[..., 2])) - np.log(n2)
            q = -2.0 * np.where(small, np.log1p(-np.where(small, r2, 0.0)), log_c2)   # rho²
            ratio = np.where(r2 > 1e-300, np.sqrt(q / np.where(r2 > 1e-300, r2, 1.0)), math.sqrt(2.0))
        return wo[..., :2] / np.sqrt(n2)[..., None] * ratio[..., None]

    @staticmethod
    def from_domain(x, wi=None):
        """Flow coordinates of disk domain points (|x| < 1)."""
        x = np.asarray(x, dtype=np.float64)
        r2 = np.sum(x * x, axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(r2 > 1e-300, np.sqrt(-2.0 * np.log1p(-r2) / np.where(r2 > 1e-300, r2, 1.0)),
                             math.sqrt(2.0))
        return x * ratio[..., None]

    @staticmethod
    def to_domain(y):
        return DiskMap.to_dir(y)[..., :2]

    @staticmethod
    def log_dw_dy(y, wi=None):
        """log of d omega / dy (solid angle per unit flow area) = log(cos theta_o / 2)."""
        return -0.25 * np.sum(np.asarray(y) ** 2, axis=-1) - LOG2

    @staticmethod
    def valid(wo):
        return np.asarray(wo)[..., 2] > 0.0


class SphericalMap:
    """(s, phi) in R x S¹ <-> wo: sin²(theta_o) = Phi(s), cos²(theta_o) = Phi(-s)."""

    domain = "spherical"
    periodic = (False, True)

    @staticmethod
    def to_dir(y, wi=None):
        y = np.asarray(y, dtype=np.float64)
        s, phi = y[..., 0], y[..., 1]
        st = np.sqrt(ndtr(s))
        ct = np.sqrt(ndtr(-s))
        return np.stack([st * np.cos(phi), st * np.sin(phi), ct], axis=-1)

    @staticmethod
    def from_dir(wo, wi=None):
        wo = np.asarray(wo, dtype=np.float64)
        n2 = np.sum(wo * wo, axis=-1)
        s2 = (wo[..., 0] ** 2 + wo[..., 1] ** 2) / n2
        c2 = wo[..., 2] ** 2 / n2
        # z > 0 with z² below the smallest normal (z < 1.5e-154) would give s = inf or NaN and a NaN
        # pdf: take the smallest normal instead (s = 37.5; the density there is < 1e-300 either way).
        # The same at the pole (wo = normal, s = -inf): a light straight above a shading point
        # asked pdf() there and got NaN (stress suite); the density's limit there is ~0.
        tiny = np.finfo(np.float64).tiny
        c2 = np.where((c2 < tiny) & (wo[..., 2] != 0), tiny, c2)
        s2 = np.maximum(s2, tiny)
        s = np.where(s2 <= 0.5, ndtri(s2), -ndtri(c2))
        return np.stack([s, np.arctan2(wo[..., 1], wo[..., 0])], axis=-1)

    @staticmethod
    def from_domain(x, wi=None):
        x = np.asarray(x, dtype=np.float64)
        theta = x[..., 0]
        tiny = np.finfo(np.float64).tiny        # as in from_dir: the pole stays finite
        s2, c2 = np.maximum(np.sin(theta) ** 2, tiny), np.maximum(np.cos(theta) ** 2, tiny)
        s = np.where(s2 <= 0.5, ndtri(s2), -ndtri(c2))
        return np.stack([s, wrap_angle(x[..., 1])], axis=-1)

    @staticmethod
    def to_domain(y):
        y = np.asarray(y, dtype=np.float64)
        theta = np.arctan2(np.sqrt(ndtr(y[..., 0])), np.sqrt(ndtr(-y[..., 0])))
        return np.stack([theta, wrap_angle(y[..., 1])], axis=-1)

    @staticmethod
    def log_dw_dy(y, wi=None):
        """log of d omega / (ds dphi) = log(N(s) / (2 cos theta_o))."""
        s = np.asarray(y, dtype=np.float64)[..., 0]
        with np.errstate(divide="ignore"):
            return log_normal_pdf(s) - LOG2 - 0.5 * np.log(ndtr(-s))

    @staticmethod
    def valid(wo):
        return np.asarray(wo)[..., 2] > 0.0


class SlopeMap:
    """(s, phi) in R x S¹ <-> the half vector h at tan(theta_h) = e^s, azimuth phi; wo = 2 (wi.h) h - wi.

    Log-polar slope space: a GGX lobe of any roughness alpha becomes a bump of unit width at
    s = log(alpha), so a sharp spike over a broad glow (clear coats, lacquers) is two bumps
    along one axis, which a flow can learn, where in a linear map their scales differ 100x.
    d omega_h / (ds dphi) = sin²(theta_h) cos(theta_h); d omega_o = 4 (wi.h) d omega_h.
    Every wo above the horizon has exactly one y, but a y whose mirror direction falls below
    the horizon has no wo: sample() returns pdf 0 there (a lost sample, no bias), and a trained
    model puts little mass there because its data has none. wi: the canonical incident
    direction per row. Training data comes as disk coordinates of wo (bake.core.domains: Disk).
    """

    domain = "slope"
    periodic = (False, True)

    @staticmethod
    def _half(y):
        y = np.asarray(y, dtype=np.float64)
        s, phi = y[..., 0], y[..., 1]
        t = np.exp(-np.abs(s))                     # tan or cot of theta_h, never overflows
        norm = 1.0 / np.sqrt(1.0 + t * t)
        st = np.where(s > 0, norm, t * norm)
        ct = np.where(s > 0, t * norm, norm)
        return np.stack([st * np.cos(phi), st * np.sin(phi), ct], axis=-1)

    @staticmethod
    def to_dir(y, wi):
        h = SlopeMap._half(y)
        return 2.0 * np.sum(wi * h, axis=-1, keepdims=True) * h - wi

    @staticmethod
    def from_dir(wo, wi):
        wo = np.asarray(wo, dtype=np.float64)
        h = wo / np.linalg.norm(wo, axis=-1, keepdims=True) + wi
        tiny = np.finfo(np.float64).tiny          # h along the normal: s = -inf, kept finite
        r = np.maximum(np.hypot(h[..., 0], h[..., 1]), tiny)
        with np.errstate(divide="ignore"):
            s = np.log(r) - np.log(np.maximum(h[..., 2], tiny))
        return np.stack([s, np.arctan2(h[..., 1], h[..., 0])], axis=-1)

    @staticmethod
    def from_domain(x, wi):
        return SlopeMap.from_dir(Disk().to_dir(x), wi)

    @staticmethod
    def log_dw_dy(y, wi):
        s = np.asarray(y, dtype=np.float64)[..., 0]
        log_sin = -0.5 * np.logaddexp(0.0, -2.0 * s)
        log_cos = -0.5 * np.logaddexp(0.0, 2.0 * s)
        cos_ih = np.sum(wi * SlopeMap._half(y), axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            return 2.0 * log_sin + log_cos + np.log(4.0 * np.maximum(cos_ih, 0.0))

    @staticmethod
    def valid(wo):
        return np.asarray(wo)[..., 2] > 0.0


MAPS = {"disk": DiskMap, "spherical": SphericalMap, "slope": SlopeMap}
