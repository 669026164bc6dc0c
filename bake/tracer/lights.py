"""Lights: an importance-sampled environment (image, procedural sky or constant), point lights
and one-sided quad area lights. World space is z-up (as in Blender).

Every light has `sample(p, u) -> (wl, dist, Li, pdf)` (pdf per steradian at p; `delta`
lights return pdf 1 and must not be hit by BSDF rays); the environment and quads also have
`eval`/`pdf` for directions a BSDF sample found, which MIS needs.

Environment images are equirectangular in Blender's convention: column u = 0.5 -
atan2(y, x) / 2 pi, row = theta / pi * H (row 0 is the zenith). Radiance is piecewise
constant per pixel; a pixel is chosen with probability proportional to its luminance times
its solid angle and the direction drawn uniformly in the pixel's solid angle, so sample()
and pdf() are exactly consistent.
"""
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..geometry import LUMINANCE


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
        d, pdf, Li = self.sample_dir(u)
        return d, np.full(len(p), np.inf), Li, pdf


class PointLight:
    delta = True

    def __init__(self, position, intensity):
        self.position = np.asarray(position, float)
        self.intensity = np.asarray(intensity, float)
        self.power = float(4 * np.pi * self.intensity @ LUMINANCE)

    def sample(self, p, u):
        v = self.position - p
        dist = np.linalg.norm(v, axis=1)
        wl = v / dist[:, None]
        return wl, dist, self.intensity[None, :] / (dist * dist)[:, None], np.ones(len(p))


class QuadLight:
    """A one-sided emitting parallelogram corner + s edge1 + t edge2; it emits towards
    edge1 x edge2 with constant radiance."""
    delta = False

    def __init__(self, corner, edge1, edge2, radiance):
        self.corner, self.edge1, self.edge2 = (np.asarray(x, float) for x in (corner, edge1, edge2))
        n = np.cross(self.edge1, self.edge2)
        self.area = float(np.linalg.norm(n))
        if not self.area > 0:
            raise ValueError("quad light has zero area")
        self.normal = n / self.area
        self.radiance = np.asarray(radiance, float)
        self.power = float(np.pi * self.area * self.radiance @ LUMINANCE)

    def sample(self, p, u):
        q = self.corner + u[:, :1] * self.edge1 + u[:, 1:2] * self.edge2
        v = q - p
        dist = np.linalg.norm(v, axis=1)
        wl = v / dist[:, None]
        cos_l = -(wl @ self.normal)
        front = cos_l > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            pdf = np.where(front, dist * dist / (self.area * cos_l), 0.0)
        Li = np.where(front[:, None], self.radiance[None, :], 0.0)
        return wl, dist, Li, pdf

    def eval_hit(self, d):
        """Radiance seen along d when it hits the quad (front side only)."""
        return np.where(((d @ self.normal) < 0)[:, None], self.radiance[None, :], 0.0)

    def pdf_hit(self, d, t):
        cos_l = -(d @ self.normal)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(cos_l > 0, t * t / (self.area * cos_l), 0.0)


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
