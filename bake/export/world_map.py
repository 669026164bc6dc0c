"""The world's importance map: where the Cycles back ends sample the world (numpy only).

The add-on renders the scene's world, whatever its nodes, into an equirectangular radiance
image (blender_addon/world.py) and hands it here. A pixel is chosen with probability
proportional to its luminance times its solid angle, the direction uniformly within the
pixel's solid angle: the pdf per steradian is then constant over a pixel, and `pdf(d)` reads
it back, so sampling and density are exactly consistent. Only the density matters for
correctness: the shaders weight a world-map direction by the mixture's pdf and let Cycles
find the true radiance along it, so a blurred or noisy map costs variance, never bias.

Blender's equirectangular convention (as the reference tracer's Environment): column u =
0.5 - atan2(y, x) / 2 pi, row = theta / pi * H (row 0 the zenith, +z).

The CDF is flattened over the H x W pixels (row-major) and rounded to float32 first, as the
shader reads it; each pixel's pdf is recomputed from the rounded CDF, so a pixel whose
probability rounds to nothing has pdf 0 and is never drawn (no mismatch between the two).

Texture layout (float32 RGBA OpenEXR, ZIP; texel (x, y) read at ((x + 0.5) / Wt, (y + 0.5) / Ht),
"closest"), read by blender_addon/osl/world.h:
    row 0                       (LAYOUT, W, H), (G, first CDF row, first pdf row),
                                (first guide row, 0, 0)
    CDF rows                    entry k = 0 .. W H at x = k mod Wt, row + k div Wt (red)
    pdf rows                    pixel (row, col) at x = col, pdf row + row (red), per steradian
    guide rows                  g = 0 .. G - 1 at x = g mod Wt, row + g div Wt: (lo, hi) with
                                lo <= k < hi for the k with cdf_k <= u < cdf_k+1, u in [g, g + 1) / G
"""
import json
from pathlib import Path

import numpy as np

from ..core.geometry import LUMINANCE
from ..errors import FlowBSDFError
from ..plumbing.exrio import write_rgba_exr

LAYOUT = 1
TEXTURE_WIDTH = 1024
GUIDES = 4096
META_KEY = "flowbsdf_world"


class WorldMap:
    """Importance sampling of an equirectangular radiance image (H, W, 3): sample(u) and pdf(d)."""

    def __init__(self, radiance):
        radiance = np.asarray(radiance, np.float64)
        if radiance.ndim != 3 or radiance.shape[2] < 3 or min(radiance.shape[:2]) < 1:
            raise FlowBSDFError(f"world radiance must be an (H, W, 3) image, not {radiance.shape}")
        if not np.all(np.isfinite(radiance[..., :3])):
            raise FlowBSDFError("world radiance holds NaN or inf")
        self.H, self.W = radiance.shape[:2]
        self.z_edges = np.cos(np.linspace(0.0, np.pi, self.H + 1))
        omega = (self.z_edges[:-1] - self.z_edges[1:]) * (2.0 * np.pi / self.W)
        power = (np.maximum(radiance[..., :3] @ LUMINANCE, 0.0) * omega[:, None]).ravel()
        total = power.sum()
        if total <= 0:
            raise FlowBSDFError("the world is black: nothing to importance-sample")
        cdf = np.concatenate([[0.0], np.cumsum(power) / total])
        cdf[-1] = 1.0
        self.cdf = cdf.astype(np.float32).astype(np.float64)
        self.pdf_pixel = (np.diff(self.cdf).reshape(self.H, self.W) / omega[:, None])
        # how unevenly the world's light is spread: 1 for a constant world (from the float64
        # shares: the float32 CDF's rounding makes tiny pixels' densities coarse)
        self.peak = float((power.reshape(self.H, self.W) / omega[:, None]).max() / total * 4.0 * np.pi)

    def _pixel(self, d):
        theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
        u = 0.5 - np.arctan2(d[:, 1], d[:, 0]) / (2.0 * np.pi)
        u -= np.floor(u)
        row = np.clip((theta / np.pi * self.H).astype(np.int64), 0, self.H - 1)
        col = np.clip((u * self.W).astype(np.int64), 0, self.W - 1)
        return row, col

    def pdf(self, d):
        row, col = self._pixel(np.atleast_2d(d))
        return self.pdf_pixel[row, col]

    def sample(self, u):
        """Directions (N, 3) for u (N, 2) in [0, 1)^2, and their pdf per steradian."""
        u = np.atleast_2d(np.asarray(u, np.float64))
        k = np.clip(np.searchsorted(self.cdf, u[:, 0], side="right") - 1, 0, self.H * self.W - 1)
        row, col = np.divmod(k, self.W)
        z = self.z_edges[row] + u[:, 1] * (self.z_edges[row + 1] - self.z_edges[row])
        lo, hi = self.cdf[k], self.cdf[k + 1]
        t = np.clip((u[:, 0] - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0, 1.0)
        phi = (0.5 - (col + t) / self.W) * 2.0 * np.pi
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1), self.pdf_pixel[row, col]

    def guides(self, count=GUIDES):
        """(count, 2) brackets [lo, hi) of the sampled pixel index for u0 in [g, g + 1) / count."""
        g = np.arange(count)
        n = self.H * self.W
        lo = np.clip(np.searchsorted(self.cdf, g / count, side="right") - 1, 0, n - 1)
        hi = np.clip(np.searchsorted(self.cdf, (g + 1) / count, side="left"), lo + 1, n)
        return np.stack([lo, hi], axis=1).astype(np.float64)

    def texture_image(self):
        """The (Ht, Wt, 4) float32 image of the layout above."""
        n = self.H * self.W
        wt = max(TEXTURE_WIDTH, self.W, 3)
        rows = lambda count: -(-count // wt)       # noqa: E731
        r_cdf = 1
        r_pdf = r_cdf + rows(n + 1)
        r_guide = r_pdf + self.H
        height = r_guide + rows(GUIDES)
        img = np.zeros((height, wt, 4), np.float64)
        img[0, 0, :3] = (LAYOUT, self.W, self.H)
        img[0, 1, :3] = (GUIDES, r_cdf, r_pdf)
        img[0, 2, :3] = (r_guide, 0, 0)
        k = np.arange(n + 1)
        img[r_cdf + k // wt, k % wt, 0] = self.cdf
        img[r_pdf:r_pdf + self.H, :self.W, 0] = self.pdf_pixel
        g = np.arange(GUIDES)
        img[r_guide + g // wt, g % wt, :2] = self.guides()
        return img.astype(np.float32)


def write_world_texture(path, world_map, meta=None):
    """Write the world map's texture (atomically); returns the path."""
    write_rgba_exr(path, world_map.texture_image(), META_KEY, {"layout": LAYOUT, **(meta or {})})
    return Path(path)


def read_world_meta(path):
    """The metadata of a world texture, or None when the file is not a current one."""
    if not Path(path).is_file():
        return None
    try:
        import OpenEXR
        raw = OpenEXR.File(str(path)).header().get(META_KEY)
        meta = json.loads(raw) if raw else None
    except Exception:       # noqa: BLE001  (missing, foreign or broken files)
        return None
    return meta if meta and meta.get("layout") == LAYOUT else None
