"""The world's importance map: where the Cycles back ends sample the world (numpy only).

The add-on renders the scene's world, whatever its nodes, into an equirectangular radiance
image (blender_addon/render/world.py) and hands it here. A pixel is chosen with probability
proportional to its luminance times its solid angle, the direction uniformly within the
pixel's solid angle: the pdf per steradian is then constant over a pixel, and `pdf(d)` reads
it back, so sampling and density are exactly consistent. Only the density matters for
correctness: the shaders weight a world-map direction by the mixture's pdf and let Cycles
find the true radiance along it, so a blurred or noisy map costs variance, never bias.

Blender's equirectangular convention (as the reference tracer's Environment): column u =
0.5 - atan2(y, x) / 2 pi, row = theta / pi * H (row 0 the zenith, +z).

A pixel is drawn in two steps, as Cycles draws its own world map: its row by the rows'
marginal CDF (u0), then its column by that row's conditional CDF (u1); the leftover of u0 places
the direction's z within the row, that of u1 its azimuth within the pixel. A pixel's 2D
neighbours stay neighbours in u, so stratified u stays stratified over the map (measured, numpy,
a Lambertian under the "sunny" HDRI, 64 (0,2)-sequence samples per estimate: next-event
variance 3-11x below a CDF flattened over all pixels, row by row).

The CDFs are rounded to float32 first, as the shaders read them; each pixel's pdf is
recomputed from the rounded CDFs, so a pixel whose probability rounds to nothing has pdf 0 and
is never drawn (no mismatch between the two).

Texture layout (float32 RGBA OpenEXR, ZIP; texel (x, y) read at ((x + 0.5) / Wt, (y + 0.5) / Ht),
"closest"; Wt > W, H), read by blender_addon/render/osl/world.h and blender_addon/render/svm/world.py:
    row 0                       (LAYOUT, W, H)
    row 1                       the rows' marginal CDF: entry r = 0 .. H at x = r (red); guide x
                                = 0 .. Wt - 1 (green, blue): lo <= r < hi for the r with
                                cdf_r <= u < cdf_r+1, u in [x, x + 1) / Wt
    rows 2 .. H + 1             map row i at row 2 + i: its conditional CDF, entry c = 0 .. W at
                                x = c (red), its pixels' pdf per steradian at x = c < W (green),
                                its guide x = 0 .. Wt - 1 (blue, alpha) as the marginal's
The guides let the OSL shader search a bracket of ~1 entry in place of log2 of the row or
column count (a texture fetch each: the searches' 21 fetches for a 2048 x 1024 map doubled the
shader's time per sample); the SVM graph's branchless searches ignore them.
"""
import json
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..formats import WORLD_LAYOUT
from ..io.exrio import write_rgba_exr
from ..maths.geometry import LUMINANCE

LAYOUT = WORLD_LAYOUT   # bake/formats.py
TEXTURE_WIDTH = 1024
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
        power = np.maximum(radiance[..., :3] @ LUMINANCE, 0.0) * omega[:, None]
        total = power.sum()
        if total <= 0:
            raise FlowBSDFError("the world is black: nothing to importance-sample")
        rows = power.sum(1)
        self.marginal = _cdf32(rows)
        self.conditional = _cdf32(power)
        self.pdf_pixel = (np.diff(self.marginal)[:, None] * np.diff(self.conditional, axis=1) / omega[:, None])
        # how unevenly the world's light is spread: 1 for a constant world (from the float64
        # shares: the float32 CDFs' rounding makes tiny pixels' densities coarse)
        self.peak = float((power / omega[:, None]).max() / total * 4.0 * np.pi)

    def light_direction(self, density):
        """The unit mean direction of the pixels whose density is `density` (per steradian) or
        more, weighted by their power: where a small sun is (None without such pixels)."""
        bright = self.pdf_pixel >= density
        if not bright.any():
            return None
        z = 0.5 * (self.z_edges[:-1] + self.z_edges[1:])[:, None]
        phi = (0.5 - (np.arange(self.W) + 0.5) / self.W)[None, :] * 2.0 * np.pi
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        w = np.where(bright, np.diff(self.marginal)[:, None] * np.diff(self.conditional, axis=1), 0.0)
        d = np.array([(w * s * np.cos(phi)).sum(), (w * s * np.sin(phi)).sum(), (w * z).sum()])
        return d / np.linalg.norm(d)

    def bright_only(self, radiance, density):
        """The map of `radiance` (this map's image) with every pixel whose density here is below
        `density` (per steradian) black: where the OSL shader's next-event estimation of a small
        sun draws from. Same size, so its pixels are this map's."""
        bright = self.pdf_pixel >= density
        return WorldMap(np.where(bright[..., None], np.asarray(radiance, np.float64)[..., :3], 0.0))

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

    def sample_pixel(self, u):
        """(row, col, t_row, t_col) for u (N, 2): the pixel and the leftovers of u0 and u1 in it."""
        u = np.atleast_2d(np.asarray(u, np.float64))
        row = np.clip(np.searchsorted(self.marginal, u[:, 0], side="right") - 1, 0, self.H - 1)
        # every row's CDF lifted by its index: one sorted array, one search for all samples
        lifted = (self.conditional + np.arange(self.H)[:, None]).ravel()
        k = np.searchsorted(lifted, u[:, 1] + row, side="right") - 1
        col = np.clip(k - row * (self.W + 1), 0, self.W - 1)
        cdf = self.conditional[row]
        i = np.arange(len(row))
        return row, col, _leftover(u[:, 0], self.marginal[row], self.marginal[row + 1]), \
            _leftover(u[:, 1], cdf[i, col], cdf[i, col + 1])

    def sample(self, u):
        """Directions (N, 3) for u (N, 2) in [0, 1)^2, and their pdf per steradian."""
        row, col, t_row, t_col = self.sample_pixel(u)
        z = self.z_edges[row] + t_row * (self.z_edges[row + 1] - self.z_edges[row])
        phi = (0.5 - (col + t_col) / self.W) * 2.0 * np.pi
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1), self.pdf_pixel[row, col]

    def texture_image(self):
        """The (Ht, Wt, 4) float32 image of the layout above."""
        wt = max(TEXTURE_WIDTH, self.W + 1, self.H + 1)
        img = np.zeros((2 + self.H, wt, 4), np.float64)
        img[0, 0, :3] = (LAYOUT, self.W, self.H)
        img[1, :self.H + 1, 0] = self.marginal
        img[1, :, 1:3] = _guides(self.marginal, wt)
        img[2:, :self.W + 1, 0] = self.conditional
        img[2:, :self.W, 1] = self.pdf_pixel
        img[2:, :, 2:4] = np.stack([_guides(cdf, wt) for cdf in self.conditional])
        return img.astype(np.float32)


def _cdf32(weights):
    """The CDFs of weights along the last axis (a 0 first, 1 last; uniform where the weights sum
    to 0: never drawn), rounded to float32 as the shaders read them."""
    weights = np.asarray(weights, np.float64)
    total = weights.sum(-1, keepdims=True)
    cum = np.cumsum(weights, -1) / np.where(total > 0, total, 1.0)
    uniform = np.broadcast_to(np.arange(1, weights.shape[-1] + 1) / weights.shape[-1], cum.shape)
    cum = np.where(total > 0, cum, uniform)
    cdf = np.concatenate([np.zeros(cum.shape[:-1] + (1,)), cum], -1)
    cdf[..., -1] = 1.0
    return cdf.astype(np.float32).astype(np.float64)


def _guides(cdf, count):
    """(count, 2) brackets [lo, hi) of the entry k < n (cdf's entries 0 .. n, the last 1) with
    cdf_k <= u < cdf_k+1, for u in [g, g + 1) / count: the last k with cdf_k <= g / count, the
    first k with cdf_k >= (g + 1) / count (float32 u rounds up to it at most)."""
    g = np.arange(count)
    n = len(cdf) - 1
    lo = np.clip(np.searchsorted(cdf, g / count, side="right") - 1, 0, n - 1)
    hi = np.clip(np.searchsorted(cdf, (g + 1) / count, side="left"), lo + 1, n)
    return np.stack([lo, hi], axis=1).astype(np.float64)


def _leftover(u, lo, hi):
    return np.clip((u - lo) / np.where(hi > lo, hi - lo, 1.0), 0.0, 1.0)


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
