"""Image files and image metrics: RGB EXR in/out, PNG out (zlib, no extra packages),
tone mapping, false-colour error maps, MSE / MAE / SSIM."""
import struct
import zlib
from pathlib import Path

import numpy as np

from ..io.files import atomic_path
from ..maths.geometry import LUMINANCE


def _atomic(path, write):
    with atomic_path(path) as tmp:
        write(tmp)


def write_exr(path, image, header=None):
    """(H, W, 3) float32 RGB, ZIP compressed; header: extra string attributes."""
    import OpenEXR
    img = np.ascontiguousarray(image, dtype=np.float32)
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    hdr.update({k: str(v) for k, v in (header or {}).items()})
    _atomic(path, lambda tmp: OpenEXR.File(hdr, {"RGB": img}).write(tmp))


def read_exr(path):
    from .lights import read_image
    return read_image(path, allow_negative=True)


def tonemap(image, exposure=1.0):
    """Linear RGB -> sRGB 8 bit (clipped)."""
    x = np.clip(np.asarray(image, float) * exposure, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (s * 255 + 0.5).astype(np.uint8)


def write_png(path, rgb8):
    rgb8 = np.ascontiguousarray(rgb8, dtype=np.uint8)
    H, W = rgb8.shape[:2]
    raw = b"".join(b"\x00" + rgb8[y].tobytes() for y in range(H))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 2, 0, 0, 0)) \
        + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    _atomic(path, lambda tmp: Path(tmp).write_bytes(png))


# A perceptual ramp (approximately viridis) for error maps, 0 -> 1.
_RAMP = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float) / 255


def false_colour(x, vmax):
    """Scalar map -> RGB8 on the ramp, 0..vmax (clipped)."""
    t = np.clip(np.asarray(x, float) / max(vmax, 1e-300), 0.0, 1.0) * (len(_RAMP) - 1)
    i = np.minimum(t.astype(int), len(_RAMP) - 2)
    f = (t - i)[..., None]
    return ((_RAMP[i] * (1 - f) + _RAMP[i + 1] * f) * 255 + 0.5).astype(np.uint8)


def mse(a, b):
    return float(np.mean((np.asarray(a, float) - b) ** 2))


def mae(a, b):
    return float(np.mean(np.abs(np.asarray(a, float) - b)))


def _box(x, r):
    """Mean over (2r+1)² windows, valid region only."""
    c = np.cumsum(np.cumsum(np.pad(x, ((1, 0), (1, 0))), axis=0), axis=1)
    k = 2 * r + 1
    return (c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]) / (k * k)


def ssim(a, b, r=3):
    """Mean SSIM of the tone-mapped luminance (values in [0, 1]) over 7x7 windows."""
    x = tonemap(a).astype(float) @ LUMINANCE / 255
    y = tonemap(b).astype(float) @ LUMINANCE / 255
    if min(x.shape) < 2 * r + 1:
        r = max(0, (min(x.shape) - 1) // 2)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mx, my = _box(x, r), _box(y, r)
    vx = _box(x * x, r) - mx * mx
    vy = _box(y * y, r) - my * my
    cxy = _box(x * y, r) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(np.mean(s))

