"""The anisotropic tables' coordinates: the half vector h of (wi, wo) on a disk.

Why: in the isotropic tables' coordinates (theta_o and the azimuth from wi's plane) a thin
anisotropic lobe is a streak that turns as phi_i turns, so tables blended between two phi_i
bins smear it over a blob tens of times its area (rv 500x the ideal tabulation half-way
between bins, 1:25 GGX at theta_i 70, 8 bins over pi). In the half vector, in the
material's own frame, the same lobe stays where the microfacets are: only its weights
change with wi, and blending follows it.

The map, for a given wi (upper hemisphere):
- The valid h (whose mirror of wi, wo = 2 (wi.h) h - wi, is above the horizon) are the
  h with theta_h < theta_max(phi_h) = atan2(wi_z, -A) / 2, A = wi's component along phi_h:
  a star-shaped cap around the pole, shrinking on the side away from wi.
- Scaled radially to a unit disk by area: radius^2 = (1 - cos theta_h) / (1 - cos theta_max),
  angle phi_h (the material frame's x axis at angle 0).
- The disk onto the square [-1, 1]^2 by the concentric map (area-preserving, rays to rays,
  the disk's centre, the specular peak of every wi, at the square's centre), and the square
  onto the tables' (a, b) in [0, 1] x [0, 2 pi].
So the valid h fill the tables' domain exactly: no sample is lost below the horizon, and a
streak of microfacets is a straight line through the centre at every wi.

Measure: d omega_h = (1 - cos theta_max(phi_h)) da db, d omega_o = 4 (wo.h) d omega_h, so
a density over (a, b) is one over wo divided by jac = 4 (wo.h) (1 - cos theta_max).
"""
import numpy as np

from ..maths.geometry import atan2
from ..maths.warps import rotate_z

TWO_PI = 2.0 * np.pi
QUARTER = 0.25 * np.pi
_TINY = 1e-300


def _cap(wi, phi_h):
    """1 - cos theta_max(phi_h): the valid cap's extent along phi_h, per direction."""
    return _cap_along(wi[:, 2], wi[:, 0] * np.cos(phi_h) + wi[:, 1] * np.sin(phi_h))


def _cap_along(wi_z, along):
    """_cap from wi's height and its component along phi_h."""
    return np.maximum(2.0 * np.sin(0.25 * atan2(wi_z, -along)) ** 2, _TINY)   # no cancellation


def _per_point(wi, n):
    wi = np.asarray(wi, np.float64)
    return np.broadcast_to(wi, (n, 3)) if wi.ndim == 1 else wi


def from_ab(wi, a, b, frame=0.0):
    """(wo, jac) of table coordinates (a, b) at wi: jac = d omega_o / (da db). h is mapped in
    the frame turned by `frame` (per point or one angle) from wi's and wo's."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    wi = rotate_z(_per_point(wi, len(a)), -frame)
    x, y = 2.0 * a - 1.0, b / np.pi - 1.0
    wide = np.abs(x) >= np.abs(y)                        # the square's sector: |x| >= |y|
    r = np.where(wide, x, y)
    safe = np.where(r == 0.0, 1.0, r)
    angle = np.where(wide, QUARTER * (y / safe), 2.0 * QUARTER - QUARTER * (x / safe))
    u, v = r * np.cos(angle), r * np.sin(angle)          # the disk point
    phi_h = atan2(v, u)
    cap = _cap(wi, phi_h)
    return _mirror(wi, (u * u + v * v) * cap, phi_h, cap, frame)


def _mirror(wi, one_minus_cos, phi_h, cap, frame):
    """(wo turned back by frame, jac) of the half vector (1 - cos theta_h, phi_h) at wi (in the frame)."""
    sin_h = np.sqrt(np.maximum(one_minus_cos * (2.0 - one_minus_cos), 0.0))
    h = np.stack([sin_h * np.cos(phi_h), sin_h * np.sin(phi_h), 1.0 - one_minus_cos], axis=-1)
    cos_ih = np.sum(wi * h, axis=-1)
    wo = 2.0 * cos_ih[:, None] * h - wi
    wo[:, 2] = np.maximum(wo[:, 2], 0.0)                  # the rim is the horizon (rounding)
    return rotate_z(wo, frame), 4.0 * cos_ih * cap


def _half_of(wi, wo, frame):
    """(wi, h = normalize(wi + wo)) in the frame turned by `frame`."""
    wo = rotate_z(np.asarray(wo, np.float64), -frame)
    wi = np.asarray(wi, np.float64)
    if wi.ndim == 1 and np.ndim(frame) == 0:        # one wi turned once: the numbers of each row turned
        wi = np.broadcast_to(rotate_z(wi, -frame), (len(wo), 3))
    else:
        wi = rotate_z(_per_point(wi, len(wo)), -frame)
    h = wi + wo
    with np.errstate(invalid="ignore", divide="ignore"):     # wo = -wi (below): callers give pdf 0
        return wi, h / np.linalg.norm(h, axis=-1, keepdims=True)


def to_ab(wi, wo, frame=0.0):
    """(a, b, jac) of directions wo at wi (both upper hemisphere), as from_ab's inverse."""
    wi, h = _half_of(wi, wo, frame)
    phi_h = atan2(h[:, 1], h[:, 0])
    cap = _cap(wi, phi_h)
    radius = np.sqrt(np.clip((h[:, 0] ** 2 + h[:, 1] ** 2) / (1.0 + h[:, 2]) / cap, 0.0, 1.0))
    u, v = radius * np.cos(phi_h), radius * np.sin(phi_h)
    wide = np.abs(u) >= np.abs(v)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(wide, np.sign(u) * radius, np.sign(v) * radius * np.arctan(u / v) / QUARTER)
        y = np.where(wide, np.sign(u) * radius * np.arctan(v / u) / QUARTER, np.sign(v) * radius)
    x, y = np.nan_to_num(x), np.nan_to_num(y)             # the centre: u = v = 0
    a = np.clip(0.5 * (x + 1.0), 0.0, 1.0)
    b = np.clip(np.pi * (y + 1.0), 0.0, TWO_PI)
    return a, b, 4.0 * np.sum(wi * h, axis=-1) * cap


# The isotropic tables' polar map: the same valid cap, polar instead of concentric. a = the
# disk radius^2 = (1 - cos theta_h) / (1 - cos theta_max(phi_h)), b = phi_h in the frame (Tables
# turns it by phi_i + pi: b = 0 away from wi, where the cap is narrowest). Rings of a are
# rings around the mirror direction, as a lobe's level sets are; d omega_h = cap da db, so
# again jac = 4 (wo.h) cap.


def polar_from_ab(wi, a, b, frame=0.0):
    """(wo, jac) of polar coordinates (a, b) at wi, h mapped in the frame turned by `frame`."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    wi = rotate_z(_per_point(wi, len(a)), -frame)
    cap = _cap(wi, b)
    return _mirror(wi, a * cap, b, cap, frame)


def polar_grid_from_ab(wi, a, b, frame=0.0):
    """polar_from_ab at one wi on each cell's grid of nodes: a (cells, qa) x b (cells, qb), flat
    in the order (cell, a node, b node). The same numbers as polar_from_ab on the repeated
    nodes; the cap and the azimuth's sines, which depend on b alone, once per b node."""
    wi = rotate_z(np.asarray(wi, np.float64), -frame)
    cos_b, sin_b = np.cos(b), np.sin(b)
    cap = _cap_along(wi[2], wi[0] * cos_b + wi[1] * sin_b)
    from ..maths import fasttables
    fast = fasttables.polar_grid(a, cos_b, sin_b, cap, wi, np.cos(frame), np.sin(frame))
    if fast is not None:        # the per-node products below in C, the same bits
        return fast
    one_minus_cos = a[:, :, None] * cap[:, None, :]
    sin_h = np.sqrt(np.maximum(one_minus_cos * (2.0 - one_minus_cos), 0.0))
    h = (sin_h * cos_b[:, None, :], sin_h * sin_b[:, None, :], 1.0 - one_minus_cos)
    cos_ih = wi[0] * h[0] + wi[1] * h[1] + wi[2] * h[2]
    # wo = 2 (wi.h) h - wi, the rim the horizon (rounding), turned back by the frame: rotate_z's
    # products written into one array (the quadrature's hottest lines: a stack each, before).
    twice = 2.0 * cos_ih
    x, y, z = (np.subtract(np.multiply(twice, h[k], out=h[k]), wi[k], out=h[k]) for k in range(3))
    np.maximum(z, 0.0, out=z)
    c, s = np.cos(frame), np.sin(frame)
    wo = np.empty(x.shape + (3,))
    np.subtract(c * x, s * y, out=wo[..., 0])
    np.add(s * x, c * y, out=wo[..., 1])
    wo[..., 2] = z
    return wo.reshape(-1, 3), (4.0 * cos_ih * cap[:, None, :]).ravel()


def polar_to_ab(wi, wo, frame=0.0):
    """(a, b, jac) of directions wo at wi, as polar_from_ab's inverse."""
    a, b, wi, h, cap = _polar_ab(wi, wo, frame)
    return a, b, 4.0 * np.sum(wi * h, axis=-1) * cap


def _polar_ab(wi, wo, frame=0.0):
    """polar_to_ab's a and b, and what its jac takes (wi and h in the frame, the cap): the
    baker's points need a and b alone."""
    wi, h = _half_of(wi, wo, frame)
    b = np.mod(atan2(h[:, 1], h[:, 0]), TWO_PI)
    cap = _cap(wi, b)
    a = np.nan_to_num(np.clip((h[:, 0] ** 2 + h[:, 1] ** 2) / (1.0 + h[:, 2]) / cap, 0.0, 1.0))
    return a, np.nan_to_num(b), wi, h, cap
