"""MERL BRDF files (Matusik et al. 2003): reading, evaluating, and writing.

File format (little-endian): 3 int32 (90, 90, 180), then float64 blocks R, G, B of
90 * 90 * 180 values each. Within a block the index is
    (i_theta_h * 90 + i_theta_d) * 180 + i_phi_d,
over the half/difference angles of Rusinkiewicz (the difference vector is wi expressed
in the frame of the half vector h, after turning h to phi_h = 0):
    theta_h in [0, pi/2]:  i = floor(sqrt(theta_h / (pi/2)) * 90)   (sqrt-mapped: fine near 0)
    theta_d in [0, pi/2]:  j = floor(theta_d / (pi/2) * 90)         (1 degree bins)
    phi_d   in [0, pi):    k = floor(phi_d / pi * 180)              (1 degree bins; by
                           reciprocity phi_d and phi_d + pi give the same value, so phi_d
                           is taken modulo pi)
each clamped to the table. Stored values times (1/1500, 1.15/1500, 1.66/1500) (R, G, B) are f
(no cosine). Negative stored values mean "invalid" (not measured, e.g. below the horizon).

Choices made here:
  - Lookup: `MERLMaterial(path)` uses the reference's nearest-bin lookup (lookup="nearest"),
    so evaluation is exactly the data, bin for bin, as in every MERL reader. lookup="linear"
    interpolates trilinearly between bin centres instead (phi_d periodic with period pi,
    theta_h and theta_d clamped at the table ends) for a continuous f.
  - Invalid entries: a negative value reads as f = 0 for that channel (no energy where
    nothing was measured). With lookup="linear", invalid neighbours are left out and the
    weights of the valid ones renormalized; f = 0 only when all 8 neighbours are invalid.
  - `write_merl` tabulates an isotropic Material at the bin *centres* (index + 1/2 in each
    mapped coordinate), which the nearest lookup maps back to the same bin, and stores
    -1 (invalid) in bins whose centre has wi or wo below the horizon.
"""
import hashlib
import os
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..maths.geometry import atan2
from .base import Material, as_dirs

RES_THETA_H, RES_THETA_D, RES_PHI_D = 90, 90, 180
DIMS = (RES_THETA_H, RES_THETA_D, RES_PHI_D)
N_BINS = RES_THETA_H * RES_THETA_D * RES_PHI_D
SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
HEADER_BYTES = 3 * 4
FILE_BYTES = HEADER_BYTES + 3 * N_BINS * 8
INVALID = -1.0


# --------------------------------------------------------------------------- coordinates

def half_diff(wi, wo):
    """(theta_h, theta_d, phi_d) of direction pairs (N,3); phi_d in (-pi, pi].

    h = normalize(wi + wo); d = wi turned by -phi_h about the normal, then by -theta_h about
    the y axis (so that h becomes the pole).
    """
    wi, wo = as_dirs(wi, wo)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    r = np.hypot(h[:, 0], h[:, 1])
    theta_h = atan2(r, h[:, 2])
    # cos/sin of phi_h, and of theta_h, without trigonometry.
    has_r = r > 0
    safe_r = np.where(has_r, r, 1.0)
    c = np.where(has_r, h[:, 0] / safe_r, 1.0)
    s = np.where(has_r, h[:, 1] / safe_r, 0.0)
    x1 = c * wi[:, 0] + s * wi[:, 1]
    y1 = -s * wi[:, 0] + c * wi[:, 1]
    z1 = wi[:, 2]
    ct, st = h[:, 2], r
    x2 = x1 * ct - z1 * st
    z2 = x1 * st + z1 * ct
    theta_d = atan2(np.hypot(x2, y1), z2)
    phi_d = atan2(y1, x2)
    return theta_h, theta_d, phi_d


def half_diff_to_dirs(theta_h, theta_d, phi_d):
    """The (wi, wo) pair with the given angles and phi_h = 0 (inverse of `half_diff`)."""
    theta_h, theta_d, phi_d = np.broadcast_arrays(*(np.asarray(a, float) for a in (theta_h, theta_d, phi_d)))
    sd = np.sin(theta_d)
    dx, dy, dz = sd * np.cos(phi_d), sd * np.sin(phi_d), np.cos(theta_d)
    ch, sh = np.cos(theta_h), np.sin(theta_h)
    wi = np.stack([dx * ch + dz * sh, dy, -dx * sh + dz * ch], axis=-1)
    wo = np.stack([-dx * ch + dz * sh, -dy, dx * sh + dz * ch], axis=-1)
    return wi, wo


def _u_theta_h(theta_h):
    """The sqrt-mapped continuous theta_h coordinate, in bins: sqrt(theta_h / (pi/2)) * 90."""
    return np.sqrt(np.maximum(theta_h, 0.0) / (0.5 * np.pi)) * RES_THETA_H


def _u_theta_d(theta_d):
    return theta_d / (0.5 * np.pi) * RES_THETA_D


def _u_phi_d(phi_d):
    """phi_d folded into [0, pi) (reciprocity), in bins."""
    return np.mod(phi_d, np.pi) / np.pi * RES_PHI_D


def bin_index(theta_h, theta_d, phi_d):
    """The reference's nearest-bin indices (i_theta_h, i_theta_d, i_phi_d), clamped to the table."""
    i = np.clip(np.floor(_u_theta_h(theta_h)).astype(np.int64), 0, RES_THETA_H - 1)
    j = np.clip(np.floor(_u_theta_d(theta_d)).astype(np.int64), 0, RES_THETA_D - 1)
    k = np.clip(np.floor(_u_phi_d(phi_d)).astype(np.int64), 0, RES_PHI_D - 1)
    return i, j, k


def bin_centres():
    """Angles of the bin centres: theta_h (90,), theta_d (90,), phi_d (180,)."""
    theta_h = ((np.arange(RES_THETA_H) + 0.5) / RES_THETA_H) ** 2 * (0.5 * np.pi)
    theta_d = (np.arange(RES_THETA_D) + 0.5) / RES_THETA_D * (0.5 * np.pi)
    phi_d = (np.arange(RES_PHI_D) + 0.5) / RES_PHI_D * np.pi
    return theta_h, theta_d, phi_d


# --------------------------------------------------------------------------- reading

def read_merl(path):
    """The raw (unscaled) table of a MERL file, float64 (3, 90, 90, 180), checked strictly."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise FlowBSDFError(f"cannot read MERL file: {e.strerror or e}", path) from None
    return _parse(data, path), data


def _parse(data, path):
    if len(data) < HEADER_BYTES:
        raise FlowBSDFError(f"not a MERL file: {len(data)} bytes, shorter than the 12-byte header", path)
    dims = tuple(int(d) for d in np.frombuffer(data, dtype="<i4", count=3))
    if dims != DIMS:
        raise FlowBSDFError(f"not a MERL BRDF: header dimensions {dims}, expected {DIMS}", path)
    if len(data) != FILE_BYTES:
        what = "truncated" if len(data) < FILE_BYTES else "has trailing bytes"
        raise FlowBSDFError(f"MERL file {what}: {len(data)} bytes, expected {FILE_BYTES}", path)
    table = np.frombuffer(data, dtype="<f8", offset=HEADER_BYTES).astype(np.float64).reshape((3,) + DIMS)
    bad = ~np.isfinite(table)
    if bad.any():
        c, i, j, k = np.argwhere(bad)[0]
        kind = "NaN" if np.isnan(table[c, i, j, k]) else "infinite"
        raise FlowBSDFError(f"MERL data holds {int(bad.sum())} non-finite values (first: {kind} in channel "
                            f"{'RGB'[c]} at theta_h/theta_d/phi_d bin ({i}, {j}, {k}))", path)
    return table


class MERLMaterial(Material):
    """A MERL BRDF (isotropic). name = file stem; fingerprint = sha256 of the file's bytes."""

    LOOKUPS = ("nearest", "linear")

    def __init__(self, path, lookup="nearest"):
        if lookup not in self.LOOKUPS:
            raise FlowBSDFError(f"MERL lookup must be one of {list(self.LOOKUPS)}, not {lookup!r}")
        self.path = Path(path)
        raw, data = read_merl(self.path)
        self.name = self.path.stem
        self.isotropic = True
        self.lookup = lookup
        self._sha256 = hashlib.sha256(data).hexdigest()
        # Rows in file order, RGB columns; invalid (negative) entries read as 0.
        flat = raw.reshape(3, N_BINS).T
        self._valid = flat >= 0.0
        self._values = np.where(self._valid, flat, 0.0) * SCALE
        self.invalid_fraction = float(1.0 - self._valid.mean())

    def fingerprint(self):
        if self.lookup == "nearest":
            return self._sha256
        return hashlib.sha256(f"{self._sha256}:{self.lookup}".encode()).hexdigest()

    def table(self):
        """The scaled table f (RGB, invalid entries as 0), shape (3, 90, 90, 180)."""
        return self._values.T.reshape((3,) + DIMS)

    def eval(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        out = np.zeros((len(wo), 3))
        ok = (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
        if np.any(ok):
            th, td, pd = half_diff(wi[ok], wo[ok])
            out[ok] = self._nearest(th, td, pd) if self.lookup == "nearest" else self._linear(th, td, pd)
        return out

    def _nearest(self, th, td, pd):
        i, j, k = bin_index(th, td, pd)
        return self._values[(i * RES_THETA_D + j) * RES_PHI_D + k]

    def _linear(self, th, td, pd):
        # Continuous coordinates with sample points at the bin centres (integers here).
        coords = [(np.clip(_u_theta_h(th) - 0.5, 0.0, RES_THETA_H - 1), RES_THETA_H, False),
                  (np.clip(_u_theta_d(td) - 0.5, 0.0, RES_THETA_D - 1), RES_THETA_D, False),
                  (_u_phi_d(pd) - 0.5, RES_PHI_D, True)]
        corners = []
        for u, n, periodic in coords:
            lo = np.floor(u)
            t = u - lo
            lo = lo.astype(np.int64)
            if periodic:
                a, b = np.mod(lo, n), np.mod(lo + 1, n)
            else:
                a, b = np.clip(lo, 0, n - 1), np.clip(lo + 1, 0, n - 1)
            corners.append(((a, 1.0 - t), (b, t)))
        num = np.zeros((len(th), 3))
        den = np.zeros((len(th), 3))
        for i, wi_ in corners[0]:
            for j, wj in corners[1]:
                for k, wk in corners[2]:
                    row = (i * RES_THETA_D + j) * RES_PHI_D + k
                    w = (wi_ * wj * wk)[:, None] * self._valid[row]
                    num += w * self._values[row]
                    den += w
        return np.where(den > 0.0, num / np.where(den > 0.0, den, 1.0), 0.0)


# --------------------------------------------------------------------------- writing

def tabulate(material):
    """The raw MERL table (3, 90, 90, 180) of an isotropic Material, sampled at the bin centres."""
    if not isinstance(material, Material):
        raise FlowBSDFError(f"write_merl needs a Material, not {type(material).__name__}")
    if not material.isotropic:
        raise FlowBSDFError(f"material {material.name!r} is anisotropic; a MERL file can only hold an "
                            "isotropic BRDF")
    theta_h, theta_d, phi_d = bin_centres()
    TD, PD = np.meshgrid(theta_d, phi_d, indexing="ij")
    table = np.empty((3,) + DIMS)
    for i, th in enumerate(theta_h):
        wi, wo = half_diff_to_dirs(th, TD.ravel(), PD.ravel())
        f = np.asarray(material.eval(wi, wo), dtype=np.float64)
        if not np.all(np.isfinite(f)):
            raise FlowBSDFError(f"material {material.name!r} returned non-finite values (theta_h = "
                                f"{np.degrees(th):.3f} deg)")
        raw = f / SCALE
        raw[(wi[:, 2] <= 0.0) | (wo[:, 2] <= 0.0)] = INVALID
        table[:, i] = raw.T.reshape(3, RES_THETA_D, RES_PHI_D)
    return table


def write_merl(path, material):
    """Tabulate an isotropic Material into a MERL file (see the module docstring)."""
    path = Path(path)
    table = tabulate(material)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(np.array(DIMS, dtype="<i4").tobytes())
            fh.write(np.ascontiguousarray(table, dtype="<f8").tobytes())
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise FlowBSDFError(f"cannot write MERL file: {e.strerror or e}", path) from None
    return path


__all__ = ["MERLMaterial", "write_merl", "read_merl", "tabulate", "half_diff", "half_diff_to_dirs",
           "bin_index", "bin_centres", "SCALE", "DIMS"]
