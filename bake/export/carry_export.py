"""The carried blend's data (bake/core/carried.py) in the texture layout the Cycles OSL shader reads
(blender_addon/render/osl/carried.h): an isotropic RGL file's warp as a carrying sampler stores it
(RGLMaterial.stored_warp: float16 over each slice's maximum) with the derived sums its warp reads
(rgl._continuous_warp_table: conditional and marginal CDFs, float32 as numpy has them), the
tables' bin angles and which of their intervals carry (tables.meta["carried"]).

One RGBA float32 OpenEXR (ZIP). W = nx + 1, H = 1 + S (ny - 1) for S slices of ny x nx vertices:

    row 0                   header: (CARRY_LAYOUT, S, ny, nx), (W, H, K, 0) with K the tables' bins;
                            x = 2 + s: theta_i of slice s (red); x = 2 + S + k: theta_bin k (red)
                            and whether interval k (bins k, k + 1) carries (green, 1 or 0)
    row 1 + s (ny - 1) + y  slice s, patch row y: x < nx holds the vertices (y, x) and (y + 1, x):
                            (density, conditional CDF, density, conditional CDF); x = nx the
                            marginal CDF at row y (red)

so a patch's nine numbers (rgl._continuous_warp_table) are four fetches a slice: its two columns,
the row's last vertex (the rows' totals) and the marginal. Every value is numpy's float32 bit for
bit. Named after the tables' content hash like the other exports (`<stem>.carry<layout>-<hash12>.exr`).
"""
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..formats import CARRY_LAYOUT
from ..io.exrio import read_rgba_exr, write_rgba_exr

CARRY_SLICES = 16       # carried.h's CARRY_SLICES: the shader reads the slices' angles once, into an array
META_KEY = "flowbsdf_carry"
KIND = "carry"


def carry_image(material, tables, carry):
    """The texture (H, W, 4) float32 of an isotropic RGL material, its tables (joined bins, as the
    OSL texture lays them out) and one flag per interval of the tables' bins."""
    from ..core.carried import check_carriable
    check_carriable(material)
    bins = np.asarray(tables.theta_bins, np.float64)
    carry = np.asarray(carry, bool)
    if carry.shape != (max(len(bins) - 1, 0),):
        raise FlowBSDFError(f"carried: one flag per interval of the tables' {len(bins)} bins, not {carry.shape}")
    S = material._slices
    if S > CARRY_SLICES:
        raise FlowBSDFError(f"the carried blend's texture holds at most {CARRY_SLICES} theta_i slices, the file has {S}")
    ny, nx = material._vndf_shape
    t = material._stored_warp_table().reshape(S, ny - 1, nx - 1, 9)
    W, H = nx + 1, 1 + S * (ny - 1)
    if 2 + S + len(bins) > W:
        raise FlowBSDFError(f"the carried blend's texture holds at most {W - 2 - S} bins, the tables have {len(bins)}")
    img = np.zeros((H, W, 4))
    img[0, 0] = (CARRY_LAYOUT, S, ny, nx)
    img[0, 1] = (W, H, len(bins), 0)
    img[0, 2:2 + S, 0] = material.theta_i
    img[0, 2 + S:2 + S + len(bins), 0] = bins
    img[0, 2 + S:2 + S + len(carry), 1] = carry
    rows = img[1:].reshape(S, ny - 1, W, 4)
    rows[:, :, :nx - 1, 0] = t[..., 0]          # density at (y, x)
    rows[:, :, nx - 1, 0] = t[:, :, -1, 1]      # ... the row's last vertex
    rows[:, :, :nx - 1, 1] = t[..., 4]          # conditional CDF at (y, x)
    rows[:, :, nx - 1, 1] = t[:, :, -1, 6]      # ... the row's total
    rows[:, :, :nx - 1, 2] = t[..., 2]          # (y + 1, x)
    rows[:, :, nx - 1, 2] = t[:, :, -1, 3]
    rows[:, :, :nx - 1, 3] = t[..., 5]
    rows[:, :, nx - 1, 3] = t[:, :, -1, 7]
    rows[:, :, nx, 0] = t[:, :, 0, 8]           # marginal CDF at row y
    out = img.astype(np.float32)
    if not np.array_equal(out[1:].reshape(S, ny - 1, W, 4)[:, :, :nx - 1, :2].astype(np.float64), t[..., [0, 4]]):
        raise FlowBSDFError("the warp's table is not float32-exact (rgl._continuous_warp_table changed?)")
    return out


def path(tables_path, digest):
    """<stem>.carry<CARRY_LAYOUT>-<hash12>.exr beside the tables."""
    tables_path = Path(tables_path)
    return tables_path.with_name(f"{tables_path.stem}.carry{CARRY_LAYOUT}-{digest[:12]}.exr")


def read(path):
    """(image (H, W, 4) float32, metadata) of a carry texture; FlowBSDFError if it is not one."""
    return read_rgba_exr(path, META_KEY, "carry texture")


def is_current(path, digest):
    try:
        _, meta = read(path)
    except FlowBSDFError:
        return False
    return meta.get("tables_hash") == digest and meta.get("layout") == CARRY_LAYOUT


def write_carry_export(path, material, tables, carry, digest):
    write_rgba_exr(path, carry_image(material, tables, carry), META_KEY,
                   {"layout": CARRY_LAYOUT, "tables_hash": digest, "material": material.fingerprint()})


def write(path, tables_path, tables, digest, material=None):
    """The texture of tables whose meta says which intervals carry, made from `material` (the file
    the tables were baked from)."""
    write_carry_export(path, material, tables, tables.meta["carried"], digest)
