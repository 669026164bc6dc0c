"""The baked tables in the texture layout the Cycles OSL shader reads (blender_addon/osl/).

OSL reads data only through `texture()`. The export is one RGB float32 OpenEXR (ZIP,
lossless) whose texels the shader fetches one at a time with `"interp", "closest"` and
zero derivatives, so every value comes back bit-exact. Everything is precomputed the way
`Tables.sample` (the numpy reference) uses it: masses normalized per bin, cumulative row
and column sums in float64 then stored as float32, the outer edges exactly 0, 1 and 0, 2 pi.

Layout (W = texture width, rows from the top of the image; texel (x, y) is read at
s = (x + 0.5) / W, t = (y + 0.5) / H):

    row 0                   header: (LAYOUT, K, R), (C, W, H), (0, 0, 0)
    row 1                   cos(theta_bin k) at x = k (red)
    rows 2 + k R + i        bin k, table row i: cell j at x = j holds W_kij (RGB)
    rows 2 + K R + k R + i  bin k, table row i: cell j holds (mass, alpha, beta)
    pair block p = 0 .. P-1 (P = max(K - 1, 1)), first row 2 + 2 K R + p (2 + 2 R):
        +0          row CDF, x = 0..R
        +1          a edges, x = 0..R
        +2 + i      column cumulative sums of row i, x = 0..C
        +2 + R + i  b edges of row i, x = 0..C
      with red = bin p and green = bin p + 1 (one fetch gives both ends of the lerp;
      a single-bin table stores bin 0 in both).

The file is named after the table file's content hash (`<stem>.osl-<hash12>.exr` next to
the tables) and carries the full hash in its metadata: a changed table gets a new export
file (OpenImageIO caches textures by name, so a rewritten file of the same name could be
served stale inside a running Blender), and older exports of the same tables are removed.

The layout (and the shader) know bins over theta_i only: anisotropic tables get no export
(`ensure_osl_export` raises IsotropicOnly, `bake_derived` logs it), and the Blender node
renders their closure fit, as it does whenever the texture is missing.
"""
import json
from pathlib import Path

import numpy as np

from .errors import FlowBSDFError
from .files import atomic_path, file_hash
from .tables import open_tables

LAYOUT = 1
META_KEY = "flowbsdf_osl"


class IsotropicOnly(FlowBSDFError):
    """The tables are anisotropic (bins over phi_i): the layout has theta bins only."""


def export_path(tables_path, digest):
    tables_path = Path(tables_path)
    return tables_path.with_name(f"{tables_path.stem}.osl-{digest[:12]}.exr")


def texture_image(tables):
    """The (H, W, 3) float32 image of the layout above."""
    if tables.anisotropic:
        raise IsotropicOnly("anisotropic tables have no OSL layout")
    K, R, C = len(tables.theta_bins), tables.rows, tables.cols
    P = max(K - 1, 1)
    width = max(C + 1, R + 1, K, 3)
    height = 2 + 2 * K * R + P * (2 + 2 * R)
    img = np.zeros((height, width, 3), np.float64)
    img[0, 0] = (LAYOUT, K, R)
    img[0, 1] = (C, width, height)
    img[1, :K, 0] = np.cos(tables.theta_bins)
    img[2:2 + K * R, :C] = tables.weights.reshape(K * R, C, 3)
    cells = np.stack([tables._m, tables._alpha, tables._beta], axis=-1)      # (K, R, C, 3)
    img[2 + K * R:2 + 2 * K * R, :C] = cells.reshape(K * R, C, 3)
    for p in range(P):
        base = 2 + 2 * K * R + p * (2 + 2 * R)
        for ch, k in enumerate((p, min(p + 1, K - 1))):
            img[base, :R + 1, ch] = tables._row_cdf[k]
            img[base + 1, :R + 1, ch] = tables._a[k]
            img[base + 2:base + 2 + R, :C + 1, ch] = tables._col_cum[k]
            img[base + 2 + R:base + 2 + 2 * R, :C + 1, ch] = tables._b[k]
    return img.astype(np.float32)


def _write(path, img, meta):
    import OpenEXR
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              META_KEY: json.dumps(meta, sort_keys=True)}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, {"RGB": np.ascontiguousarray(img)}).write(tmp)


def read_export(path):
    """(image (H, W, 3) float32, metadata) of an export file; FlowBSDFError if it is not one."""
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError("OSL texture not found", path)
    import OpenEXR
    try:
        f = OpenEXR.File(str(path))
        raw = f.header().get(META_KEY)
        ch = f.channels()
        img = ch["RGB"].pixels
    except Exception as e:      # noqa: BLE001  (foreign or broken files)
        raise FlowBSDFError(f"not a readable FlowBSDF OSL texture ({e})", path) from None
    if raw is None:
        raise FlowBSDFError("an OpenEXR file, but not a FlowBSDF OSL texture", path)
    return img, json.loads(raw)


def is_current(path, digest):
    try:
        _, meta = read_export(path)
    except FlowBSDFError:
        return False
    return meta.get("tables_hash") == digest and meta.get("layout") == LAYOUT


def ensure_osl_export(tables_path, log=None):
    """The OSL texture of a table file, (re)built when missing, stale or broken; returns its path."""
    tables_path = Path(tables_path)
    if not tables_path.is_file():
        raise FlowBSDFError("table file not found", tables_path)
    digest = file_hash(tables_path)
    path = export_path(tables_path, digest)
    if not is_current(path, digest):
        tables = open_tables(tables_path)
        if tables.anisotropic:
            path = None         # and no older export stays behind
        else:
            _write(path, texture_image(tables),
                   {"layout": LAYOUT, "tables_hash": digest, "tables": tables_path.name,
                    "material": tables.meta.get("material")})
            if log:
                log(f"[osl] wrote {path}")
    for old in tables_path.parent.glob(f"{tables_path.stem}.osl-*.exr"):
        if path is None or old.name != path.name:
            old.unlink(missing_ok=True)
    if path is None:
        raise IsotropicOnly("anisotropic tables: the OSL back end reads isotropic tables only, so there is "
                            "no OSL texture (the Blender node renders the closure fit)", tables_path)
    return path


def bake_derived(tables_path, log=None):
    """What the Blender node needs beside a table file: its OSL texture (None for anisotropic
    tables, see IsotropicOnly) and its closure fit (each rebuilt only when missing or stale).
    Called by the bake pipeline."""
    from .closure_fit import ensure_fit
    try:
        texture = ensure_osl_export(tables_path, log=log)
    except IsotropicOnly as e:
        texture = None
        if log:
            log(f"[osl] none for {Path(tables_path).name}: {e.problem}")
    return texture, ensure_fit(tables_path, log=log)

