"""The baked tables in the texture layout the Cycles SVM node graph reads (blender_addon/render/svm/).

The SVM back end samples the tables with plain shader nodes (every Cycles device runs
them), reading data through Image Texture nodes: Closest interpolation, Extend, Non-Color,
alpha Channel Packed, a float32 RGBA OpenEXR (ZIP, lossless). Texel (x, y) (y counted from
the top row) is read at ((x + 0.5) / W, 1 - (y + 0.5) / H) and comes back bit-exact. A node
graph cannot loop or branch, so everything a sample needs is laid out to be fetched in a
fixed number of lookups, and the numbers the graph needs to know when it is built (sizes,
offsets, search step counts) travel in the file's metadata (`read_layout`), not in texels.
Values are what `Tables.sample` (the numpy reference) uses: masses normalized per bin,
cumulative sums in float64 stored as float32, the outer edges exactly 0, 1 and 0, 2 pi.

Bins: K over theta_i, times P over phi_i for anisotropic tables (P = 1 isotropic), bin
b = k P + p as in Tables. A sample blends NB bins: NB = 2 isotropic, (k, k + 1); NB = 4
anisotropic, (k, p), (k + 1, p), (k, p + 1), (k + 1, p + 1) (p + 1 wrapping to 0, k + 1
clipped to K - 1). A *record* is one quantity at those NB bins, in that channel order:
records pack 4 / NB to a texel (isotropic: red, green = the first record; blue, alpha = the
second). R x C is the largest bin's table: the bins of MixedTables (isotropic layout groups of
their own resolutions) are its padded working copies (PAD, 1e30, past a bin's own R_b + 1 edges
and cumulative sums; masses and weights 0, profile nodes 1), laid out as one table of R x C
cells each; a corner's own R_b x C_b (its bins share it: the corner at the boundary of two
groups, two bins at one angle that are never blended, takes the smaller) bounds its guides and
its searches. Layout (W x H texels):

    row 0, global bin guides (a guide over a value v: entry g holds (t1, t2, t3, n), and the
    number of bin starts <= v is n - sum_j [v < t_j] for every v the graph puts in entry g
    (unused t_j = 1e30); entry G holds the upper end itself, so the graph needs no clamp):
        x = 0 .. GT          theta guide, v = -cos(theta_i), g = floor(sqrt(1 - cos theta_i) GT):
                             the count is k, the last bin with cos(theta_k) >= cos theta_i,
                             within [0, K - 2] (absent when K = 1)
        x = GT + 1 ..        phi guide, v = (phi_i - phi_bin 0) mod period in [0, period],
                             g = floor(v GP / period): the count is p (absent when P = 1)
    rows 1 ..: one block per corner c = k P + p (k < max(K - 1, 1), p < P), BW x BH texels
    with BH = R + 1, at block column c mod NX, block row c // NX (texel origin
    (BW (c mod NX), 1 + BH (c // NX))). Within a block:
        row 0, x = 0         header: (cos theta_k, cos theta_k+1, start_p, end_p) (start_p =
                             phi_bin p - phi_bin 0, end_p the next start or the period);
                             isotropic tables: (cos theta_k, cos theta_k+1, R_b - 1, C_b - 1)
        row 0, x = 1 + g     row guide, g < GR: (lo, hi) brackets the row for u0 in
                             [g, g + 1) / GR (guides.guide over the corner's own R_b + 1
                             entries), lo lowered so that lo + 2^row_steps - 1 stays within
                             the records
        row 0, x = XR + SR i records [row CDF(i), a edge(i)], i = 0 .. NR - 1, NR = max(R + 1,
                             2^row_steps, 2^ceil(log2 R)) (8 past the end: a branchless search,
                             the sampler's from its guide or the pdf's from 0, never stops there)
        row 1 + i, x = g     column guide of table row i, g < GC: (lo, hi) for u1 in
                             [g, g + 1) / GC (over the row's own C_b + 1 entries; (0, 0) for
                             i >= R_b), lowered likewise
        row 1 + i, x = XC + SC j   records [column cumsum(i, j), b edge(i, j)], j = 0 .. NC - 1,
                             NC = max(C + 1, 2^col_steps, 2^ceil(log2 C)) (8 past the end)
        row 1 + i, x = XX + SX j   records [mass, the a profile's NSEG + 1 node values, the b
                             profile's, W red, W green, W blue] of cell (i, j), j < C (the
                             node values normalized per bin: Tables._alpha, _beta)
      SR = SC = 2 / (4 / NB) texels (1 isotropic, 2 anisotropic), SX = CELL_QUANTITIES NB / 4.

The graph's binary searches are branchless: lo moves forward by 2^(n-1), ..., 1 where the
blended record there is <= the target. The sampler's (CDFs) start from their guide's lo,
n = row_steps or col_steps (the guides' widest bracket over all corners, fixed when the
graph is built); the pdf's (the inverse, on the a and b edges) start from 0 over all R
(C) (PAD and PAST_END records are above every target). Results are capped at the corner's
R_b - 1 (C_b - 1; read from the header, isotropic tables; R - 1 and C - 1 anisotropic): a
blended total can round to <= a target near it.

Every side stays within MAX_SIDE (16384, the GPU texture limit of some devices): blocks
wrap into rows of NX blocks; tables too large for that raise FlowBSDFError. (64 x 64 cells:
40 theta bins, 12519 x 66 texels, 13 MB; 12 x 8 anisotropic bins, 16184 x 261, 68 MB: every
corner block repeats its bins' data, so that one fetch serves the whole blend.)

Metadata (JSON in the header attribute "flowbsdf_svm"): layout (LAYOUT), K, P, R, C, NB,
period, phi0 (phi_bin 0), width, height (W, H), block ([BW, BH]), blocks_per_row (NX),
corners, x_row, x_col, x_cell, row_stride, col_stride, cell_stride (XR, XC, XX, SR, SC, SX),
row_guide, col_guide (GR = R, GC = C), row_steps, col_steps, theta_guide and phi_guide
([x0, G]: the guide's first texel and G, the smallest power of two >= 16 that leaves at most
three starts to an entry), plus tables_hash, tables (file name), material, anisotropic.

The file is named after the table file's content hash (`<stem>.svm<LAYOUT>-<hash12>.exr`
next to the tables) and carries the full hash in its metadata: a changed table gets a new
file (Blender and Cycles cache images by name), and older exports of the same tables are
removed.
"""
import json
import struct
from pathlib import Path

import numpy as np

from ..core.profiles import NSEG
from ..errors import FlowBSDFError
from ..formats import SVM_LAYOUT
from ..io.exrio import read_rgba_exr, write_rgba_exr
from .guides import guide, own_size

LAYOUT = SVM_LAYOUT     # bake/formats.py
META_KEY = "flowbsdf_svm"
KIND = "svm"
MAX_SIDE = 16384
PAST_END = 8.0          # a record value above any target (CDFs and a <= 1, b <= 2 pi)
UNUSED = 1e30           # a bin guide threshold no value reaches
CELL_QUANTITIES = 1 + 2 * (NSEG + 1) + 3     # mass, the a and b profiles' node values, W red, W green, W blue


def _f32(x):
    return np.asarray(x, np.float32).astype(np.float64)


def _bin_guide(starts, bounds):
    """Guide entries (G + 1, 4) for the count of `starts` (increasing) <= v: entry g, for the
    values v in (a[g], b[g]] of `bounds(G) -> (a, b)` (the values the graph may put in entry g,
    widened for its float32 index arithmetic; the first and last entries open-ended), holds up
    to three starts to compare, padded with UNUSED, and n = (starts below all of them) + 3."""
    starts = np.asarray(starts, np.float64)
    for count in 2 ** np.arange(4, 14):
        a, b = bounds(count)
        inside = (starts[None, :] > a[:, None]) & (starts[None, :] <= b[:, None])
        if inside.sum(1).max() <= 3:
            out = np.full((count + 1, 4), UNUSED)
            out[:, 3] = np.sum(starts[None, :] <= a[:, None], axis=1) + 3
            for g in range(count + 1):
                t = starts[inside[g]]
                out[g, :len(t)] = t
            return out
    raise FlowBSDFError("incident bins too close together for the SVM bin guide")


def _linear_bounds(lo, hi):
    """Entry g = floor((v - lo) G / (hi - lo)) (the phi guide)."""
    margin = 1e-5 * (hi - lo)

    def bounds(count):
        edges = lo + (hi - lo) * np.arange(count + 1) / count
        return (np.concatenate([[-np.inf], edges[1:-1] - margin, [edges[-1] - margin]]),
                np.concatenate([edges[1:-1] + margin, [np.inf], [np.inf]]))
    return bounds


COS_ERROR = 1e-6    # what the graph's float32 cos theta_i may be off by (~16 ulps below 1)


def _theta_bounds(count):
    """Entry g = floor(sqrt(1 - cos theta_i) G) over v = -cos theta_i: sqrt(1 - cos) grows like
    theta / sqrt(2), so bins a fraction of a degree apart near the normal (the planner puts
    them there for files with a sharp peak: ilm_solo_m_68) fall in different entries, where
    1 - cos (~theta^2 / 2) crowded them into one. Each edge is widened by what a float32 cos
    can move sqrt(1 - cos) there: COS_ERROR / (2 w), at most sqrt(COS_ERROR) near w = 0."""
    w = np.arange(count + 1) / count
    slack = 1e-5 + np.minimum(np.sqrt(COS_ERROR), COS_ERROR / (2.0 * np.maximum(w, 1e-300)))
    lower = np.square(np.maximum(w - slack, 0.0)) - 1.0
    upper = np.square(w + slack) - 1.0
    return (np.concatenate([[-np.inf], lower[1:-1], [lower[-1]]]),
            np.concatenate([upper[1:-1], [np.inf], [np.inf]]))


def _steps(guides):
    """Binary search steps covering the widest bracket of the guides [(lo, hi), ...]."""
    width = max(int(np.max(g[:, 1] - g[:, 0])) for g in guides)
    return int(np.ceil(np.log2(width))) if width > 1 else 0


def _full_steps(n):
    """Binary search steps over n entries without a guide."""
    return int(n - 1).bit_length()


def _records(quantities, nb, count):
    """Texels (count, n, 4) packing records (one per quantity, each (count, nb)), 4 // nb per texel."""
    flat = np.concatenate([np.asarray(q, np.float64).reshape(count, nb) for q in quantities], axis=1)
    pad = -flat.shape[1] % 4
    return np.pad(flat, ((0, 0), (0, pad))).reshape(count, -1, 4)


def texture_image(tables):
    """(image (H, W, 4) float32, layout dict) of the layout above."""
    K, R, C = len(tables.theta_bins), tables.rows, tables.cols
    P = 1 if tables.phi_bins is None else len(tables.phi_bins)
    nb = 4 if tables.anisotropic else 2
    period = float(tables.phi_period)
    corners = [(k, p) for k in range(max(K - 1, 1)) for p in range(P)]

    def blend(k, p):
        k1, p1 = min(k + 1, K - 1), (p + 1) % P
        return [k * P + p, k1 * P + p, k * P + p1, k1 * P + p1][:nb]

    # Guides per corner (and row), from the float32 values the graph reads: each corner's own
    # rows and columns (rows past them: never reached, lo = hi = 0).
    sizes = [own_size(tables, blend(k, p)) for k, p in corners]
    row_guides, col_guides = [], []
    for (k, p), (rb, cb) in zip(corners, sizes):
        cdf = _f32(tables._row_cdf[blend(k, p), :rb + 1])
        row_guides.append(guide(cdf, cdf[:, -1], R))
        for i in range(R):
            cum = _f32(tables._col_cum[blend(k, p), i, :cb + 1])
            col_guides.append(guide(cum, cum[:, -1], C) if i < rb else np.zeros((C, 2)))
    row_steps, col_steps = _steps(row_guides), _steps(col_guides)
    # records for the widest search: the sampler's from its guides, the pdf's over all R (C)
    n_row = max(R + 1, 2 ** max(row_steps, _full_steps(R)))
    n_col = max(C + 1, 2 ** max(col_steps, _full_steps(C)))

    def lowered(guide, n, steps):
        g = guide.copy()
        g[:, 0] = np.maximum(np.minimum(g[:, 0], n - 2 ** steps), 0)
        return g

    rpt = 4 // nb                       # records per texel
    sr = sc = 2 // rpt
    sx = CELL_QUANTITIES // rpt
    xr, xc = 1 + R, C
    xx = xc + sc * n_col
    bw = max(xr + sr * n_row, xx + sx * C)
    bh = R + 1
    nx = max(1, min(len(corners), MAX_SIDE // bw))
    ny = -(-len(corners) // nx)

    cos_bins = _f32(np.cos(tables.theta_bins))
    theta_guide = _bin_guide(-cos_bins[1:K - 1], _theta_bounds) if K > 1 else np.zeros((0, 4))
    starts = _f32(np.zeros(1) if tables.phi_bins is None else tables.phi_bins - tables.phi_bins[0])
    phi_guide = _bin_guide(starts[1:], _linear_bounds(0.0, period)) if P > 1 else np.zeros((0, 4))
    gt, gp = len(theta_guide), len(phi_guide)
    width = max(nx * bw, gt + gp)
    height = 1 + ny * bh
    if width > MAX_SIDE or height > MAX_SIDE:
        raise FlowBSDFError(f"tables of {K} x {P} bins of {R} x {C} cells need an SVM texture of "
                            f"{width} x {height} texels, more than {MAX_SIDE} per side")

    img = np.zeros((height, width, 4), np.float32)
    img[0, :gt] = theta_guide
    img[0, gt:gt + gp] = phi_guide
    ends = np.append(starts[1:], period)
    for c, (k, p) in enumerate(corners):
        x0, y0 = bw * (c % nx), 1 + bh * (c // nx)
        block = img[y0:y0 + bh, x0:x0 + bw]
        bins = blend(k, p)
        if P > 1:
            block[0, 0] = (cos_bins[k], cos_bins[min(k + 1, K - 1)], starts[p], ends[p])
        else:
            block[0, 0] = (cos_bins[k], cos_bins[min(k + 1, K - 1)], sizes[c][0] - 1, sizes[c][1] - 1)
        block[0, 1:1 + R, :2] = lowered(row_guides[c], n_row, row_steps)
        cdf = np.full((n_row, nb), PAST_END)
        cdf[:R + 1] = tables._row_cdf[bins].T
        a = np.full((n_row, nb), PAST_END)
        a[:R + 1] = tables._a[bins].T
        block[0, xr:xr + sr * n_row] = _records([cdf, a], nb, n_row).reshape(-1, 4)
        for i in range(R):
            row = block[1 + i]
            row[:C, :2] = lowered(col_guides[c * R + i], n_col, col_steps)
            cum = np.full((n_col, nb), PAST_END)
            cum[:C + 1] = tables._col_cum[bins, i].T
            b = np.full((n_col, nb), PAST_END)
            b[:C + 1] = tables._b[bins, i].T
            row[xc:xc + sc * n_col] = _records([cum, b], nb, n_col).reshape(-1, 4)
            w = tables._w[bins, i].astype(np.float64)                  # (nb, C, 3)
            cells = ([tables._m[bins, i].T] + [tables._alpha[bins, i, :, n].T for n in range(NSEG + 1)]
                     + [tables._beta[bins, i, :, n].T for n in range(NSEG + 1)] + [w[..., 0].T, w[..., 1].T, w[..., 2].T])
            row[xx:xx + sx * C] = _records(cells, nb, C).reshape(-1, 4)

    layout = {"layout": LAYOUT, "K": K, "P": P, "R": R, "C": C, "NB": nb, "period": period,
              "phi0": 0.0 if tables.phi_bins is None else float(tables.phi_bins[0]),
              "coords": tables.coords, "frame": tables.frame_angle,
              "width": width, "height": height, "block": [bw, bh], "blocks_per_row": nx,
              "corners": len(corners), "x_row": xr, "x_col": xc, "x_cell": xx,
              "row_stride": sr, "col_stride": sc, "cell_stride": sx,
              "row_guide": R, "col_guide": C, "row_steps": row_steps, "col_steps": col_steps,
              "theta_guide": [0, gt - 1], "phi_guide": [gt, gp - 1]}
    return img, layout


def read_layout(path):
    """The metadata of an SVM texture (its layout dict plus tables_hash, tables, material),
    read from the OpenEXR header with the standard library only (Blender's Python may lack
    the OpenEXR module). FlowBSDFError if the file is not one."""
    path = Path(path)
    try:
        data = path.read_bytes()[:1 << 20]
    except OSError as e:
        raise FlowBSDFError(f"SVM texture unreadable ({e.strerror or e})", path) from None
    if data[:4] != b"\x76\x2f\x31\x01":
        raise FlowBSDFError("not an OpenEXR file", path)
    pos = 8
    try:
        while data[pos] != 0:
            name_end = data.index(b"\0", pos)
            type_end = data.index(b"\0", name_end + 1)
            (size,) = struct.unpack_from("<i", data, type_end + 1)
            value = data[type_end + 5:type_end + 5 + size]
            if data[pos:name_end] == META_KEY.encode() and data[name_end + 1:type_end] == b"string":
                meta = json.loads(value.decode())
                if not isinstance(meta, dict) or meta.get("layout") != LAYOUT:
                    raise FlowBSDFError(f"SVM texture layout {meta.get('layout') if isinstance(meta, dict) else '?'}"
                                        f" (this FlowBSDF reads {LAYOUT}); re-export it", path)
                return meta
            pos = type_end + 5 + size
    except (IndexError, ValueError, struct.error):
        raise FlowBSDFError("OpenEXR header damaged", path) from None
    raise FlowBSDFError("an OpenEXR file, but not a FlowBSDF SVM texture", path)


def path(tables_path, digest):
    """<stem>.svm<LAYOUT>-<hash12>.exr beside the tables."""
    tables_path = Path(tables_path)
    return tables_path.with_name(f"{tables_path.stem}.svm{LAYOUT}-{digest[:12]}.exr")


def read(path):
    """(image (H, W, 4) float32, metadata) of an SVM texture; FlowBSDFError if it is not one."""
    return read_rgba_exr(path, META_KEY, "SVM texture")


def is_current(path, digest):
    try:
        meta = read_layout(path)
    except FlowBSDFError:
        return False
    return meta.get("tables_hash") == digest


def write(path, tables_path, tables, digest, material=None):
    img, layout = texture_image(tables)
    write_rgba_exr(path, img, META_KEY, {**layout, "tables_hash": digest, "tables": Path(tables_path).name,
                                         "material": tables.meta.get("material"),
                                         "anisotropic": tables.anisotropic})
