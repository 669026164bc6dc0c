"""The tables' cell coordinates over the half vector as SVM nodes: bake/core/halfvector.py's maps
(from_ab, to_ab, polar_from_ab, polar_to_ab; in OSL blender_addon/render/osl/tables.h) and the frames
they are taken in."""
import math

from .graph import X, Y, Z, atan, atan2, clamp, cos, fma, maximum, saturate, sign, sin, sqrt, where


def _half_wi(g, cos_i, phi_i, ref):
    """wi in the halfvector map's frame (turned by `ref` from the local one)."""
    sin_i = sqrt(maximum(fma(cos_i, -cos_i, 1.0), 0.0))
    rel = phi_i - ref
    return sin_i * cos(rel), sin_i * sin(rel), cos_i


def _half_cap(g, wi, cos_h, sin_h):
    """bake/core/halfvector.py _cap: 1 - cos theta_max at the azimuth (cos_h, sin_h) of h."""
    along = fma(wi[0], cos_h, wi[1] * sin_h)
    half = sin(atan2(wi[2], -along) * 0.25)
    return maximum(half * half * 2.0, 1e-30)


def _mirror(g, wi, h, cap):
    """(wo floats, jac) of half vector h at wi: wo = 2 (wi.h) h - wi (z at least 0), jac =
    4 (wi.h) cap, as halfvector.py's maps end."""
    cos_ih = g.dot(g.combine(*wi), g.combine(*h))
    twice = cos_ih * 2.0
    wo = tuple(fma(twice, hc, -wc) for hc, wc in zip(h, wi))
    return (wo[0], wo[1], maximum(wo[2], 0.0)), cos_ih * cap * 4.0


def _h_at(g, one_minus_cos, cos_h, sin_h):
    """h (floats) of 1 - cos theta_h and the cosine and sine of phi_h."""
    sin_t = sqrt(maximum(one_minus_cos * (2.0 - one_minus_cos), 0.0))
    return sin_t * cos_h, sin_t * sin_h, 1.0 - one_minus_cos


def _half_from_ab(g, a, b, wi):
    """bake/core/halfvector.py from_ab: (wo floats in the map's frame, jac)."""
    x, y = fma(a, 2.0, -1.0), fma(b, 1.0 / math.pi, -1.0)
    wide = abs(x) > abs(y)                              # ties: either way
    r = where(wide, x, y)
    ratio = where(wide, y, x) / r                       # Blender's divide: 0 at r = 0
    angle = where(wide, ratio * (math.pi / 4), fma(ratio, -math.pi / 4, math.pi / 2))
    u, v = r * cos(angle), r * sin(angle)
    phi_h = atan2(v, u)
    cos_h, sin_h = cos(phi_h), sin(phi_h)
    cap = _half_cap(g, wi, cos_h, sin_h)
    one_minus_cos = fma(u, u, v * v) * cap
    return _mirror(g, wi, _h_at(g, one_minus_cos, cos_h, sin_h), cap)


def _polar_wi(g, cos_i):
    """wi in the halfpolar map's frame, turned by phi_i + pi: (-sin theta_i, 0, cos theta_i)."""
    sin_i = sqrt(maximum(fma(cos_i, -cos_i, 1.0), 0.0))
    return -sin_i, g.const(0.0), cos_i


def _polar_ref(g, phi_i):
    """The halfpolar map's frame angle, phi_i + pi (phi_i None: wi's frame)."""
    return g.const(math.pi) if phi_i is None else phi_i + math.pi


def _polar_from_ab(g, a, b, wi):
    """bake/core/halfvector.py polar_from_ab: (wo floats in the map's frame, jac)."""
    cos_h, sin_h = cos(b), sin(b)
    cap = _half_cap(g, wi, cos_h, sin_h)
    return _mirror(g, wi, _h_at(g, a * cap, cos_h, sin_h), cap)


def _polar_to_ab(g, wo, wi):
    """bake/core/halfvector.py polar_to_ab: (a, b, jac) of wo (floats in the map's frame)."""
    h = g.vmath('NORMALIZE', g.vmath('ADD', g.combine(*wi), g.combine(*wo)))
    hx, hy, hz = (g.dot(h, axis) for axis in (X, Y, Z))
    b = atan2(hy, hx) % (2.0 * math.pi)
    cap = _half_cap(g, wi, cos(b), sin(b))
    flat = fma(hx, hx, hy * hy) / (hz + 1.0)
    a = saturate(flat / cap)
    return a, b, g.dot(g.combine(*wi), h) * cap * 4.0


def _half_to_ab(g, wo, wi):
    """bake/core/halfvector.py to_ab: (a, b, jac) of wo (floats in the map's frame)."""
    h = g.vmath('NORMALIZE', g.vmath('ADD', g.combine(*wi), g.combine(*wo)))
    hx, hy, hz = (g.dot(h, axis) for axis in (X, Y, Z))
    phi_h = atan2(hy, hx)
    cos_h, sin_h = cos(phi_h), sin(phi_h)
    cap = _half_cap(g, wi, cos_h, sin_h)
    flat = fma(hx, hx, hy * hy) / (hz + 1.0)
    radius = saturate(sqrt(flat / cap))
    u, v = radius * cos_h, radius * sin_h
    wide = abs(u) > abs(v)
    major = where(wide, u, v)                           # r = sign(major) radius, the other by its angle
    r = sign(major) * radius
    other = r * atan(where(wide, v, u) / major) / (math.pi / 4)
    x, y = where(wide, r, other), where(wide, other, r)
    a = saturate(fma(x, 0.5, 0.5))
    b = clamp(fma(y, math.pi, math.pi), 0.0, 2.0 * math.pi)
    return a, b, g.dot(g.combine(*wi), h) * cap * 4.0
