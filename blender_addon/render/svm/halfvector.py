"""The tables' cell coordinates over the half vector as SVM nodes: bake/core/halfvector.py's maps
(from_ab, to_ab, polar_from_ab, polar_to_ab; in OSL blender_addon/osl/tables.h) and the frames
they are taken in."""
import math

from .graph import X, Y, Z


def _half_wi(g, cos_i, phi_i, ref):
    """wi in the halfvector map's frame (turned by `ref` from the local one)."""
    sin_i = g.math('SQRT', g.math('MAXIMUM', g.math('MULTIPLY_ADD', cos_i, g.math('MULTIPLY', cos_i, -1.0), 1.0), 0.0))
    rel = g.math('SUBTRACT', phi_i, ref)
    return (g.math('MULTIPLY', sin_i, g.math('COSINE', rel)), g.math('MULTIPLY', sin_i, g.math('SINE', rel)), cos_i)


def _half_cap(g, wi, cos_h, sin_h):
    """bake/core/halfvector.py _cap: 1 - cos theta_max at the azimuth (cos_h, sin_h) of h."""
    along = g.math('MULTIPLY_ADD', wi[0], cos_h, g.math('MULTIPLY', wi[1], sin_h))
    half = g.math('SINE', g.math('MULTIPLY', g.math('ARCTAN2', wi[2], g.math('MULTIPLY', along, -1.0)), 0.25))
    return g.math('MAXIMUM', g.math('MULTIPLY', g.math('MULTIPLY', half, half), 2.0), 1e-30)


def _mirror(g, wi, h, cap):
    """(wo floats, jac) of half vector h at wi: wo = 2 (wi.h) h - wi (z at least 0), jac =
    4 (wi.h) cap, as halfvector.py's maps end."""
    cos_ih = g.dot(g.combine(*wi), g.combine(*h))
    twice = g.math('MULTIPLY', cos_ih, 2.0)
    wo = tuple(g.math('MULTIPLY_ADD', twice, hc, g.math('MULTIPLY', wc, -1.0)) for hc, wc in zip(h, wi))
    return (wo[0], wo[1], g.math('MAXIMUM', wo[2], 0.0)), g.math('MULTIPLY', g.math('MULTIPLY', cos_ih, cap), 4.0)


def _h_at(g, one_minus_cos, cos_h, sin_h):
    """h (floats) of 1 - cos theta_h and the cosine and sine of phi_h."""
    sin_t = g.math('SQRT', g.math('MAXIMUM', g.math('MULTIPLY', one_minus_cos,
                                                     g.math('SUBTRACT', 2.0, one_minus_cos)), 0.0))
    return g.math('MULTIPLY', sin_t, cos_h), g.math('MULTIPLY', sin_t, sin_h), g.math('SUBTRACT', 1.0, one_minus_cos)


def _half_from_ab(g, a, b, wi):
    """bake/core/halfvector.py from_ab: (wo floats in the map's frame, jac)."""
    x, y = g.math('MULTIPLY_ADD', a, 2.0, -1.0), g.math('MULTIPLY_ADD', b, 1.0 / math.pi, -1.0)
    wide = g.math('GREATER_THAN', g.math('ABSOLUTE', x), g.math('ABSOLUTE', y))    # ties: either way
    r = g.select(wide, x, y)
    ratio = g.math('DIVIDE', g.select(wide, y, x), r)              # Blender's divide: 0 at r = 0
    angle = g.select(wide, g.math('MULTIPLY', ratio, math.pi / 4),
                     g.math('MULTIPLY_ADD', ratio, -math.pi / 4, math.pi / 2))
    u, v = g.math('MULTIPLY', r, g.math('COSINE', angle)), g.math('MULTIPLY', r, g.math('SINE', angle))
    phi_h = g.math('ARCTAN2', v, u)
    cos_h, sin_h = g.math('COSINE', phi_h), g.math('SINE', phi_h)
    cap = _half_cap(g, wi, cos_h, sin_h)
    one_minus_cos = g.math('MULTIPLY', g.math('MULTIPLY_ADD', u, u, g.math('MULTIPLY', v, v)), cap)
    return _mirror(g, wi, _h_at(g, one_minus_cos, cos_h, sin_h), cap)


def _polar_wi(g, cos_i):
    """wi in the halfpolar map's frame, turned by phi_i + pi: (-sin theta_i, 0, cos theta_i)."""
    sin_i = g.math('SQRT', g.math('MAXIMUM', g.math('MULTIPLY_ADD', cos_i, g.math('MULTIPLY', cos_i, -1.0), 1.0), 0.0))
    return g.math('MULTIPLY', sin_i, -1.0), 0.0, cos_i


def _polar_ref(g, phi_i):
    """The halfpolar map's frame angle, phi_i + pi (phi_i None: wi's frame)."""
    return math.pi if phi_i is None else g.math('ADD', phi_i, math.pi)


def _polar_from_ab(g, a, b, wi):
    """bake/core/halfvector.py polar_from_ab: (wo floats in the map's frame, jac)."""
    cos_h, sin_h = g.math('COSINE', b), g.math('SINE', b)
    cap = _half_cap(g, wi, cos_h, sin_h)
    return _mirror(g, wi, _h_at(g, g.math('MULTIPLY', a, cap), cos_h, sin_h), cap)


def _polar_to_ab(g, wo, wi):
    """bake/core/halfvector.py polar_to_ab: (a, b, jac) of wo (floats in the map's frame)."""
    h = g.vmath('NORMALIZE', g.vmath('ADD', g.combine(*wi), g.combine(*wo)))
    hx, hy, hz = (g.dot(h, axis) for axis in (X, Y, Z))
    b = g.math('FLOORED_MODULO', g.math('ARCTAN2', hy, hx), 2.0 * math.pi)
    cap = _half_cap(g, wi, g.math('COSINE', b), g.math('SINE', b))
    flat = g.math('DIVIDE', g.math('MULTIPLY_ADD', hx, hx, g.math('MULTIPLY', hy, hy)), g.math('ADD', hz, 1.0))
    a = g.math('DIVIDE', flat, cap, clamp=True)
    return a, b, g.math('MULTIPLY', g.math('MULTIPLY', g.dot(g.combine(*wi), h), cap), 4.0)


def _half_to_ab(g, wo, wi):
    """bake/core/halfvector.py to_ab: (a, b, jac) of wo (floats in the map's frame)."""
    h = g.vmath('NORMALIZE', g.vmath('ADD', g.combine(*wi), g.combine(*wo)))
    hx, hy, hz = (g.dot(h, axis) for axis in (X, Y, Z))
    phi_h = g.math('ARCTAN2', hy, hx)
    cos_h, sin_h = g.math('COSINE', phi_h), g.math('SINE', phi_h)
    cap = _half_cap(g, wi, cos_h, sin_h)
    flat = g.math('DIVIDE', g.math('MULTIPLY_ADD', hx, hx, g.math('MULTIPLY', hy, hy)), g.math('ADD', hz, 1.0))
    radius = g.math('SQRT', g.math('DIVIDE', flat, cap), clamp=True)
    u, v = g.math('MULTIPLY', radius, cos_h), g.math('MULTIPLY', radius, sin_h)
    wide = g.math('GREATER_THAN', g.math('ABSOLUTE', u), g.math('ABSOLUTE', v))
    major = g.select(wide, u, v)                     # r = sign(major) radius, the other by its angle
    r = g.math('MULTIPLY', g.math('SIGN', major), radius)
    other = g.math('DIVIDE', g.math('MULTIPLY', r, g.math('ARCTANGENT', g.math('DIVIDE', g.select(wide, v, u), major))),
                   math.pi / 4)
    x, y = g.select(wide, r, other), g.select(wide, other, r)
    a = g.math('MULTIPLY_ADD', x, 0.5, 0.5, clamp=True)
    b = g.math('MINIMUM', g.math('MAXIMUM', g.math('MULTIPLY_ADD', y, math.pi, math.pi), 0.0), 2.0 * math.pi)
    return a, b, g.math('MULTIPLY', g.math('MULTIPLY', g.dot(g.combine(*wi), h), cap), 4.0)
