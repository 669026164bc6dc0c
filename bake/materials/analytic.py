"""Analytic BSDF models (reflection only), and the GGX helpers the samplers use.

All models evaluate f(wi, wo) without the cosine, RGB (N, 3), zero unless wi.z > 0 and
wo.z > 0. All of them are reciprocal: f(wi, wo) == f(wo, wi).

Models
------
- `Lambert(albedo)`: f = albedo / pi.
- `Microfacet(distribution, alpha_x, alpha_y, angle, fresnel, ...)`: a rough conductor,
  f = D(h) G2(wi, wo) F(wi.h) / (4 cos_i cos_o), h = normalize(wi + wo).
  D is GGX (Trowbridge-Reitz) or Beckmann, anisotropic with roughness alpha_x along the
  lobe's x axis and alpha_y along its y axis; the lobe's axes are rotated by `angle`
  (degrees, counter-clockwise about the normal), i.e. f(wi, wo) = f_unrotated(R(-angle) wi,
  R(-angle) wo). Beckmann's Lambda uses a rational erfc (relative error < 1.2e-7). G2 is Smith's *height-correlated* masking-shadowing,
  G2 = 1 / (1 + Lambda(wi) + Lambda(wo)) (what Cycles uses; it is reciprocal and more
  accurate than the separable G1(wi) G1(wo)). Fresnel: "none" (F = 1), "schlick"
  (F = f0 + (1 - f0)(1 - cos)^5) or "conductor" (the exact unpolarized Fresnel
  reflectance of a conductor with complex index eta + i k per RGB channel, outside
  medium index 1).
- `RoughPlastic(albedo, alpha, ior)`: a GGX dielectric coat over a Lambert base,
  f = D G2 Fd(wi.h) / (4 cos_i cos_o) + albedo / pi * (1 - Fd(cos_i)) (1 - Fd(cos_o)),
  Fd the exact unpolarized dielectric Fresnel term for `ior`. Energy split: light that
  the coat's macro-surface does not reflect (1 - Fd(cos_i)) enters the base, is scattered
  diffusely, and leaves through the coat with weight 1 - Fd(cos_o). Internal
  reflections at the coat are not re-injected (that energy is lost), so the albedo stays
  below 1 and the model is reciprocal. The coat is white (uncoloured).
- `Sheen(color, roughness)`: Charlie sheen (Estevez & Kulla 2017), D(m) = (2 + 1/r)
  sin(theta_m)^(1/r) / (2 pi), f = color * D(h) G2 / (4 cos_i cos_o) with G2 = 1 / (1 +
  Lambda(cos_i) + Lambda(cos_o)) and their fitted sheen Lambda (no terminator softening).
  roughness is limited to [0.1, 1]: there the albedo stays below 0.95 (it rises from
  0-0.16 at normal incidence to 0.8-0.95 near grazing), while below 0.1 the fit lets it
  exceed 1 near the horizon (1.08 at 0.05, 1.5 at 0.02, at theta_i = 89.5 deg).
- `Retro(color, alpha)`: an isotropic GGX retro-reflector, the GGX lobe (F = 1) with wo
  turned half a turn about the normal: f(wi, wo) = color * f_ggx(wi, Rz(pi) wo). It
  peaks at wo = wi and has exactly the albedo of the GGX lobe it derives from.
- `Mixture([(weight, material), ...])`: f = sum of weight * f_k (weights positive; they
  are not normalized, keep their sum <= 1 for energy conservation).

Manifest spec (`from_spec`)
---------------------------
A table `{kind = "analytic", model = ..., ...}`; `kind` may be omitted, `name` (a
string) is optional for every model and replaces the generated readable name.
RGB values are a number or a list of 3 numbers.

  model = "lambert":    albedo (rgb in [0, 1], required)
  model = "ggx" | "beckmann":
                        alpha (isotropic) or alpha_x and alpha_y (anisotropic),
                        each in [0.001, 1]; angle (degrees, default 0);
                        fresnel = "none" | "schlick" | "conductor" (default: "schlick"
                        if f0 is given, "conductor" if eta/k are, else "none");
                        f0 (rgb in [0, 1], schlick, default 1);
                        eta (rgb > 0), k (rgb >= 0) (conductor, both required)
  model = "plastic":    albedo (rgb in [0, 1], required), alpha (in [0.001, 1], required),
                        ior (in (1, 10], default 1.5)
  model = "sheen":      color (rgb in [0, 1], required), roughness (in [0.1, 1], default 0.5)
  model = "retro":      color (rgb in [0, 1], default 1), alpha (in [0.001, 1], required)
  model = "mix":        components = [{weight = w > 0, model = ..., ...}, ...] (non-empty;
                        components may themselves be mixes)

Examples: {kind="analytic", model="ggx", alpha=0.1};
{model="ggx", alpha_x=0.01, alpha_y=0.5, angle=180, fresnel="conductor",
 eta=[0.2, 0.92, 1.1], k=[3.9, 2.45, 2.14]}.
Unknown models, unknown or missing keys and out-of-range values raise FlowBSDFError
naming the key.

GGX helpers (for samplers), all in the lobe's own (unrotated) frame, vectorized, with ax,
ay scalars or per-row arrays: `ggx_ndf`, `ggx_lambda`, `ggx_g1`, `ggx_sample_vndf`
(Heitz 2018), `ggx_vndf_pdf` (density of m in solid angle),
`ggx_reflection_pdf` (= ggx_vndf_pdf / (4 |wi.m|) with m the half vector) and
`ggx_sample_reflection`. For a rotated Microfacet material, rotate wi/wo by -angle
(`warps.rotate_z`) before calling them, and the results back by +angle.
"""
import hashlib
import math
import numbers

import numpy as np

from ..errors import FlowBSDFError
from ..maths.warps import rotate_z
from .base import Material, as_dirs

ALPHA_MIN, ALPHA_MAX = 1e-3, 1.0
SHEEN_ROUGHNESS_MIN = 0.1


# --------------------------------------------------------------------------- helpers

def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _rows(x, n):
    """A scalar or (N,) parameter as an (n,) float64 array."""
    return np.broadcast_to(np.asarray(x, dtype=np.float64), (n,))


def _erfc(x):
    """Complementary error function, fractional error < 1.2e-7 (Numerical Recipes' erfcc)."""
    x = np.asarray(x, dtype=np.float64)
    z = np.abs(x)
    t = 1.0 / (1.0 + 0.5 * z)
    poly = -1.26551223 + t * (1.00002368 + t * (0.37409196 + t * (0.09678418 + t * (
        -0.18628806 + t * (0.27886807 + t * (-1.13520398 + t * (1.48851587 + t * (
            -0.82215223 + t * 0.17087277))))))))
    r = t * np.exp(-z * z + poly)
    return np.where(x >= 0.0, r, 2.0 - r)


def _projected_alpha2(w, ax, ay):
    """ax² wx² + ay² wy² (the squared roughness-stretched tangential length)."""
    return (ax * w[..., 0]) ** 2 + (ay * w[..., 1]) ** 2


# --------------------------------------------------------------------------- GGX helpers

def ggx_ndf(m, ax, ay):
    """GGX normal distribution D(m) (per steradian; integral of D cos(theta_m) = 1); 0 for m.z <= 0."""
    m = np.asarray(m, dtype=np.float64)
    ax, ay = np.asarray(ax, dtype=np.float64), np.asarray(ay, dtype=np.float64)
    q = (m[..., 0] / ax) ** 2 + (m[..., 1] / ay) ** 2 + m[..., 2] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 1.0 / (np.pi * ax * ay * q * q)
    return np.where(m[..., 2] > 0.0, d, 0.0)


def ggx_lambda(w, ax, ay):
    """Smith's Lambda for GGX: (sqrt(1 + (ax² wx² + ay² wy²) / wz²) - 1) / 2 (inf at wz <= 0)."""
    w = np.asarray(w, dtype=np.float64)
    wz = w[..., 2]
    a2 = _projected_alpha2(w, ax, ay)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = 0.5 * (np.sqrt(1.0 + a2 / (wz * wz)) - 1.0)
    return np.where(wz > 0.0, lam, np.inf)


def ggx_g1(w, ax, ay):
    """Smith's G1 = 1 / (1 + Lambda), in the stable form 2 wz / (wz + sqrt(wz² + a²)); 0 for wz <= 0."""
    w = np.asarray(w, dtype=np.float64)
    wz = w[..., 2]
    den = wz + np.sqrt(wz * wz + _projected_alpha2(w, ax, ay))
    with np.errstate(divide="ignore", invalid="ignore"):
        g = 2.0 * wz / den
    return np.where(wz > 0.0, g, 0.0)


def ggx_sample_vndf(wi, ax, ay, u):
    """Sample a microfacet normal m from the visible-normal distribution D_wi (Heitz 2018).

    wi (3,) or (N,3) with wi.z > 0 (any elevation above the horizon), u (N,2) in [0,1).
    Returns m (N,3), unit, m.z >= 0, wi.m >= 0. Its density is `ggx_vndf_pdf(wi, m, ax, ay)`.
    """
    u = np.atleast_2d(np.asarray(u, dtype=np.float64))
    wi = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    n = max(len(u), len(wi))
    wi, u = np.broadcast_to(wi, (n, 3)), np.broadcast_to(u, (n, 2))
    ax, ay = _rows(ax, n), _rows(ay, n)
    # The incident direction in the stretched (alpha = 1) configuration.
    vh = np.stack([ax * wi[:, 0], ay * wi[:, 1], wi[:, 2]], axis=-1)
    vh /= np.linalg.norm(vh, axis=-1, keepdims=True)
    # An orthonormal basis (t1, t2, vh); t1 is horizontal.
    lensq = vh[:, 0] ** 2 + vh[:, 1] ** 2
    has_len = lensq > 0.0
    inv = np.where(has_len, 1.0 / np.sqrt(np.where(has_len, lensq, 1.0)), 0.0)
    t1 = np.where(has_len[:, None],
                  np.stack([-vh[:, 1] * inv, vh[:, 0] * inv, np.zeros(n)], axis=-1),
                  np.array([1.0, 0.0, 0.0]))
    t2 = np.cross(vh, t1)
    # A uniform point on the unit disk, warped onto the visible half of it.
    r = np.sqrt(u[:, 0])
    phi = 2.0 * np.pi * u[:, 1]
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = 0.5 * (1.0 + vh[:, 2])
    p2 = (1.0 - s) * np.sqrt(np.maximum(0.0, 1.0 - p1 * p1)) + s * p2
    p3 = np.sqrt(np.maximum(0.0, 1.0 - p1 * p1 - p2 * p2))
    nh = p1[:, None] * t1 + p2[:, None] * t2 + p3[:, None] * vh
    # Back to the ellipsoid configuration.
    m = np.stack([ax * nh[:, 0], ay * nh[:, 1], np.maximum(0.0, nh[:, 2])], axis=-1)
    return m / np.linalg.norm(m, axis=-1, keepdims=True)


def ggx_vndf_pdf(wi, m, ax, ay):
    """Density (per steradian of m) of `ggx_sample_vndf`: G1(wi) max(0, wi.m) D(m) / wi.z.

    Written as 2 max(0, wi.m) D(m) / (wi.z + sqrt(wi.z² + ax² wi.x² + ay² wi.y²)), which stays
    finite as wi.z -> 0. Zero for wi.z <= 0.
    """
    wi, m = as_dirs(wi, m)
    wz = wi[:, 2]
    den = wz + np.sqrt(wz * wz + _projected_alpha2(wi, ax, ay))
    with np.errstate(divide="ignore", invalid="ignore"):
        p = 2.0 * np.maximum(0.0, _dot(wi, m)) * ggx_ndf(m, ax, ay) / den
    return np.where(wz > 0.0, p, 0.0)


def ggx_sample_reflection(wi, ax, ay, u):
    """wo = reflect(wi, m) with m ~ D_wi; may land below the horizon (then its pdf/f are 0)."""
    wi_b = np.atleast_2d(np.asarray(wi, dtype=np.float64))
    m = ggx_sample_vndf(wi_b, ax, ay, u)
    wi_b = np.broadcast_to(wi_b, m.shape)
    return 2.0 * _dot(wi_b, m)[:, None] * m - wi_b


def ggx_reflection_pdf(wi, wo, ax, ay):
    """Density (per steradian of wo) of `ggx_sample_reflection`: ggx_vndf_pdf(wi, h) / (4 |wi.h|).

    h = normalize(wi + wo). Zero unless wi.z > 0 and wo.z > 0.
    """
    wi, wo = as_dirs(wi, wo)
    out = np.zeros(len(wo))
    ok = (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
    if np.any(ok):
        a, b = wi[ok], wo[ok]
        h = a + b
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        axr = np.broadcast_to(np.asarray(ax, float), (len(wo),))[ok]
        ayr = np.broadcast_to(np.asarray(ay, float), (len(wo),))[ok]
        out[ok] = ggx_vndf_pdf(a, h, axr, ayr) / (4.0 * np.abs(_dot(a, h)))
    return out


# --------------------------------------------------------------------------- Beckmann

def beckmann_ndf(m, ax, ay):
    m = np.asarray(m, dtype=np.float64)
    mz = m[..., 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        e = ((m[..., 0] / ax) ** 2 + (m[..., 1] / ay) ** 2) / (mz * mz)
        d = np.exp(-e) / (np.pi * ax * ay * mz ** 4)
    return np.where(mz > 0.0, d, 0.0)


def beckmann_lambda(w, ax, ay):
    """Smith's Lambda for Beckmann: (erf(a) - 1)/2 + exp(-a²)/(2 a sqrt(pi)), a = wz / sqrt(ax² wx² + ay² wy²)."""
    w = np.asarray(w, dtype=np.float64)
    wz = w[..., 2]
    t = np.sqrt(_projected_alpha2(w, ax, ay))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = wz / t
        lam = 0.5 * (np.exp(-a * a) / (a * math.sqrt(math.pi)) - _erfc(a))
    lam = np.where(t > 0.0, np.maximum(lam, 0.0), 0.0)
    return np.where(wz > 0.0, lam, np.inf)


# --------------------------------------------------------------------------- Fresnel

def fresnel_schlick(cos_theta, f0):
    c = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)[..., None]
    f0 = np.asarray(f0, float)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def fresnel_conductor(cos_theta, eta, k):
    """Exact unpolarized Fresnel reflectance of a conductor (index eta + i k, per channel) from a medium of index 1."""
    c = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)[..., None]
    eta, k = np.asarray(eta, float), np.asarray(k, float)
    c2 = c * c
    s2 = 1.0 - c2
    t0 = eta * eta - k * k - s2
    a2pb2 = np.sqrt(t0 * t0 + 4.0 * eta * eta * k * k)
    a = np.sqrt(np.maximum(0.0, 0.5 * (a2pb2 + t0)))
    t1 = a2pb2 + c2
    t2 = 2.0 * a * c
    rs = (t1 - t2) / (t1 + t2)
    t3 = a2pb2 * c2 + s2 * s2
    t4 = t2 * s2
    rp = rs * (t3 - t4) / (t3 + t4)
    return 0.5 * (rs + rp)


def fresnel_dielectric(cos_theta, ior):
    """Exact unpolarized Fresnel reflectance from a medium of index 1 into one of index `ior` (scalar)."""
    c = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)
    s2t = (1.0 - c * c) / (ior * ior)
    tir = s2t >= 1.0
    ct = np.sqrt(np.maximum(0.0, 1.0 - s2t))
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (c - ior * ct) / (c + ior * ct)
        rp = (ior * c - ct) / (ior * c + ct)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp))


# --------------------------------------------------------------------------- validation

def _bad(problem):
    raise FlowBSDFError(problem)


def _number(value, key, lo=None, hi=None, lo_open=False, hi_open=False):
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        _bad(f"{key!r} must be a number, not {value!r}")
    v = float(value)
    if not math.isfinite(v):
        _bad(f"{key!r} must be finite, not {value!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        _bad(f"{key!r} = {value!r} is out of range: must be {'>' if lo_open else '>='} {lo}")
    if hi is not None and (v >= hi if hi_open else v > hi):
        _bad(f"{key!r} = {value!r} is out of range: must be {'<' if hi_open else '<='} {hi}")
    return v


def _rgb(value, key, lo=None, hi=None, lo_open=False):
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        if len(value) != 3:
            _bad(f"{key!r} must be a number or a list of 3 numbers (RGB), got {len(value)} values")
        return tuple(_number(v, key, lo, hi, lo_open) for v in value)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        _bad(f"{key!r} must be a number or a list of 3 numbers (RGB), not {value!r}")
    v = _number(value, key, lo, hi, lo_open)
    return (v, v, v)


def _alpha(value, key):
    return _number(value, key, ALPHA_MIN, ALPHA_MAX)


def _fmt(x):
    return f"{x:g}"


def _fmt_rgb(c):
    return _fmt(c[0]) if c[0] == c[1] == c[2] else "[" + ",".join(_fmt(v) for v in c) + "]"


# --------------------------------------------------------------------------- models

class AnalyticMaterial(Material):
    """Common eval: broadcast, mask to the upper hemisphere, evaluate `_f` on the rows that count."""

    def fingerprint(self):
        """The model and its parameters (the name is left out: it does not change the BSDF)."""
        items = sorted((k, v) for k, v in vars(self).items() if k != "name")
        return hashlib.sha256(f"{type(self).__name__}:{items!r}".encode()).hexdigest()

    def eval(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        out = np.zeros((len(wo), 3))
        ok = (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
        if np.any(ok):
            out[ok] = self._f(wi[ok], wo[ok])
        return out

    def _f(self, wi, wo):
        raise NotImplementedError


class Lambert(AnalyticMaterial):
    def __init__(self, albedo, name=None):
        self.albedo = _rgb(albedo, "albedo", 0.0, 1.0)
        self.isotropic = True
        self.name = name or f"lambert({_fmt_rgb(self.albedo)})"

    def _f(self, wi, wo):
        return np.broadcast_to(np.asarray(self.albedo) / np.pi, (len(wo), 3)).copy()


class Microfacet(AnalyticMaterial):
    """Rough conductor: D G2 F / (4 cos_i cos_o), D GGX or Beckmann, height-correlated Smith G2."""

    DISTRIBUTIONS = ("ggx", "beckmann")
    FRESNELS = ("none", "schlick", "conductor")
    phi_period = math.pi        # D and Lambda depend on (x, y) through x², y² and x y: even

    def __init__(self, distribution="ggx", alpha_x=0.1, alpha_y=None, angle=0.0, fresnel="none",
                 f0=None, eta=None, k=None, name=None):
        if distribution not in self.DISTRIBUTIONS:
            _bad(f"'distribution' must be one of {list(self.DISTRIBUTIONS)}, not {distribution!r}")
        if fresnel not in self.FRESNELS:
            _bad(f"'fresnel' must be one of {list(self.FRESNELS)}, not {fresnel!r}")
        self.distribution = distribution
        if alpha_y is None:
            self.alpha_x = self.alpha_y = _alpha(alpha_x, "alpha")
        else:
            self.alpha_x, self.alpha_y = _alpha(alpha_x, "alpha_x"), _alpha(alpha_y, "alpha_y")
        self.angle = _number(angle, "angle")
        self.fresnel = fresnel
        self.f0 = self.eta = self.k = None
        if fresnel == "schlick":
            self.f0 = _rgb(1.0 if f0 is None else f0, "f0", 0.0, 1.0)
        elif f0 is not None:
            _bad(f"'f0' is only used with fresnel = 'schlick' (fresnel is {fresnel!r})")
        if fresnel == "conductor":
            if eta is None or k is None:
                _bad(f"fresnel = 'conductor' needs {'eta' if eta is None else 'k'!r}")
            self.eta = _rgb(eta, "eta", 0.0, lo_open=True)
            self.k = _rgb(k, "k", 0.0)
        elif eta is not None or k is not None:
            _bad(f"{'eta' if eta is not None else 'k'!r} is only used with fresnel = 'conductor' "
                 f"(fresnel is {fresnel!r})")
        self.isotropic = self.alpha_x == self.alpha_y
        if name:
            self.name = name
        else:
            rough = (f"a={_fmt(self.alpha_x)}" if self.isotropic
                     else f"ax={_fmt(self.alpha_x)},ay={_fmt(self.alpha_y)},angle={_fmt(self.angle)}")
            self.name = f"{distribution}({rough}{'' if fresnel == 'none' else ',' + fresnel})"

    # The lobe frame: the material's frame rotated by -angle.
    def _to_lobe(self, w):
        return rotate_z(w, -math.radians(self.angle)) if self.angle % 360.0 else w

    def ndf(self, m):
        """D(m) in the material frame (rotation applied)."""
        m = self._to_lobe(np.asarray(m, float))
        fn = ggx_ndf if self.distribution == "ggx" else beckmann_ndf
        return fn(m, self.alpha_x, self.alpha_y)

    def lambda_(self, w):
        w = self._to_lobe(np.asarray(w, float))
        fn = ggx_lambda if self.distribution == "ggx" else beckmann_lambda
        return fn(w, self.alpha_x, self.alpha_y)

    def fresnel_term(self, cos_theta):
        if self.fresnel == "schlick":
            return fresnel_schlick(cos_theta, self.f0)
        if self.fresnel == "conductor":
            return fresnel_conductor(cos_theta, self.eta, self.k)
        return np.ones(np.shape(cos_theta) + (3,))

    def _f(self, wi, wo):
        h = wi + wo
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        d = self.ndf(h)
        g = 1.0 / (1.0 + self.lambda_(wi) + self.lambda_(wo))
        f = d * g / (4.0 * wi[:, 2] * wo[:, 2])
        return f[:, None] * self.fresnel_term(_dot(wi, h))


class RoughPlastic(AnalyticMaterial):
    """GGX dielectric coat (white) over a Lambert base; see the module docstring for the energy split."""

    def __init__(self, albedo, alpha, ior=1.5, name=None):
        self.albedo = _rgb(albedo, "albedo", 0.0, 1.0)
        self.alpha = _alpha(alpha, "alpha")
        self.ior = _number(ior, "ior", 1.0, 10.0, lo_open=True)
        self.isotropic = True
        self.name = name or f"plastic({_fmt_rgb(self.albedo)},a={_fmt(self.alpha)},ior={_fmt(self.ior)})"

    def _f(self, wi, wo):
        h = wi + wo
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        a = self.alpha
        spec = (ggx_ndf(h, a, a) / (1.0 + ggx_lambda(wi, a, a) + ggx_lambda(wo, a, a))
                * fresnel_dielectric(_dot(wi, h), self.ior) / (4.0 * wi[:, 2] * wo[:, 2]))
        trans = (1.0 - fresnel_dielectric(wi[:, 2], self.ior)) * (1.0 - fresnel_dielectric(wo[:, 2], self.ior))
        return spec[:, None] + (trans / np.pi)[:, None] * np.asarray(self.albedo)


# Estevez & Kulla's fit of the sheen Lambda: L(x) = a / (1 + b x^c) + d x + e, with (a, b, c, d, e)
# blended between the fits for roughness 0 and 1 with weight (1 - roughness)² on the former.
_SHEEN_FIT_R0 = np.array([25.3245, 3.32435, 0.16801, -1.27393, -4.85967])
_SHEEN_FIT_R1 = np.array([21.5473, 3.82987, 0.19823, -1.97760, -4.32054])


class Sheen(AnalyticMaterial):
    """Charlie sheen: D(m) = (2 + 1/r) sin(theta_m)^(1/r) / (2 pi), G2 = 1 / (1 + Lambda_i + Lambda_o)."""

    def __init__(self, color, roughness=0.5, name=None):
        self.color = _rgb(color, "color", 0.0, 1.0)
        self.roughness = _number(roughness, "roughness", SHEEN_ROUGHNESS_MIN, 1.0)
        self.isotropic = True
        self.name = name or f"sheen({_fmt_rgb(self.color)},r={_fmt(self.roughness)})"

    def _fit(self, x):
        t = (1.0 - self.roughness) ** 2
        a, b, c, d, e = t * _SHEEN_FIT_R0 + (1.0 - t) * _SHEEN_FIT_R1
        return a / (1.0 + b * x ** c) + d * x + e

    def sheen_lambda(self, cos_theta):
        mu = np.clip(cos_theta, 0.0, 1.0)
        return np.where(mu < 0.5, np.exp(self._fit(mu)), np.exp(2.0 * self._fit(0.5) - self._fit(1.0 - mu)))

    def _f(self, wi, wo):
        h = wi + wo
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        inv_r = 1.0 / self.roughness
        sin_h = np.sqrt(np.maximum(0.0, 1.0 - h[:, 2] ** 2))
        d = (2.0 + inv_r) * sin_h ** inv_r / (2.0 * np.pi)
        g = 1.0 / (1.0 + self.sheen_lambda(wi[:, 2]) + self.sheen_lambda(wo[:, 2]))
        return (d * g / (4.0 * wi[:, 2] * wo[:, 2]))[:, None] * np.asarray(self.color)


class Retro(AnalyticMaterial):
    """Isotropic GGX retro-reflector: color * f_ggx(wi, Rz(pi) wo) (F = 1); peaks at wo = wi."""

    def __init__(self, alpha, color=1.0, name=None):
        self.color = _rgb(color, "color", 0.0, 1.0)
        self.alpha = _alpha(alpha, "alpha")
        self.isotropic = True
        self.name = name or f"retro({_fmt_rgb(self.color)},a={_fmt(self.alpha)})"

    def _f(self, wi, wo):
        wo_t = wo * np.array([-1.0, -1.0, 1.0])
        h = wi + wo_t
        n = np.linalg.norm(h, axis=-1, keepdims=True)
        # wi + Rz(pi) wo = 0 only if both lie on the horizon: excluded by the mask.
        h /= n
        a = self.alpha
        f = (ggx_ndf(h, a, a) / (1.0 + ggx_lambda(wi, a, a) + ggx_lambda(wo, a, a))
             / (4.0 * wi[:, 2] * wo[:, 2]))
        return f[:, None] * np.asarray(self.color)


class Mixture(AnalyticMaterial):
    """sum_k weight_k * f_k."""

    def __init__(self, components, name=None):
        components = list(components)
        if not components:
            _bad("'components' must be a non-empty list")
        self.weights, self.components = [], []
        for i, (w, mat) in enumerate(components):
            self.weights.append(_number(w, f"components[{i}].weight", 0.0, lo_open=True))
            if not isinstance(mat, Material):
                _bad(f"components[{i}] is not a Material")
            self.components.append(mat)
        self.isotropic = all(m.isotropic for m in self.components)
        self.name = name or "mix(" + ", ".join(f"{_fmt(w)}*{m.name}"
                                               for w, m in zip(self.weights, self.components)) + ")"

    @property
    def phi_period(self):       # periods 2 pi / n_k: the mix repeats after 2 pi / gcd(n_k)
        n = [round(2.0 * math.pi / m.phi_period) for m in self.components if not m.isotropic]
        return 2.0 * math.pi / math.gcd(*n) if n else 2.0 * math.pi

    def eval(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        out = np.zeros((len(wo), 3))
        for w, m in zip(self.weights, self.components):
            out += w * m.eval(wi, wo)
        return out

    def fingerprint(self):
        parts = ["Mixture"] + [f"{w!r}:{m.fingerprint()}" for w, m in zip(self.weights, self.components)]
        return hashlib.sha256("|".join(parts).encode()).hexdigest()


# --------------------------------------------------------------------------- from_spec

_COMMON = {"kind", "model", "name"}
_KEYS = {
    "lambert": ({"albedo"}, set()),
    "ggx": (set(), {"alpha", "alpha_x", "alpha_y", "angle", "fresnel", "f0", "eta", "k"}),
    "beckmann": (set(), {"alpha", "alpha_x", "alpha_y", "angle", "fresnel", "f0", "eta", "k"}),
    "plastic": ({"albedo", "alpha"}, {"ior"}),
    "sheen": ({"color"}, {"roughness"}),
    "retro": ({"alpha"}, {"color"}),
    "mix": ({"components"}, set()),
}


def from_spec(spec, _where="analytic material"):
    """Build an analytic Material from a manifest table (see the module docstring)."""
    if not isinstance(spec, dict):
        _bad(f"{_where} must be a table, not {type(spec).__name__}")
    kind = spec.get("kind", "analytic")
    if kind != "analytic":
        _bad(f"{_where}: 'kind' must be 'analytic' here, not {kind!r}")
    if "model" not in spec:
        _bad(f"{_where} needs a 'model' key (one of {sorted(_KEYS)})")
    model = spec["model"]
    if model not in _KEYS:
        _bad(f"{_where}: unknown 'model' {model!r}; expected one of {sorted(_KEYS)}")
    required, optional = _KEYS[model]
    allowed = _COMMON | required | optional
    unknown = sorted(set(spec) - allowed)
    if unknown:
        _bad(f"{_where} (model {model!r}): unknown key {unknown[0]!r}; allowed keys: {sorted(allowed - {'kind'})}")
    missing = sorted(required - set(spec))
    if missing:
        _bad(f"{_where} (model {model!r}): missing key {missing[0]!r}")
    name = spec.get("name")
    if name is not None and not isinstance(name, str):
        _bad(f"{_where}: 'name' must be a string, not {name!r}")
    try:
        return _build(model, spec, name, _where)
    except FlowBSDFError as e:
        if e.problem.startswith(_where):
            raise
        raise FlowBSDFError(f"{_where} (model {model!r}): {e.problem}") from None


def _build(model, spec, name, where):
    if model == "lambert":
        return Lambert(spec["albedo"], name=name)
    if model in ("ggx", "beckmann"):
        has_iso = "alpha" in spec
        has_aniso = "alpha_x" in spec or "alpha_y" in spec
        if has_iso and has_aniso:
            _bad("give either 'alpha' or 'alpha_x' and 'alpha_y', not both")
        if has_aniso:
            for key in ("alpha_x", "alpha_y"):
                if key not in spec:
                    _bad(f"missing key {key!r} (anisotropic roughness needs alpha_x and alpha_y)")
        elif not has_iso:
            _bad("missing key 'alpha' (or 'alpha_x' and 'alpha_y')")
        fresnel = spec.get("fresnel")
        if fresnel is None:
            fresnel = "schlick" if "f0" in spec else "conductor" if ("eta" in spec or "k" in spec) else "none"
        if has_iso:
            ax, ay = spec["alpha"], None
        else:
            ax, ay = spec["alpha_x"], spec["alpha_y"]
        return Microfacet(model, ax, ay, angle=spec.get("angle", 0.0), fresnel=fresnel,
                          f0=spec.get("f0"), eta=spec.get("eta"), k=spec.get("k"), name=name)
    if model == "plastic":
        return RoughPlastic(spec["albedo"], spec["alpha"], spec.get("ior", 1.5), name=name)
    if model == "sheen":
        return Sheen(spec["color"], spec.get("roughness", 0.5), name=name)
    if model == "retro":
        return Retro(spec["alpha"], spec.get("color", 1.0), name=name)
    # mix
    comps = spec["components"]
    if not isinstance(comps, (list, tuple)) or not comps:
        _bad("'components' must be a non-empty list of tables")
    parts = []
    for i, c in enumerate(comps):
        w = f"{where}.components[{i}]"
        if not isinstance(c, dict):
            _bad(f"{w} must be a table, not {type(c).__name__}")
        if "weight" not in c:
            _bad(f"{w}: missing key 'weight'")
        weight = _number(c["weight"], f"components[{i}].weight", 0.0, lo_open=True)
        parts.append((weight, from_spec({k: v for k, v in c.items() if k != "weight"}, w)))
    return Mixture(parts, name=name)


__all__ = [
    "Lambert", "Microfacet", "RoughPlastic", "Sheen", "Retro", "Mixture", "AnalyticMaterial", "from_spec",
    "ggx_ndf", "ggx_lambda", "ggx_g1", "ggx_sample_vndf", "ggx_vndf_pdf", "ggx_reflection_pdf",
    "ggx_sample_reflection", "beckmann_ndf", "beckmann_lambda",
    "fresnel_schlick", "fresnel_conductor", "fresnel_dielectric",
]
