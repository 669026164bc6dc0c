"""Lights: an importance-sampled environment (image, procedural sky or constant) and Blender's
lamps -- point, spot, sun and area -- with Cycles' radiometry. World space is z-up (as in Blender).

Every light has `sample(p, u) -> (wl, dist, Li, pdf)` (pdf per steradian at p; `delta` lights
return pdf 1 and cannot be hit by BSDF rays). The environment also has `eval`/`pdf` for
directions that escape; the other non-delta lamps have `intersect(o, d, t_max) -> (hit, t)`,
`eval_hit(o, d, t)` and `pdf_hit(o, d, t)` for rays a BSDF sample found, which MIS needs
(pdf_hit is exactly the pdf sample() gives that direction). `camera`: whether camera rays see
the lamp (Blender's object ray visibility).

Lamps follow Cycles: they are not geometry -- they cast no shadow, and a ray that hits one goes on
through it. S below is Blender's strength, color * energy * 2^exposure (W; the sun's is an
irradiance, W/m^2; Blender's Normalize off is folded into S by the exporter). Checked against
Cycles renders in tests/test_tracer_lamps.py.

  point  radius 0: a delta light of intensity S/(4 pi) W/sr. Radius r > 0: radiance
         S/(4 pi * pi r^2) on a disk of radius r that faces the shading point (soft falloff,
         Blender's default) or on a sphere of radius r (sampled by solid angle). The radius
         is Blender's as it is: object scale does not change it.
  spot   a point lamp whose radiance leaving in direction w is scaled by
         smoothstep((cos a - cos(size/2)) / ((1 - cos(size/2)) * blend)), a = the angle between
         w and the lamp's -Z in the lamp's frame (object scale included: a non-uniform scale
         makes the cone elliptic). Shading points inside a sphere lamp see its unattenuated
         radiance from every direction (Cycles' spot, there, is hit only by rays heading
         towards its centre).
  sun    angle 0: a delta direction of irradiance S (times cos at the surface). Angle > 0:
         uniform radiance S / (pi sin^2(angle/2)) over the cone of directions of half-angle
         angle/2 (irradiance S at normal incidence), sampled within the cone; rays that
         escape into the cone see it.
  area   a rectangle or an ellipse, one-sided: it emits along the lamp's local -Z,
         -(axis_u x axis_v). Radiance S / (pi A) (A its area, object scale included), times
         max((tan(s/2) - tan t) / (tan(s/2) - s/2), 0) for a spread s < 180 deg (t = the angle
         from the normal): the spread keeps the emitted power S.

Environment images are equirectangular in Blender's convention: column u = 0.5 -
atan2(y, x) / 2 pi, row = theta / pi * H (row 0 is the zenith). Radiance is piecewise
constant per pixel; a pixel is chosen with probability proportional to its luminance times
its solid angle and the direction drawn uniformly in the pixel's solid angle, so sample()
and pdf() are exactly consistent.
"""
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..maths.geometry import LUMINANCE
from .accel import EPS_T


class Environment:
    delta = False

    def __init__(self, image, strength=1.0, rotate_z=0.0, name="environment"):
        image = np.asarray(image, float)
        if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
            raise ValueError(f"environment image must be (H, W, 3), got {image.shape}")
        self.image = image * float(strength)
        self.rot = np.radians(float(rotate_z))
        self.name = name
        H, W = image.shape[:2]
        self.H, self.W = H, W
        z_edges = np.cos(np.linspace(0.0, np.pi, H + 1))           # decreasing
        self.z_edges = z_edges
        omega = (z_edges[:-1] - z_edges[1:]) * (2 * np.pi / W)     # solid angle per pixel, by row
        lum = np.maximum(self.image @ LUMINANCE, 0.0)
        w = (lum * omega[:, None]).ravel()
        total = w.sum()
        self.power = float(total)
        if total > 0:
            self.cdf = np.concatenate([[0.0], np.cumsum(w)]) / total
            self.lum_over_total = lum / total                       # pdf per steradian by pixel
        else:
            self.cdf = None
            self.lum_over_total = np.zeros_like(lum)

    def _pixel(self, d):
        theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
        phi = np.arctan2(d[:, 1], d[:, 0]) - self.rot
        u = 0.5 - phi / (2 * np.pi)
        u -= np.floor(u)
        row = np.clip((theta / np.pi * self.H).astype(np.int64), 0, self.H - 1)
        col = np.clip((u * self.W).astype(np.int64), 0, self.W - 1)
        return row, col

    def eval(self, d):
        row, col = self._pixel(d)
        return self.image[row, col]

    def pdf(self, d):
        row, col = self._pixel(d)
        return self.lum_over_total[row, col]

    def sample_dir(self, u):
        k = np.clip(np.searchsorted(self.cdf, u[:, 0], side="right") - 1, 0, self.H * self.W - 1)
        row, col = np.divmod(k, self.W)
        z = self.z_edges[row] + u[:, 1] * (self.z_edges[row + 1] - self.z_edges[row])
        # reuse the remainder of u0 within the chosen pixel for the azimuth
        lo, hi = self.cdf[k], self.cdf[k + 1]
        t = np.clip((u[:, 0] - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0, 1.0)
        uu = (col + t) / self.W
        phi = (0.5 - uu) * 2 * np.pi + self.rot
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        d = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)
        return d, self.lum_over_total[row, col], self.image[row, col]

    def sample(self, p, u):
        n = len(p)
        if self.cdf is None:                    # a black world: nothing to sample
            return np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, np.inf), np.zeros((n, 3)), np.zeros(n)
        d, pdf, Li = self.sample_dir(u)
        return d, np.full(n, np.inf), Li, pdf


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _basis(n):
    """Unit vectors s, t completing unit vectors n (N, 3) to orthonormal frames (Duff et al.)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    s = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return s, t


def _one_minus_cos(sin2):
    """1 - cos x from sin^2 x (x <= 90 deg), without cancellation."""
    return sin2 / (1.0 + np.sqrt(np.maximum(1.0 - sin2, 0.0)))


def _cone(axis, one_minus_cos, u):
    """Directions uniform in the cones about unit axes (N, 3) with 1 - cos(half-angle) =
    one_minus_cos; and their pdf per steradian."""
    omc = u[:, 0] * one_minus_cos
    cos = 1.0 - omc
    sin = np.sqrt(np.maximum(omc * (2.0 - omc), 0.0))
    phi = 2 * np.pi * u[:, 1]
    s, t = _basis(axis)
    d = cos[:, None] * axis + (sin * np.cos(phi))[:, None] * s + (sin * np.sin(phi))[:, None] * t
    return d, np.broadcast_to(1.0 / (2 * np.pi * one_minus_cos), len(d)).copy()


def _disk(u):
    """Points uniform in the unit disk: (x, y), each (N,)."""
    r, phi = np.sqrt(u[:, 0]), 2 * np.pi * u[:, 1]
    return r * np.cos(phi), r * np.sin(phi)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


class PointLight:
    """Blender's point lamp (see the module docstring); `SpotLight` adds the cone. Exactly one
    of strength (Blender's S) and intensity (W/sr, S / 4 pi)."""

    def __init__(self, position, *, strength=None, intensity=None, radius=0.0, soft_falloff=True, camera=True):
        if (strength is None) == (intensity is None):
            raise ValueError("give exactly one of strength and intensity")
        self.position = np.asarray(position, float)
        self.strength = np.asarray(strength, float) if intensity is None else 4 * np.pi * np.asarray(intensity, float)
        self.radius = float(radius)
        self.delta = self.radius == 0
        self.sphere = not self.delta and not soft_falloff
        self.camera = bool(camera)
        self.intensity = self.strength / (4 * np.pi)
        self.radiance = None if self.delta else self.intensity / (np.pi * self.radius ** 2)

    def attenuation(self, w):
        """Factor on the radiance leaving the lamp in unit directions w (N, 3): 1 for a point."""
        return np.ones(len(w))

    def _emitted(self, w, inside=None):
        """Radiance (N, 3) leaving the lamp's surface in directions w (unattenuated inside a sphere)."""
        att = self.attenuation(w)
        if inside is not None:
            att = np.where(inside, 1.0, att)
        return att[:, None] * self.radiance[None, :]

    def sample(self, p, u):
        v = self.position - p
        d2 = _dot(v, v)
        d = np.sqrt(d2)
        to_c = v / d[:, None]
        if self.delta:
            Li = self.attenuation(-to_c)[:, None] * self.intensity[None, :] / d2[:, None]
            return to_c, d, Li, np.ones(len(p))
        r2 = self.radius ** 2
        if self.sphere:
            inside = d2 <= r2
            wl, pdf = _cone(to_c, _one_minus_cos(np.minimum(r2 / d2, 1.0)), u)
            z = 1.0 - 2.0 * u[:, 0]                         # inside: uniform over the sphere
            rho, phi = np.sqrt(np.maximum(1.0 - z * z, 0.0)), 2 * np.pi * u[:, 1]
            wl[inside] = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)[inside]
            pdf[inside] = 1.0 / (4 * np.pi)
            t = self._sphere_t(p, wl, clamp=True)
            return wl, t, self._emitted(-wl, inside), pdf
        s, t_ = _basis(-to_c)                                   # the disk faces p
        x, y = _disk(u)
        q = self.position + self.radius * (x[:, None] * s + y[:, None] * t_)
        wl = q - p
        t = np.linalg.norm(wl, axis=1)
        wl = wl / t[:, None]
        cos_l = _dot(to_c, wl)
        return wl, t, self._emitted(-wl), t * t / (np.pi * r2 * cos_l)

    def _sphere_t(self, o, d, clamp=False):
        """Distance along unit d from o to the sphere (the far side from inside), NaN on a miss
        (clamp: directions sampled within the sphere's cone always hit)."""
        oc = o - self.position
        b = _dot(oc, d)
        c = _dot(oc, oc) - self.radius ** 2
        disc = b * b - c
        if clamp:
            disc = np.maximum(disc, 0.0)
        with np.errstate(invalid="ignore"):
            sq = np.sqrt(disc)
        return np.where(c > 0, -b - sq, -b + sq)

    def intersect(self, o, d, t_max):
        oc = o - self.position
        if self.sphere:
            t = self._sphere_t(o, d)
        else:
            n = _unit(oc)                                   # the disk faces the ray's origin
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -np.linalg.norm(oc, axis=1) / _dot(d, n)
            x = oc + t[:, None] * d
            t = np.where(_dot(x, x) <= self.radius ** 2, t, np.nan)
        hit = (t > EPS_T) & (t < t_max)
        return hit, np.where(hit, t, np.inf)

    def eval_hit(self, o, d, t):
        inside = _dot(o - self.position, o - self.position) <= self.radius ** 2 if self.sphere else None
        return self._emitted(-d, inside)

    def pdf_hit(self, o, d, t):
        oc = o - self.position
        d2 = _dot(oc, oc)
        r2 = self.radius ** 2
        if self.sphere:
            with np.errstate(divide="ignore"):
                return np.where(d2 > r2, 1.0 / (2 * np.pi * _one_minus_cos(np.minimum(r2 / d2, 1.0))),
                                1.0 / (4 * np.pi))
        cos_l = -_dot(oc, d) / np.sqrt(d2)
        return t * t / (np.pi * r2 * cos_l)


class SpotLight(PointLight):
    """Blender's spot lamp: a point lamp (any radius) whose emission is confined to a cone.
    frame: the lamp's world-from-local 3x3 (object scale included); the cone is about -Z."""

    def __init__(self, position, *, frame, size_deg, blend, **point):
        super().__init__(position, **point)
        self.to_local = np.linalg.inv(np.asarray(frame, float))
        self.cos_half = float(np.cos(np.radians(size_deg) / 2))
        self.blend = float(blend)

    def attenuation(self, w):
        z = -_unit(w @ self.to_local.T)[:, 2]
        if self.blend == 0:
            return (z > self.cos_half).astype(float)
        return _smoothstep((z - self.cos_half) / ((1.0 - self.cos_half) * self.blend))


class SunLight:
    """Blender's sun lamp (see the module docstring). direction: where its light travels."""

    def __init__(self, direction, *, strength, angle_deg=0.0, camera=True):
        self.toward = -np.asarray(direction, float) / np.linalg.norm(direction)
        self.strength = np.asarray(strength, float)
        half = np.radians(float(angle_deg)) / 2
        self.delta = half == 0
        self.camera = bool(camera)
        self.cos_half = float(np.cos(half))
        self.omc = float(2 * np.sin(half / 2) ** 2)
        self.radiance = None if self.delta else self.strength / (np.pi * np.sin(half) ** 2)

    def sample(self, p, u):
        n = len(p)
        if self.delta:
            return np.tile(self.toward, (n, 1)), np.full(n, np.inf), np.tile(self.strength, (n, 1)), np.ones(n)
        wl, pdf = _cone(np.tile(self.toward, (n, 1)), self.omc, u)
        return wl, np.full(n, np.inf), np.tile(self.radiance, (n, 1)), pdf

    def intersect(self, o, d, t_max):
        """Rays that escape (t_max infinite) within the sun's cone see it."""
        hit = np.isinf(t_max) & (d @ self.toward >= self.cos_half)
        return hit, np.full(len(d), np.inf)

    def eval_hit(self, o, d, t):
        return np.tile(self.radiance, (len(d), 1))

    def pdf_hit(self, o, d, t):
        return np.full(len(d), 1.0 / (2 * np.pi * self.omc))


class AreaLight:
    """Blender's area lamp (see the module docstring): centre `position`, full extents axis_u
    and axis_v (perpendicular; scale included), a rectangle or (ellipse) the ellipse inscribed
    in it. Exactly one of `strength` (S) and `radiance` (before the spread factor).

    Sampling: uniform by area over the shape; with a spread < 180 deg, uniform over the part
    of the shape's bounding rectangle that lies within the spread circle's bounding square
    (outside the circle of radius h tan(spread/2) about the point's projection, h its height,
    the lamp sends the point nothing), points outside an ellipse giving no light."""
    delta = False

    def __init__(self, position, axis_u, axis_v, *, strength=None, radiance=None, ellipse=False,
                 spread_deg=180.0, camera=True):
        self.position, self.axis_u, self.axis_v = (np.asarray(x, float) for x in (position, axis_u, axis_v))
        n = np.cross(self.axis_u, self.axis_v)
        self.ellipse = bool(ellipse)
        self.len_u, self.len_v = np.linalg.norm(self.axis_u), np.linalg.norm(self.axis_v)
        self.area = self.len_u * self.len_v * (np.pi / 4 if self.ellipse else 1.0)
        if not self.area > 0:
            raise ValueError("area light has zero area")
        self.normal = -n / np.linalg.norm(n)                 # the emission direction, local -Z
        if (strength is None) == (radiance is None):
            raise ValueError("give exactly one of strength and radiance")
        self.radiance = np.asarray(radiance, float) if strength is None \
            else np.asarray(strength, float) / (np.pi * self.area)
        half = np.radians(float(spread_deg)) / 2
        if not 0 < half <= np.pi / 2:
            raise ValueError(f"spread must be in (0, 180] degrees, got {spread_deg}")
        self.tan_half = np.inf if half == np.pi / 2 else float(np.tan(half))
        self.spread_norm = 1.0 / (self.tan_half - half)
        self.camera = bool(camera)

    def _emitted(self, cos_l):
        """Radiance (N, 3) leaving the front at cos_l = cos(angle to the normal) (0 behind)."""
        front = cos_l > 0
        if np.isinf(self.tan_half):
            f = front.astype(float)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                tan = np.sqrt(np.maximum(1.0 - cos_l * cos_l, 0.0)) / cos_l
            f = np.where(front, np.maximum((self.tan_half - tan) * self.spread_norm, 0.0), 0.0)
        return f[:, None] * self.radiance[None, :]

    def _coords(self, x):
        """Coordinates along axis_u, axis_v in units of the full extents (the shape: |a|, |b| <= 1/2)."""
        return x @ self.axis_u / self.len_u ** 2, x @ self.axis_v / self.len_v ** 2

    def _region(self, p):
        """(lo_a, hi_a, lo_b, hi_b, area) of the part of the shape's bounding rectangle that
        sampling from points p covers; area 0 where p gets no light."""
        n = len(p)
        if np.isinf(self.tan_half):
            lo, hi = np.full(n, -0.5), np.full(n, 0.5)
            return lo, hi, lo, hi, np.full(n, self.area)
        x = p - self.position
        r = np.maximum(x @ self.normal, 0.0) * self.tan_half
        a, b = self._coords(x)
        lo_a, hi_a = np.maximum(a - r / self.len_u, -0.5), np.minimum(a + r / self.len_u, 0.5)
        lo_b, hi_b = np.maximum(b - r / self.len_v, -0.5), np.minimum(b + r / self.len_v, 0.5)
        area = np.maximum(hi_a - lo_a, 0.0) * np.maximum(hi_b - lo_b, 0.0) * self.len_u * self.len_v
        return lo_a, hi_a, lo_b, hi_b, area

    def _inside(self, a, b):
        return a * a + b * b <= 0.25 if self.ellipse else (np.abs(a) <= 0.5) & (np.abs(b) <= 0.5)

    def sample(self, p, u):
        lo_a, hi_a, lo_b, hi_b, region = self._region(p)
        if self.ellipse and np.isinf(self.tan_half):
            a, b = _disk(u)
            a, b = a / 2, b / 2
        else:
            a, b = lo_a + u[:, 0] * (hi_a - lo_a), lo_b + u[:, 1] * (hi_b - lo_b)
        q = self.position + a[:, None] * self.axis_u + b[:, None] * self.axis_v
        wl = q - p
        dist = np.linalg.norm(wl, axis=1)
        wl = wl / dist[:, None]
        cos_l = -(wl @ self.normal)
        ok = (cos_l > 0) & (region > 0) & self._inside(a, b)
        with np.errstate(divide="ignore", invalid="ignore"):
            pdf = np.where(ok, dist * dist / (region * cos_l), 0.0)
        return wl, dist, np.where(ok[:, None], self._emitted(cos_l), 0.0), pdf

    def intersect(self, o, d, t_max):
        """One-sided: rays travelling against the normal."""
        dn = d @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.position - o) @ self.normal) / dn
        x = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d - self.position
        hit = (dn < 0) & (t > EPS_T) & (t < t_max) & self._inside(*self._coords(x))
        return hit, np.where(hit, t, np.inf)

    def eval_hit(self, o, d, t):
        return self._emitted(-(d @ self.normal))

    def pdf_hit(self, o, d, t):
        lo_a, hi_a, lo_b, hi_b, region = self._region(o)
        a, b = self._coords(o + t[:, None] * d - self.position)
        cos_l = -(d @ self.normal)
        ok = (cos_l > 0) & (region > 0) & (a >= lo_a) & (a <= hi_a) & (b >= lo_b) & (b <= hi_b)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(ok, t * t / (region * cos_l), 0.0)


# --------------------------------------------------------------------------- images

def sky_image(width=256, height=128, sun_elevation=35.0, sun_azimuth=30.0, sun_size=12.0,
              sun_strength=6.0, zenith=(0.25, 0.45, 0.9), horizon=(1.0, 1.0, 1.0),
              ground=(0.3, 0.27, 0.24)):
    """A soft procedural sky (no files needed): a zenith-to-horizon gradient, a broad
    Gaussian sun glow (sun_size = its angular standard deviation, degrees) and a dim
    ground, blended smoothly across the horizon."""
    theta = (np.arange(height) + 0.5) / height * np.pi
    u = (np.arange(width) + 0.5) / width
    phi = (0.5 - u) * 2 * np.pi
    T, P = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1)
    z = d[..., 2]
    zen, hor, gnd = (np.asarray(c, float) for c in (zenith, horizon, ground))
    up = np.clip(z, 0.0, 1.0)[..., None] ** 0.6
    sky = hor * (1 - up) + zen * up
    el, az = np.radians(sun_elevation), np.radians(sun_azimuth)
    sun_dir = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    ang = np.arccos(np.clip(d @ sun_dir, -1.0, 1.0))
    sky = sky + sun_strength * np.exp(-0.5 * (ang / np.radians(sun_size)) ** 2)[..., None] \
        * np.array([1.0, 0.95, 0.85])
    blend = 1.0 / (1.0 + np.exp(-z / 0.03))
    return sky * blend[..., None] + gnd * (1 - blend)[..., None]


def read_hdr(path):
    """Radiance RGBE (.hdr/.pic), flat or RLE scanlines."""
    data = Path(path).read_bytes()
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise FlowBSDFError("not a Radiance .hdr file (no #?RADIANCE header)", path)
    pos = data.find(b"\n\n")
    if pos < 0:
        raise FlowBSDFError("broken .hdr header", path)
    header = data[:pos].decode("latin-1")
    if "FORMAT=32-bit_rle_xyze" in header:
        raise FlowBSDFError("XYZE .hdr files are not supported (RGBE only)", path)
    end = data.find(b"\n", pos + 2)
    res = data[pos + 2:end].decode("latin-1").split()
    if len(res) != 4 or res[0] != "-Y" or res[2] != "+X":
        raise FlowBSDFError(f"unsupported .hdr orientation {' '.join(res)!r} (need -Y H +X W)", path)
    H, W = int(res[1]), int(res[3])
    buf = np.frombuffer(data, np.uint8, offset=end + 1)
    out = np.zeros((H, W, 4), np.uint8)
    i = 0
    try:
        for y in range(H):
            if W >= 8 and W < 32768 and buf[i] == 2 and buf[i + 1] == 2 and (buf[i + 2] << 8 | buf[i + 3]) == W:
                i += 4
                for c in range(4):
                    x = 0
                    while x < W:
                        n = int(buf[i])
                        i += 1
                        if n > 128:
                            n -= 128
                            out[y, x:x + n, c] = buf[i]
                            i += 1
                        else:
                            out[y, x:x + n, c] = buf[i:i + n]
                            i += n
                        x += n
            else:
                out[y] = buf[i:i + 4 * W].reshape(W, 4)
                i += 4 * W
    except (IndexError, ValueError):
        raise FlowBSDFError("truncated or corrupt .hdr pixel data", path) from None
    e = out[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return out[..., :3].astype(np.float64) * scale[..., None]


def read_image(path, allow_negative=False):
    """An image (.exr RGB(A) or .hdr) as float (H, W, 3). Environments must be finite and
    non-negative; renders of measured materials may hold negative values (allow_negative)."""
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError("environment image not found", path)
    suffix = path.suffix.lower()
    if suffix in (".hdr", ".pic"):
        img = read_hdr(path)
    elif suffix == ".exr":
        import OpenEXR
        try:
            ch = OpenEXR.File(str(path)).channels()
        except Exception as e:      # noqa: BLE001  (OpenEXR raises several types)
            raise FlowBSDFError(f"not a readable OpenEXR image ({e})", path) from None
        if "RGB" in ch or "RGBA" in ch:
            img = np.asarray(ch.get("RGB", ch.get("RGBA")).pixels, float)[..., :3]
        elif all(c in ch for c in "RGB"):
            img = np.stack([np.asarray(ch[c].pixels, float) for c in "RGB"], axis=-1)
        elif "Y" in ch:
            img = np.repeat(np.asarray(ch["Y"].pixels, float)[..., None], 3, axis=-1)
        else:
            raise FlowBSDFError(f"EXR has no R, G, B (or Y) channels (has {sorted(ch)})", path)
    else:
        raise FlowBSDFError("environment image must be .exr or .hdr", path)
    if not np.all(np.isfinite(img)):
        raise FlowBSDFError("image holds NaN or inf values", path)
    if not allow_negative and np.any(img < 0):
        raise FlowBSDFError("environment image holds negative values", path)
    return img
