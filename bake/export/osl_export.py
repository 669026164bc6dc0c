"""The baked tables in the texture layout the Cycles OSL shader reads (blender_addon/render/osl/).

OSL reads data only through `texture()`. The export is one RGBA float32 OpenEXR (ZIP,
lossless) whose texels the shader fetches one at a time with `"interp", "closest"` and
zero derivatives, so every value comes back bit-exact. Everything is precomputed the way
`Tables.sample` (the numpy reference) uses it: masses normalized per bin, cumulative row
and column sums in float64 then stored as float32, the outer edges exactly 0, 1 and 0, 2 pi.

Bins: K over theta_i, times P over phi_i for anisotropic tables (P = 1 isotropic), bin
b = k P + p as in Tables. R x C is the largest bin's table: the bins of MixedTables (layout
groups of their own resolutions) are its padded working copies (PAD past a bin's own R_b + 1
edges and cumulative sums, masses and weights 0, profile nodes 1), laid out as one table of
R x C cells each, and the shader reads only a bin's own entries (the guides and the count texel
below bound its searches). Layout (W = texture width, rows from the top of the image; texel
(x, y) is read at s = (x + 0.5) / W, t = (y + 0.5) / H):

    row 0                   header: (LAYOUT, K, R, C), (P, phi period, the coordinates (their
                            index in tables.COORDS: 0 wo, 1 halfvector, 2 halfpolar), their
                            frame's angle); the shader checks the texture's size against them.
                            The same eight numbers are the file's header attributes HEADER (ints,
                            and float32 period and angle): the shader reads those, by
                            gettextureinfo(), which OSL answers once when it compiles the shader
                            (a texture() call costs at every shading point)
    row 1                   cos(theta_bin k) at x = k (red); phi_bin p at x = p (green)
    row 2                   theta guide: at x = g < W, (lo, hi) brackets k for cos theta_i in
                            [g / W, (g + 1) / W), then cos(theta_bin k), cos(theta_bin k + 1) for
                            k = min(lo, K - 2) (what the shader needs when hi = lo + 1)
    rows 3 + 3 (i B + b) + q, q = 0, 1, 2
                            bin b, table row i: cell j at x = j holds (mass, a0, a1, a2), (a3,
                            b0, b1, b2), (b3, W_bij): the mass, the profiles' node values along a
                            and b (Tables._alpha, _beta: normalized per bin) and the weight (RGB),
                            three RGBA texels a cell, one above the other, the bins of a table
                            row next to each other (what a blend reads shares an OIIO tile)
    corner block (k, p), k = 0 .. max(K - 1, 1) - 1, first row 3 + 3 B R + (k P + p)(3 + 3 R):
        +0          row CDF, x = 0..R
        +1          a edges, x = 0..R
        +2          row guide: at x = g < G_R = R, (lo, hi) brackets the row for u0 in [g, g + 1) / R
                    (red, green), and the row of a = 1 - cos theta_o in [g, g + 1) / R among the
                    a edges (blue, alpha: the inverse's search, eval_tables); at x = R the count
                    texel (R_b, C_b): the corner's own rows and columns (edge_search's fallback)
        +3 + 3 i    column cumulative sums of row i, x = 0..C
        +4 + 3 i    b edges of row i, x = 0..C
        +5 + 3 i    column guide of row i < R_b: at x = g < G_C = C, (lo, hi) brackets the column
                    for u1 in [g, g + 1) / C (red, green), and the column of b in [g, g + 1) 2 pi / C
                    among the row's b edges (blue, alpha)
                    (a table row's three rows together: a sample's column search stays in a tile)
      with the four bins a sample blends in its channels: red (k, p), green (k + 1, p), blue
      (k, p + 1), alpha (k + 1, p + 1) (p + 1 wrapping to 0; k + 1 clipped to K - 1), so one
      fetch gives all four ends of the blend. Isotropic tables (P = 1, where blue and alpha would
      repeat red and green, blended with weight 0) put the next rows' values there instead: the
      row CDF's texels carry the a edges (of +1) and the column sums' the b edges (of +2 + R + i),
      so a sample's searches read the edges with the sums. A guide's bracket holds for any blend of the four
      (for every bin: its value at lo is below the fraction, at hi above it), so the shader's
      binary searches start from it: one fetch instead of log2(R) or log2(C). Guides come from
      the corner's own entries (own_size), so lo < hi <= R_b (C_b): a search, and the entries
      it reads at lo and lo + 1, stay within them. (The corner at the boundary of two layout
      groups, two bins at one angle that are never blended, may join bins of two sizes: it is
      read within the smaller's.)

The file is named after the table file's content hash (`<stem>.osl-<hash12>.exr` next to
the tables) and carries the full hash in its metadata: a changed table gets a new export
file (OpenImageIO caches textures by name, so a rewritten file of the same name could be
served stale inside a running Blender), and older exports of the same tables are removed.
"""
from pathlib import Path

import numpy as np

from ..core.tables import COORDS
from ..errors import FlowBSDFError
from ..formats import OSL_LAYOUT
from ..io.exrio import read_rgba_exr, write_rgba_exr
from .guides import guide, own_size

LAYOUT = OSL_LAYOUT     # bake/formats.py
META_KEY = "flowbsdf_osl"
KIND = "osl"


def texture_image(tables):
    """The (H, W, 4) float32 image of the layout above."""
    K, R, C = len(tables.theta_bins), tables.rows, tables.cols
    P = 1 if tables.phi_bins is None else len(tables.phi_bins)
    B = K * P
    KP = max(K - 1, 1)
    width = max(C + 1, R + 1, K, P, 3)
    height = 3 + 3 * B * R + KP * P * (3 + 3 * R)
    img = np.zeros((height, width, 4), np.float64)
    img[0, 0] = (LAYOUT, K, R, C)
    img[0, 1] = (P, tables.phi_period, COORDS.index(tables.coords), tables.frame_angle)
    cos_bins = np.cos(tables.theta_bins).astype(np.float32).astype(np.float64)
    img[1, :K, 0] = cos_bins
    img[1, :P, 1] = [0.0] if tables.phi_bins is None else tables.phi_bins
    # theta guide: k* = the last k with cos_k >= cos_i; for cos_i in [g, g + 1) / width,
    # lo = the last k with cos_k > (g + 1) / width, hi = the first k with cos_k < g / width.
    g = np.arange(width)
    img[2, :, 0] = [max(np.sum(cos_bins > (x + 1) / width) - 1, 0) for x in g]
    img[2, :, 1] = [K - np.sum(cos_bins < x / width) for x in g]
    k = np.clip(img[2, :, 0].astype(int), 0, max(K - 2, 0))
    img[2, :, 2], img[2, :, 3] = cos_bins[k], cos_bins[np.minimum(k + 1, K - 1)]
    cells = np.concatenate([tables._m[..., None], tables._alpha, tables._beta, tables._w], axis=-1)     # (B, R, C, 12)
    # (B, R, C, 3 texels, 4) -> rows (R, B, 3): y = 3 + 3 (i B + b) + q
    img[3:3 + 3 * B * R, :C] = cells.reshape(B, R, C, 3, 4).transpose(1, 0, 3, 2, 4).reshape(3 * B * R, C, 4)
    f32 = lambda x: np.asarray(x, np.float32).astype(np.float64)      # noqa: E731  (what the shader reads)
    for k in range(KP):
        for p in range(P):
            base = 3 + 3 * B * R + (k * P + p) * (3 + 3 * R)
            k1, p1 = min(k + 1, K - 1), (p + 1) % P
            blend = [k * P + p, k1 * P + p, k * P + p1, k1 * P + p1]
            sums, edges, guides = (slice(base + 3 + q, base + 3 + 3 * R, 3) for q in range(3))   # row i's
            for ch, b in enumerate(blend):
                img[base, :R + 1, ch] = tables._row_cdf[b]
                img[base + 1, :R + 1, ch] = tables._a[b]
                img[sums, :C + 1, ch] = tables._col_cum[b]
                img[edges, :C + 1, ch] = tables._b[b]
            if P == 1:          # the sums' blue and alpha: the edges of bins k, k + 1
                for ch, b in ((2, blend[0]), (3, blend[1])):
                    img[base, :R + 1, ch] = tables._a[b]
                    img[sums, :C + 1, ch] = tables._b[b]
            rb, cb = own_size(tables, blend)
            row_cdf, a_edges = f32(tables._row_cdf[blend, :rb + 1]), f32(tables._a[blend, :rb + 1])
            img[base + 2, :R, :2] = guide(row_cdf, row_cdf[:, -1], R)
            img[base + 2, :R, 2:] = guide(a_edges, np.ones(4), R)
            img[base + 2, R, :2] = (rb, cb)
            for i in range(rb):
                col_cum, b_edges = f32(tables._col_cum[blend, i, :cb + 1]), f32(tables._b[blend, i, :cb + 1])
                img[base + 5 + 3 * i, :C, :2] = guide(col_cum, col_cum[:, -1], C)
                img[base + 5 + 3 * i, :C, 2:] = guide(b_edges, np.full(4, 2.0 * np.pi), C)
    return img.astype(np.float32)


HEADER = ("flowbsdf_layout", "flowbsdf_K", "flowbsdf_R", "flowbsdf_C", "flowbsdf_P", "flowbsdf_period",
          "flowbsdf_coords", "flowbsdf_frame")


def header_attributes(image):
    """The header texels of texture_image's `image` as the file's attributes HEADER (period and frame
    angle as the float32 the texels hold, the others ints)."""
    values = [float(x) for x in image[0, :2].reshape(-1)]
    return {name: (v if name in ("flowbsdf_period", "flowbsdf_frame") else int(v)) for name, v in zip(HEADER, values)}


def path(tables_path, digest):
    """<stem>.osl<LAYOUT>-<hash12>.exr beside the tables (blender_addon/render/derived.py builds the same name)."""
    tables_path = Path(tables_path)
    return tables_path.with_name(f"{tables_path.stem}.osl{LAYOUT}-{digest[:12]}.exr")


def read(path):
    """(image (H, W, 4) float32, metadata) of an export file; FlowBSDFError if it is not one."""
    return read_rgba_exr(path, META_KEY, "OSL texture")


def is_current(path, digest):
    try:
        _, meta = read(path)
    except FlowBSDFError:
        return False
    return meta.get("tables_hash") == digest and meta.get("layout") == LAYOUT


def write(path, tables_path, tables, digest, material=None):
    image = texture_image(tables)
    write_rgba_exr(path, image, META_KEY,
                   {"layout": LAYOUT, "tables_hash": digest, "tables": Path(tables_path).name,
                    "material": tables.meta.get("material"), "anisotropic": tables.anisotropic},
                   header_attributes(image))
