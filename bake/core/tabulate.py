"""Building baked tables (see tables.py for what they are) from a material and a source sampler.

Edges are quantiles of a stratified set of the source's directions, anchored to the
specular direction and pooled over neighbouring incident bins; masses, profiles and RGB
weights are integrated from the true f·cos per cell (refined until the cell's quadrature
settles and agrees with the source points that fall in it). A cell's profile along each axis
runs through its marginal density at the profile's nodes (_profile_logs).

What to build (the resolution, the incident bins, the layout between them) is planner.py's
choice: it runs this builder for every trial, and this module imports nothing of it.
"""
import threading

import numpy as np

from ..errors import FlowBSDFError
from ..io.threads import parallel as _parallel
from ..maths.fasttables import one_blas_thread
from ..maths.geometry import luminance, spherical_dir
from . import halfvector
from .mixed_tables import MixedTables
from .profiles import K_MAX, NSEG, _log_mean, exp_density, exp_mean
from .tables import HALF_MAX, TWO_PI, Tables, _search, to_ab

A_MIN = 1e-4     # the least gap between row knots (keeps every segment of rows non-empty)
B_MIN = 1e-4     # the same for column knots
CENTRE_ROW_KNOTS = np.array([0.0, 0.5, 1.0])       # halfvector coordinates: through the centre
# Column knots of the half vector's coordinates (wo's follow the lobe per row: lobe_col_knots).
# Halfpolar columns also split at the quarter turns: at grazing wi the rows' mass crowds into the
# azimuths across the plane of incidence, where 48² cells straddling b = pi/2 and 3 pi/2 lost
# 2-5x the ideal's rv (theta_i 85 on the bin: malachite 3.8 -> 2.5x, paper_white 2.6 -> 0.8x).
COL_KNOTS = {"halfvector": np.array([0.0, np.pi, TWO_PI]),
             "halfpolar": np.array([0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi, TWO_PI])}


def exp_rate_for_mean(mean):
    """The k whose exponential density on [0, 1] has the given mean (bisection, vectorized)."""
    mean = np.clip(np.asarray(mean, np.float64), 1e-9, 1 - 1e-9)
    lo, hi = np.full(mean.shape, -K_MAX), np.full(mean.shape, K_MAX)
    for _ in range(60):
        k = 0.5 * (lo + hi)
        m = exp_mean(k)
        lo, hi = np.where(m < mean, k, lo), np.where(m < mean, hi, k)
    return 0.5 * (lo + hi)


def _strictly_increasing(edges, lo, hi):
    """Float32 edges strictly increasing from lo to hi (last axis), each gap >= 1 ulp.
    Works on the integer bit patterns, which are ordered like non-negative floats."""
    e = np.clip(edges, lo, hi).astype(np.float32)
    e[..., 0], e[..., -1] = lo, hi
    k = e.view(np.int32).astype(np.int64)
    idx = np.arange(k.shape[-1])
    k = np.maximum.accumulate(k - idx, axis=-1) + idx
    k_hi = np.int64(np.float32(hi).view(np.int32))
    k = np.minimum(k, k_hi - (idx[-1] - idx))
    return k.astype(np.int32).view(np.float32)


def _mixture_edges(x, w, n, lo, hi, share):
    """n+1 edges at the quantiles of (1 - share) * (weighted points) + share * uniform on [lo, hi].
    x sorted. The uniform part is exact: its CDF is added, not sampled."""
    total = w.sum()
    xs = np.concatenate([[lo], x, [hi]])
    uniform = (xs - lo) / (hi - lo)
    if total <= 0:
        cdf = uniform
    else:
        cdf = (1.0 - share) * np.concatenate([[0.0], np.cumsum(w) / total, [1.0]]) + share * uniform
    return np.interp(np.arange(n + 1) / n, cdf, xs)


def _normalized(w):
    total = w.sum()
    return w / total if total > 0 else w


# Share of a segment's (rows, columns) spread evenly over it. Quantiles alone crowd the cells
# into a lobe's core and leave its flanks and tails to wide cells whose exponential cannot
# follow them: isotropic single 48² bins of the ten shared files went from 2.1-16x the ideal's
# rv (worst of theta_i 0/30/60/75/85) to 0.5-7.6x with 0.3 / 0.4 and _weighted_counts
# (measured; 0.02 / 0.05 and even counts before). Anisotropic tables keep what they were
# measured with.
SHARES = {"isotropic": (0.3, 0.4), "anisotropic": (0.02, 0.05)}
ISO_COORDS = "wo"       # isotropic tables' default coordinates (tables.py)
SEGMENT_EVEN = 0.25     # share of a row's (column's) cells split evenly among its segments


def _even_counts(n, segments):
    return [n // segments + (1 if s < n % segments else 0) for s in range(segments)]


def _weighted_counts(n, shares):
    """n cells over segments: SEGMENT_EVEN of them evenly, the rest in proportion to `shares`
    (each segment's share of the edge weight, averaged over the bins that must agree on the
    counts), at least one each, by largest remainder. An even split put 36 of 48 rows inside
    chm_mint's 2.3 deg lobe zone at theta_i 0 and 12 over the rest: 12.5x the ideal's rv there
    for a single 48² bin, 1.4x by weight (measured)."""
    segments = len(shares)
    total = float(np.sum(shares))
    share = np.asarray(shares, np.float64) / total if total > 0 else np.full(segments, 1.0 / segments)
    want = 1.0 + (n - segments) * (SEGMENT_EVEN / segments + (1.0 - SEGMENT_EVEN) * share)
    counts = np.floor(want).astype(int)
    counts[np.argsort(counts - want)[:n - counts.sum()]] += 1
    return [int(c) for c in counts]


def _segment_shares(parts, segments):
    """Per segment, its share of each part's (bin's) edge weight, averaged over the parts."""
    shares = np.zeros(segments)
    for _, w, bounds in parts:
        sums = np.add.reduceat(np.append(w, 0.0), bounds[:-1]) * (bounds[1:] > bounds[:-1])
        shares += sums / max(sums.sum(), 1e-300)
    return shares / max(len(parts), 1)


def _normalize(x, knots):
    """(segment index, position in [0, 1] within it) of x, for increasing knots."""
    seg = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
    lo, hi = knots[seg], knots[seg + 1]
    return seg, np.clip((x - lo) / (hi - lo), 0.0, 1.0)


def _stable_argsort(x):
    """np.argsort(x, kind="stable") of a 1D float array without NaN: numpy's quicksort (several
    times faster on floats), then each run of equal values put back in index order."""
    order = np.argsort(x)
    xs = x[order]
    return _ties_in_index_order(order, xs[1:] == xs[:-1])


def _ties_in_index_order(order, tie):
    """order with each run of entries tied to the next (tie[i]: order[i] ties order[i + 1]) put
    in index order, in place."""
    if tie.any():
        at = np.flatnonzero(np.concatenate([tie, [False]]) | np.concatenate([[False], tie]))
        run = np.cumsum(np.concatenate([[True], ~tie]))[at]      # the run of equal values of each
        order[at] = order[at][np.lexsort((order[at], run))]
    return order


def _by_segment(seg, r, w, segments, by=None):
    """Points ordered by segment (in [0, segments)), then by r, ties in their given order:
    (r, w) in that order and each segment's bounds. Sorted once per bin, for every
    neighbourhood that pools the bin (see _pooled_edges). by: optionally _stable_argsort of a
    quantity x that r follows within each segment (r a non-decreasing function of x there, as
    the normalized position in a segment is of the coordinate): the same order, from x's order
    (kept across builds: _b_order) by a sort over the segments alone."""
    key = lambda s: s.astype(np.int16 if segments < 1 << 15 else np.int64)     # noqa: E731 (radix sort)
    if by is not None and not np.isnan(r).any():
        order = by[np.argsort(key(seg[by]), kind="stable")]
        rs, ss = r[order], seg[order]           # (the same after the ties' fix: it permutes equal pairs)
        order = _ties_in_index_order(order, (rs[1:] == rs[:-1]) & (ss[1:] == ss[:-1]))
        return rs, w[order], np.searchsorted(ss, np.arange(segments + 1))
    order = _stable_argsort(r) if not np.isnan(r).any() else np.argsort(r, kind="stable")
    order = order[np.argsort(key(seg[order]), kind="stable")]
    return r[order], w[order], np.searchsorted(seg[order], np.arange(segments + 1))


def _pooled_edges(parts, s_, count, share, pooled=None):
    """Normalized edges of segment s_: quantiles of the points of the parts (_by_segment of
    each bin of a neighbourhood) that fall in it, mixed with uniform density. The points are
    pooled in the parts' order and sorted by r, ties in pooled order (a stable merge);
    pooled: those (r, w) given (_pooled_pieces)."""
    r, w = _pooled(parts, s_) if pooled is None else pooled
    return _mixture_edges(r, w, count, 0.0, 1.0, share)


def _pooled(parts, s_, piece=(None, None)):
    """(r, w) of segment s_'s points of the parts, pooled in the parts' order and sorted by r,
    ties in pooled order; piece (lo, hi): only those with lo <= r < hi (None: no bound; NaN,
    sorted last, counts as above every bound)."""
    lo, hi = piece
    r, w = [], []
    for p in parts:
        a, b = p[2][s_], p[2][s_ + 1]       # (a part's r is sorted within its segment)
        if lo is not None:
            a += int(np.searchsorted(p[0][a:b], lo, side="left"))
        if hi is not None:
            b = a + int(np.searchsorted(p[0][a:b], hi, side="left"))
        r.append(p[0][a:b])
        w.append(p[1][a:b])
    if len(parts) == 1:
        return r[0], w[0]
    r, w = np.concatenate(r), np.concatenate(w)
    order = np.argsort(r, kind="stable")
    return r[order], w[order]


# A segment pooled over this many points (a layout for all of a group's bins) is sorted in two
# pieces, below and above a pivot, in threads: one segment's sort was the longest stretch of
# one working thread in a Final bake (the placements' groups, ~1 s each on 45 bins).
POOL_SPLIT = 1 << 21


def _pooled_pieces(parts, segments):
    """[_pooled(parts, s_) for s_ in segments], with the segments of POOL_SPLIT points or more
    pooled in two pieces (below the median of a sample of their points, and from it), all of
    them in threads: the pieces joined are the segment's sorted points, bit for bit (a stable
    sort puts every point below the pivot first, each piece in pooled order)."""
    tasks = []
    for s_ in segments:
        sizes = [p[2][s_ + 1] - p[2][s_] for p in parts]
        if len(parts) > 1 and sum(sizes) >= POOL_SPLIT:
            sample = np.concatenate([p[0][p[2][s_]:p[2][s_ + 1]:64] for p in parts])
            pivot = float(np.median(sample)) if np.isfinite(sample).all() else None
            if pivot is not None:
                tasks += [(s_, (None, pivot)), (s_, (pivot, None))]
                continue
        tasks.append((s_, (None, None)))
    pieces = list(_parallel(lambda t: _pooled(parts, *t), tasks))
    out = {}
    for (s_, _), (r, w) in zip(tasks, pieces):
        out.setdefault(s_, []).append((r, w))
    return [got[0] if len(got) == 1 else tuple(np.concatenate(x) for x in zip(*got))
            for got in (out[s_] for s_ in segments)]


def _denormalize(shared, knots):
    """Edges from normalized per-segment edges and this bin's knots."""
    parts = [knots[0:1]]
    for s_, e in enumerate(shared):
        parts.append(knots[s_] + e[1:] * (knots[s_ + 1] - knots[s_]))
    return np.concatenate(parts)


def _knots(values, lo, hi, gap):
    """Increasing knots from lo to hi, consecutive ones at least `gap` apart."""
    k = np.clip(np.asarray(values, np.float64), lo, hi)
    idx = np.arange(len(k))
    k = np.maximum.accumulate(k - idx * gap) + idx * gap
    return np.minimum(k, hi - (idx[-1] - idx) * gap)


def lobe_knots(theta_i, lobe_width):
    """Row knots in a: the pole, the lobe zone's lower end, the mirror direction, the lobe
    zone's upper end, the horizon. Without a lobe width (broad materials): no knots."""
    a_of = lambda t: 1.0 - np.cos(np.clip(t, 0.0, 0.5 * np.pi))
    if lobe_width is None:
        return np.array([0.0, 1.0])
    return _knots([0.0, a_of(theta_i - lobe_width), a_of(theta_i), a_of(theta_i + lobe_width), 1.0],
                  0.0, 1.0, A_MIN)


def lobe_col_knots(a_mid, lobe_width):
    """Column knots in b for a row at a = a_mid: the lobe zone spans the azimuths within
    lobe_width of the mirror plane (b = pi)."""
    if lobe_width is None:
        return _knots([0.0, np.pi, TWO_PI], 0.0, TWO_PI, B_MIN)
    sin_o = np.sqrt(max(a_mid * (2.0 - a_mid), 0.0))
    half = np.pi if sin_o <= np.sin(lobe_width) else np.arcsin(np.sin(lobe_width) / sin_o)
    return _knots([0.0, np.pi - half, np.pi, np.pi + half, TWO_PI], 0.0, TWO_PI, B_MIN)


def _nodes(a0, a1, b0, b1, s, phi_ref):
    """The directions of a q x q midpoint rule per cell (a-major: node i * q + j at a node i,
    b node j), as from_ab of every node, with the sine and cosines taken once per a and b
    node rather than per node (they were ~40 % of the quadrature)."""
    a = a0[:, None] + s[None, :] * (a1 - a0)[:, None]
    phi = (b0[:, None] + s[None, :] * (b1 - b0)[:, None]) - np.pi + phi_ref
    sin_t = np.sqrt(np.maximum(a * (2.0 - a), 0.0))
    q = len(s)
    wo = np.empty((len(a0), q, q, 3))
    np.multiply(sin_t[:, :, None], np.cos(phi)[:, None, :], out=wo[..., 0])
    np.multiply(sin_t[:, :, None], np.sin(phi)[:, None, :], out=wo[..., 1])
    wo[..., 2] = (1.0 - a)[:, :, None]
    return wo.reshape(-1, 3)


class _WoFrame:
    """The isotropic cells' (a, b) of wo, b from wi's plane (tables.to_ab, phi_ref = phi_i + pi)."""

    def __init__(self, phi_i):
        self.phi_ref = phi_i + np.pi

    def nodes(self, a0, a1, b0, b1, s):
        """The q x q rule's directions and d omega_o / (da db) (1 here)."""
        return _nodes(a0, a1, b0, b1, s, self.phi_ref), None

    def ab(self, wo):
        return to_ab(wo, self.phi_ref)


class _PolarFrame:
    """The isotropic halfpolar cells' (a, b) of the half vector at wi = (theta, phi):
    halfvector.polar_to_ab in the frame turned by phi + pi, as Tables maps them."""

    def __init__(self, wi, phi):
        self.wi, self.angle = wi, phi + np.pi

    def nodes(self, a0, a1, b0, b1, s):
        a = a0[:, None] + s[None, :] * (a1 - a0)[:, None]
        b = b0[:, None] + s[None, :] * (b1 - b0)[:, None]
        return halfvector.polar_grid_from_ab(self.wi, a, b, self.angle)

    def ab(self, wo):
        return halfvector._polar_ab(self.wi, wo, self.angle)[:2]


# Row knots of halfpolar cells at these fractions of the lobe width: a coat's spike inside a
# broader lobe (cc_green_malachite, 48² single bins at theta_i 0/30/60/85: one knot at the lobe
# width 2.08/1.12/0.79/9.73x the ideal's rv, with one at a quarter too 0.57/0.36/0.72/4.00x).
POLAR_FRACTIONS = (0.25, 1.0)


def polar_lobe_knots(wi, lobe_width):
    """Row knots in a of halfpolar cells at wi: the centre (the mirror direction), the rings
    holding the half vectors within POLAR_FRACTIONS of lobe_width / 2 of the normal (the
    mirror doubles h's angle; their median a, the cap varying around the ring), the rim.
    Without a lobe width: none."""
    if lobe_width is None:
        return np.array([0.0, 1.0])
    around = np.linspace(0.0, TWO_PI, 16, endpoint=False)
    knots = [0.0]
    for fraction in POLAR_FRACTIONS:
        t = 0.5 * lobe_width * fraction
        h = np.stack([np.sin(t) * np.cos(around), np.sin(t) * np.sin(around), np.full_like(around, np.cos(t))], axis=1)
        wo = 2.0 * (h @ wi)[:, None] * h - wi
        wo[:, 2] = np.maximum(wo[:, 2], 1e-9)
        knots.append(np.median(halfvector.polar_to_ab(wi, wo)[0]))      # a: the same in any frame
    return _knots(knots + [1.0], 0.0, 1.0, A_MIN)


class _HalfFrame:
    """The anisotropic cells' (a, b) of the half vector at wi (halfvector.py), mapped in the
    frame of the lobe's axes (at `angle` from the material's x axis)."""

    def __init__(self, wi, angle):
        self.wi, self.angle = wi, angle

    def nodes(self, a0, a1, b0, b1, s):
        q = len(s)
        a = np.repeat(a0[:, None] + s[None, :] * (a1 - a0)[:, None], q, axis=1)    # a-major, as _nodes
        b = np.tile(b0[:, None] + s[None, :] * (b1 - b0)[:, None], (1, q))
        return halfvector.from_ab(self.wi, a.ravel(), b.ravel(), self.angle)

    def ab(self, wo):
        return halfvector.to_ab(self.wi, wo, self.angle)[:2]


def _closing_turn(period):
    """The closing phi bin of halfvector tables from the first (the material turned by the
    period, exactly): itself for a period of 2 pi; for pi, its cells turned by pi, which
    in halfvector coordinates is (a, b) -> (1 - a, 2 pi - b). None: build it."""
    if np.isclose(period, TWO_PI):
        return lambda column: column
    if not np.isclose(period, np.pi):
        return None

    def turn(column):
        a_edges, b_edges, mass, alpha, beta, weights = column
        flip = lambda x: x[:, ::-1, ::-1]         # noqa: E731 (rows and columns reversed, per bin)

        def flip_profile(logs):      # the cells reversed, and each profile's nodes: logs over the new first
            nodes = np.concatenate([np.zeros(logs.shape[:-1] + (1,), logs.dtype), logs], axis=-1)[..., ::-1]
            return flip(nodes[..., 1:] - nodes[..., :1])
        return (np.float32(1.0) - a_edges[:, ::-1], np.float32(TWO_PI) - b_edges[:, ::-1, ::-1], flip(mass),
                flip_profile(alpha), flip_profile(beta), weights[:, ::-1, ::-1])
    return turn


def lobe_axes_angle(source, grid=64):
    """The angle of the principal axes of the source's half vectors at normal incidence
    (their weighted second moments), the frame of halfvector coordinates: a lobe's streak
    lies along the cells' rows or columns instead of across them."""
    g = (np.arange(grid) + 0.5) / grid
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    wo, pdf = source.sample(np.array([0.0, 0.0, 1.0]), u)
    ok = (pdf > 0) & (wo[:, 2] > 0) & np.isfinite(pdf)
    h = wo[ok] + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    sxx, syy, sxy = np.mean(h[:, 0] ** 2), np.mean(h[:, 1] ** 2), np.mean(h[:, 0] * h[:, 1])
    return float(0.5 * np.arctan2(2.0 * sxy, sxx - syy))


def _moments(material, wi, frame, a0, a1, b0, b1, q, chunk=1 << 18):
    """Per cell [a0,a1]x[b0,b1], a q x q midpoint rule: target mass, its mean local x and y,
    the RGB integral of f·cos (over d omega_o: da db times the frame's Jacobian), and the
    target's marginal densities along a and b at the q nodes of each axis (shape (cells, q))."""
    s = (np.arange(q) + 0.5) / q
    X = np.repeat(s, q)
    Y = np.tile(s, q)
    n = len(a0)
    mass, mx, my = np.zeros(n), np.zeros(n), np.zeros(n)
    rgb = np.zeros((n, 3))
    along_a, along_b = np.zeros((n, q)), np.zeros((n, q))
    step = max(1, chunk // (q * q))
    for c0 in range(0, n, step):
        sl = slice(c0, min(n, c0 + step))
        wo, jac = frame.nodes(a0[sl], a1[sl], b0[sl], b1[sl], s)
        per_ab = wo[:, 2] if jac is None else wo[:, 2] * jac        # f·cos per da db
        value = (material.eval(wi, wo) * per_ab[:, None]).reshape(-1, q * q, 3)
        area = ((a1 - a0) * (b1 - b0))[sl] / (q * q)
        lum = np.maximum(luminance(value), 0.0)
        g = lum * area[:, None]
        mass[sl] = g.sum(axis=1)
        mx[sl], my[sl] = g @ X, g @ Y
        rgb[sl] = _sum_axis1(value) * area[:, None]
        grid = lum.reshape(-1, q, q)
        along_a[sl] = grid.sum(axis=2) * ((b1 - b0)[sl] / q)[:, None]
        along_b[sl] = _sum_axis1(grid) * ((a1 - a0)[sl] / q)[:, None]
    return mass, mx, my, rgb, along_a, along_b


def _sum_axis1(x):
    """x.sum(axis=1) of a 3D array, bit for bit: numpy adds along a middle axis in order,
    from +0, a few (the last axis') elements per inner loop, slow when that axis is short
    (3 colours, q nodes). Here the same adds, a whole slice at a time: in a loop over a short
    axis 1, else along axis 0 of a transposed copy (numpy adds an outer axis in order)."""
    if x.shape[1] > 16:
        return np.ascontiguousarray(x.transpose(1, 0, 2)).sum(axis=0)
    out = np.zeros((x.shape[0], x.shape[2]))
    for k in range(x.shape[1]):
        out += x[:, k]
    return out


def _moments_around(material, wi, frame, a0, a1, b0, b1, box, q):
    """Like _moments, with each cell cut at the box (lo_a, hi_a, lo_b, hi_b) that holds its
    source points, widened a little: up to 3 x 3 pieces, each with its own q x q rule, so
    that a sliver of mass at a hard edge inside a wide cell gets nodes of its own. The
    marginal densities come at the 3 q nodes per axis, with their cell-local positions
    (NaN for empty pieces)."""
    lo_a, hi_a, lo_b, hi_b = box
    cuts = []
    for lo, hi, e0, e1 in ((lo_a, hi_a, a0, a1), (lo_b, hi_b, b0, b1)):
        pad = np.maximum(0.5 * (hi - lo), 1e-3 * (e1 - e0))
        inner0, inner1 = np.clip(lo - pad, e0, e1), np.clip(hi + pad, e0, e1)
        cuts.append([e0, inner0, inner1, e1])
    n = len(a0)
    mass, mx, my, rgb = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((n, 3))
    along_a, along_b, at_a, at_b = (np.full((n, 3, q), np.nan) for _ in range(4))
    s = (np.arange(q) + 0.5) / q
    for i in range(3):
        for j in range(3):
            pa0, pa1 = cuts[0][i], cuts[0][i + 1]
            pb0, pb1 = cuts[1][j], cuts[1][j + 1]
            ok = np.flatnonzero((pa1 > pa0) & (pb1 > pb0))
            if not len(ok):
                continue
            m, x, y, c, pa, pb = _moments(material, wi, frame, pa0[ok], pa1[ok], pb0[ok], pb1[ok], q)
            # piece-local first moments -> cell-local ones
            sa, sb = (pa1 - pa0)[ok] / (a1 - a0)[ok], (pb1 - pb0)[ok] / (b1 - b0)[ok]
            oa, ob = (pa0 - a0)[ok] / (a1 - a0)[ok], (pb0 - b0)[ok] / (b1 - b0)[ok]
            mass[ok] += m
            mx[ok] += m * oa + x * sa
            my[ok] += m * ob + y * sb
            rgb[ok] += c
            along_a[ok, i] = np.nan_to_num(along_a[ok, i]) + pa
            along_b[ok, j] = np.nan_to_num(along_b[ok, j]) + pb
            at_a[ok, i], at_b[ok, j] = oa[:, None] + s * sa[:, None], ob[:, None] + s * sb[:, None]
    return (mass, mx, my, rgb) + tuple(x.reshape(n, -1) for x in (along_a, along_b, at_a, at_b))


def _rate_bound(marginal, at):
    """The largest exponential rate a cell's marginal density supports: the log of its
    max / min over the nodes where it is positive, per unit of the distance (cell-local)
    those nodes span; inf where fewer than two nodes are positive."""
    pos = marginal > 0
    hi = np.max(np.where(pos, marginal, 0.0), axis=1)
    lo = np.min(np.where(pos, marginal, np.inf), axis=1)
    span = np.max(np.where(pos, at, -np.inf), axis=1) - np.min(np.where(pos, at, np.inf), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(span > 0, np.log(hi / lo) / span, np.inf)


def _profile_logs(marginal, at):
    """Per cell, the logs of node values 1..NSEG over node 0 of a profile (log-linear between
    NSEG + 1 nodes) through the marginal density at its positive nodes `at` (others: none;
    flat beyond the end ones). Uniform where fewer than two nodes are positive."""
    xs = np.arange(NSEG + 1) / NSEG
    good = np.isfinite(at) & np.isfinite(marginal) & (marginal > 0)
    pos = np.where(good, at, np.inf)
    order = np.argsort(pos, axis=1)
    pos = np.take_along_axis(pos, order, 1)
    val = np.log(np.take_along_axis(np.where(good, marginal, 1.0), order, 1))
    count = good.sum(axis=1)
    L = _log_interp(pos, val, count, xs)
    L = _piece_masses_kept(L, pos, val, count)
    # No piece steeper than K_MAX across a whole cell (the exponential's bound): nodes raised to
    # the envelope max_j (L_j - K_MAX |k - j| / NSEG). Steeper pieces amplify the float32
    # rounding of a point's place in its cell on the render back ends (0.4 % in pdf, measured).
    k = np.arange(NSEG + 1)
    L = np.max(L[:, None, :] - (K_MAX / NSEG) * np.abs(k[:, None] - k[None, :])[None], axis=2)
    # On a grid of 1/64: every difference of two stored logs (within +-K_MAX) is then a float16
    # too, so a profile reversed (the closing turn of halfvector tables) is exact.
    return np.round((L[:, 1:] - L[:, :1]) * 64.0) / 64.0


def _profile_logs_ab(along_a, at_a, along_b, at_b):
    """(_profile_logs(along_a, at_a), _profile_logs(along_b, at_b)) in one call on the rows of both
    (the same numbers: every step works row by row; half the calls, whose many small steps were
    much of a bin's time)."""
    n = len(along_a)
    if along_a.shape != along_b.shape:
        return _profile_logs(along_a, at_a), _profile_logs(along_b, at_b)
    both = _profile_logs(np.concatenate([along_a, along_b]),
                         np.concatenate([np.broadcast_to(at_a, along_a.shape), np.broadcast_to(at_b, along_b.shape)]))
    return both[:n], both[n:]


def _log_interp(pos, logs, count, x):
    """Per cell, the logs of its marginal at the places x (m,): linear between its samples'
    logs (`pos` sorted, the first `count` valid; log-linear in the density, exact on an
    exponential flank), flat beyond the end ones; 0 where fewer than two are valid."""
    Q = pos.shape[1]
    i1 = np.clip(np.sum(pos[:, None, :] < x[None, :, None], axis=2), 1, np.maximum(count - 1, 1)[:, None])
    p0, p1 = np.take_along_axis(pos, i1 - 1, 1), np.take_along_axis(pos, np.minimum(i1, Q - 1), 1)
    m0, m1 = np.take_along_axis(logs, i1 - 1, 1), np.take_along_axis(logs, np.minimum(i1, Q - 1), 1)
    with np.errstate(invalid="ignore"):
        w = np.clip(np.nan_to_num((x[None, :] - p0) / np.maximum(p1 - p0, 1e-300)), 0.0, 1.0)
    return np.where((count >= 2)[:, None], (1 - w) * m0 + w * m1, 0.0)


PIECE_POINTS = 8        # points per piece where _piece_masses_kept reads the marginal


def _piece_masses_kept(L, pos, logs, count):
    """Node logs L (cells, NSEG + 1) raised where a piece holds less than the marginal's mass
    over it (the marginal read at PIECE_POINTS per piece by _log_interp of its samples' logs;
    linear between values overstated convex flanks): the piece's lower end, until the masses
    agree. Points alone undershoot a density that falls linearly to 0 (a Lambertian's last
    row, f·cos ~ cos): log-linear from 0.34 to 0.004 of the row's start put 1/6 of f·cos
    near the horizon (measured) and half the piece's mass; raising its end holds the mass."""
    n = len(L)
    x = (np.arange(NSEG * PIECE_POINTS) + 0.5) / (NSEG * PIECE_POINTS)
    true = np.exp(_log_interp(pos, logs, count, x)).reshape(n, NSEG, PIECE_POINTS).mean(axis=2) / NSEG
    ok = count >= 2
    for k in range(NSEG):
        lo_first = L[:, k] <= L[:, k + 1]
        lo, hi = np.where(lo_first, L[:, k], L[:, k + 1]), np.maximum(L[:, k], L[:, k + 1])
        vh = np.exp(hi)
        want = true[:, k] * NSEG

        def mass(l):
            return _log_mean(np.exp(l), vh)
        short = np.flatnonzero(ok & (mass(lo) < want * (1 - 1e-3)))
        if not len(short):
            continue
        # bisection on the short cells alone (row by row: the numbers of all cells at once)
        a, b, vh_s, want_s = lo[short], hi[short], vh[short], want[short]
        for _ in range(40):
            mid = 0.5 * (a + b)
            below = _log_mean(np.exp(mid), vh_s) < want_s
            a, b = np.where(below, mid, a), np.where(below, b, mid)
        raised = lo.copy()
        raised[short] = b
        L[:, k] = np.where(lo_first, raised, L[:, k])
        L[:, k + 1] = np.where(lo_first, L[:, k + 1], raised)
    return L


def _cell_moments(material, wi, a_edges, b_edges, frame, q, point_mass, box=None, rtol=0.02, q_max=64,
                  q_around=16):
    """Cell moments by a midpoint rule refined (q, 2q, 4q, ...) per cell until two levels
    agree within rtol and the rule does not fall short of `point_mass` (the importance-
    sampled mass of the source points in the cell): a lobe flank that the coarse nodes
    straddle is found by the points. Cells still short at q_max (a sliver of mass at a hard
    edge inside a wide cell) are integrated again around their points' `box` (per cell
    lo_a, hi_a, lo_b, hi_b), with a q_around x q_around rule per piece: the pieces hug the
    mass, so 16 nodes a side give the tables' rv that 64 gave (measured on the sharpest
    shared files) at 1/16 of the evaluations, which were ~85 % of a sharp bin's. Returns mass,
    mean local x and y, RGB integral, and the rate bounds along a and b (_rate_bound of the
    finest rule's marginals)."""
    rows, cols = b_edges.shape[0], b_edges.shape[1] - 1
    a_e, b_e = a_edges.astype(np.float64), b_edges.astype(np.float64)
    a0 = np.repeat(a_e[:-1], cols)
    a1 = np.repeat(a_e[1:], cols)
    b0, b1 = b_e[:, :-1].ravel(), b_e[:, 1:].ravel()
    point_mass = point_mass.ravel()

    def rule(moments, at_a, at_b):
        at_a = np.broadcast_to(at_a, moments[4].shape)
        at_b = np.broadcast_to(at_b, moments[5].shape)
        return moments[:4] + (_rate_bound(moments[4], at_a), _rate_bound(moments[5], at_b),
                              *_profile_logs_ab(moments[4], at_a, moments[5], at_b))

    # Each level's marginals are kept, and a cell's rate bounds and profiles computed once, from
    # the level that stands for it (they are computed row by row: the numbers are those that
    # computing them at every level and keeping the last would give, at a fraction of the cost).
    n = len(a0)
    moments = _moments(material, wi, frame, a0, a1, b0, b1, q)
    out = list(moments[:4])
    levels = [(np.arange(n), q, moments[4], moments[5])]
    final = np.zeros(n, np.int64)       # per cell: the level that stands for it (-1: the pieces around its points)
    tiny = 1e-7 * max(out[0].sum(), point_mass.sum())
    active = np.arange(n)
    while q < q_max and len(active):
        q *= 2
        moments = _moments(material, wi, frame, a0[active], a1[active], b0[active], b1[active], q)
        old_mass = out[0][active]
        for o, v in zip(out, moments[:4]):
            o[active] = v
        final[active] = len(levels)
        levels.append((active, q, moments[4], moments[5]))
        settled = (np.abs(moments[0] - old_mass) <= rtol * moments[0] + tiny) & \
            (point_mass[active] <= 1.5 * moments[0] + tiny)
        active = active[~settled]
    out += [np.empty(n), np.empty(n), np.empty((n, NSEG)), np.empty((n, NSEG))]
    if box is not None and len(active):
        short = active[point_mass[active] > 1.5 * out[0][active] + tiny]
        short = short[np.isfinite(box[0][short])]
        if len(short):
            around = _moments_around(material, wi, frame, a0[short], a1[short], b0[short], b1[short],
                                     [x[short] for x in box], min(q, q_around))
            new = rule(around[:6], *around[6:])
            for o, v in zip(out, new):
                o[short] = v
            final[short] = -1
    for level, (cells, q_level, along_a, along_b) in enumerate(levels):
        sel = np.flatnonzero(final[cells] == level)
        if not len(sel):
            continue
        nodes = (np.arange(q_level) + 0.5) / q_level
        new = rule((None,) * 4 + (along_a[sel], along_b[sel]), nodes, nodes)
        for o, v in zip(out[4:], new[4:]):
            o[cells[sel]] = v
    mass, mx, my, rgb, bound_a, bound_b, prof, prof_b = out
    with np.errstate(divide="ignore", invalid="ignore"):
        mx = np.where(mass > 0, mx / mass, 0.5)
        my = np.where(mass > 0, my / mass, 0.5)
    shape = (rows, cols)
    return tuple(x.reshape(shape) for x in (mass, mx, my)) + (rgb.reshape(shape + (3,)),) + \
        tuple(x.reshape(shape) for x in (bound_a, bound_b)) + tuple(x.reshape(shape + (NSEG,)) for x in (prof, prof_b))


def _points(material, source, wi, grid, frame, gamma):
    """A stratified grid of the source's directions for wi: their table coordinates (a, b),
    the weight of each for placing edges (normalized), and its importance-sampled target
    mass (target / source pdf / grid²)."""
    g = (np.arange(grid) + 0.5) / grid
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)

    def draw(u):        # (each point's numbers its own: the same in halves as in one piece)
        wo, pdf = source.sample(wi, u)
        ok = (pdf > 0) & (wo[:, 2] > 0) & np.isfinite(pdf)
        wo, pdf = wo[ok], pdf[ok]
        target = np.maximum(luminance(material.eval(wi, wo)), 0.0) * wo[:, 2]
        return (*frame.ab(wo), target / pdf, target ** gamma / pdf)
    # A source that samples from a table per wi (the ideal) draws each u on its own: the grid's
    # halves in threads give the same points (where the caller is not one of them: prefetch_points),
    # and their table coordinates (a lone new angle's were a serial stretch after its draws).
    halves = np.array_split(u, 2) if getattr(source, "tabulates_per_wi", False) else [u]
    a, b, mass, tail = (np.concatenate(x) for x in zip(*_parallel(draw, halves)))
    # Edges follow half the target itself (cells where the mass is) and half target^gamma
    # (cells on flanks and tails, where a cellwise model errs most).
    weight = 0.5 * _normalized(mass) + 0.5 * _normalized(tail)
    return a, b, weight, mass / (grid * grid)


def _point_boxes(cell, a, b, has, n):
    """Per cell of n, the box of its points where `has` (lo_a, hi_a, lo_b, hi_b; inf, -inf where
    none): min and max over the points ordered by cell (np.minimum.at's numbers, a fraction of
    its time)."""
    box = [np.full(n, sign * np.inf) for sign in (1, -1, 1, -1)]
    at = np.flatnonzero(has)
    if len(at):
        at = at[np.argsort(cell[at].astype(np.int16 if n < 1 << 15 else np.int64), kind="stable")]
        cells, first = np.unique(cell[at], return_index=True)
        for k, v in enumerate((a, b)):
            box[2 * k][cells] = np.minimum.reduceat(v[at], first)
            box[2 * k + 1][cells] = np.maximum.reduceat(v[at], first)
    return box


def _finish_bin(material, wi, frame, a_edges, b_edges, a, b, point_mass, quadrature, floor):
    """Per cell mass, profiles (logs) and RGB weight for one incident direction."""
    rows, cols = b_edges.shape[0], b_edges.shape[1] - 1
    row = np.clip(np.searchsorted(a_edges, a, side="right") - 1, 0, rows - 1)
    col = _find_cols(b_edges, row, b)
    cell = row * cols + col
    box = _point_boxes(cell, a, b, point_mass > 0, rows * cols)
    point_mass = np.bincount(cell, weights=point_mass, minlength=rows * cols)
    mass, mx, my, rgb, bound_a, bound_b, prof, prof_b = _cell_moments(material, wi, a_edges, b_edges, frame, quadrature,
                                                               point_mass, box)
    # Exponential rates matching each cell's first moments along a and b, no steeper than the
    # cell's own f·cos: what _unresolved_edges compares across edges (the profiles are kept).
    rate_x, rate_y = exp_rate_for_mean(np.stack([mx, my]))        # one bisection for both (elementwise)
    alpha = np.clip(rate_x, -bound_a, bound_a)
    beta = np.clip(rate_y, -bound_b, bound_b)
    a_e, b_e = a_edges.astype(np.float64), b_edges.astype(np.float64)
    for find in (lambda: _unresolved_edges(a_edges, b_edges, mass, alpha, beta),
                 lambda: _ridge_edges(material, wi, frame, a_e, b_e, mass)):
        cells, strip = find()
        if not len(cells):
            continue
        # Integrated again in a strip along that edge: the mass the rule's nodes stepped over.
        r, c = np.divmod(cells, cols)
        m, _, _, c_rgb, along_a, along_b, at_a, at_b = _moments_around(
            material, wi, frame, a_e[r], a_e[r + 1], b_e[r, c], b_e[r, c + 1], strip, STRIP_NODES)
        found = m > 1.25 * mass.flat[cells]      # materially more: else the first rule stands
        r, c = r[found], c[found]
        mass[r, c], rgb[r, c] = m[found], c_rgb[found]
        prof[r, c], prof_b[r, c] = _profile_logs_ab(along_a[found], at_a[found], along_b[found], at_b[found])
    # A floor of uniform density keeps pdf > 0 everywhere, so the table never loses a
    # direction where f·cos > 0 (unbiased whatever the quadrature missed).
    area = np.diff(a_edges.astype(np.float64))[:, None] * np.diff(b_edges.astype(np.float64), axis=1)
    total = mass.sum()
    share = mass / total if total > 0 else np.zeros_like(mass)
    prob = (1.0 - floor) * share + floor * area / TWO_PI
    # Estimator weight per cell: its integral of f·cos over its probability (sum P W = albedo).
    w_rgb = rgb / prob[..., None]
    f32, f16 = (lambda x: x.astype(np.float32)), (lambda x: x.astype(np.float16))
    weights = f16(w_rgb) if np.all(np.abs(w_rgb) < HALF_MAX) else f32(w_rgb)
    return f32(prob), f16(prof), f16(prof_b), weights


EDGE_JUMP = 30.0     # a cell's density at an edge this many times below its neighbour's across it: unresolved
STRIP = 1.0 / 32     # the strip along such an edge integrated again, as a share of the cell
STRIP_NODES = 16


def _unresolved_edges(a_edges, b_edges, mass, alpha, beta):
    """Cells whose density at an edge falls EDGE_JUMP times below their neighbour's across it
    (f·cos is continuous: the cell's rule stepped over the flank of a lobe that crosses the
    edge, and the exponential matching its moments leans away from it), with a strip along that
    edge per cell (boxes lo_a, hi_a, lo_b, hi_b for _moments_around). Measured: a cell 64 deg wide beside the
    specular peak at theta_i 85 held 1/4 of its mass, leaning the wrong way: q/p ~1e-5 at the
    flank, rv 0.83 where the ideal tabulation has 6e-4."""
    rows, cols = mass.shape
    a_e, b_e = a_edges.astype(np.float64), b_edges.astype(np.float64)
    da, db = np.diff(a_e)[:, None], np.diff(b_e, axis=1)
    mean = mass / (da * db)
    d = lambda k, x: exp_density(np.full(k.shape, float(x)), k)       # noqa: E731
    at = {"a0": mean * d(alpha, 0) * d(beta, 0.5), "a1": mean * d(alpha, 1) * d(beta, 0.5),
          "b0": mean * d(alpha, 0.5) * d(beta, 0), "b1": mean * d(alpha, 0.5) * d(beta, 1)}
    significant = 1e-7 * mass.sum()
    worst = np.zeros((rows, cols))
    side = np.full((rows, cols), "", dtype=object)

    def flag(i, j, edge, own, other, area):      # cell (i, j)'s density `own` at `edge`, `other` across it
        with np.errstate(divide="ignore", invalid="ignore"):
            jump = np.where(other * area > significant, other / np.maximum(own, 1e-300), 0.0)
        better = (jump > EDGE_JUMP) & (jump > worst[i, j])
        worst[i[better], j[better]] = jump[better]
        side[i[better], j[better]] = edge

    i, j = np.indices((rows, cols))
    nxt = (j + 1) % cols                         # the b axis wraps: the last column meets the first
    flag(i, j, "b1", at["b1"], at["b0"][i, nxt], da * db)
    flag(i, nxt, "b0", at["b0"][i, nxt], at["b1"], (da * db)[i, nxt])
    if rows > 1:                                 # across rows: the cell above the middle of each cell
        centre = 0.5 * (b_e[:-1, :-1] + b_e[:-1, 1:])
        up = np.stack([np.clip(np.searchsorted(b_e[k + 1], centre[k], side="right") - 1, 0, cols - 1)
                       for k in range(rows - 1)])
        lo_i, lo_j = i[:-1], j[:-1]
        flag(lo_i, lo_j, "a1", at["a1"][:-1], at["a0"][lo_i + 1, up], (da * db)[:-1])
        flag(lo_i + 1, up, "a0", at["a0"][lo_i + 1, up], at["a1"][:-1], (da * db)[lo_i + 1, up])
    cells = np.flatnonzero(side.ravel() != "")
    r, c = np.divmod(cells, cols)
    a0, a1, b0, b1 = a_e[r], a_e[r + 1], b_e[r, c], b_e[r, c + 1]
    edge = side[r, c]
    wa, wb = STRIP * (a1 - a0), STRIP * (b1 - b0)
    box = [np.where(edge == "a1", a1 - wa, a0), np.where(edge == "a0", a0 + wa, a1),
           np.where(edge == "b1", b1 - wb, b0), np.where(edge == "b0", b0 + wb, b1)]
    return cells, box


PLANE_B = (0.0, np.pi, TWO_PI)      # the plane of incidence in b (wo and halfpolar): column knots
RIDGE = 1e-3                       # the strip beside a ridge on an edge, as a share of the cell


def _ridge_edges(material, wi, frame, a_e, b_e, mass, q=4):
    """Cells with an edge on the plane of incidence (PLANE_B) where f·cos on the edge itself, at
    q points along it, is EDGE_JUMP times the cell's mean density: a ridge along the plane,
    narrower than the cell's rule sees and missed by both cells beside it, so no jump between
    them shows it (_unresolved_edges). Measured data have grid lines there: ilm_solo_m_68 at
    theta_i 89.9 has one within 0.001 deg of the plane from theta_o 89.9 to the horizon, which a
    row of the 4 MB tables missed: rv 0.25 where the ideal's is 0.0026, weights 2400x the albedo.
    Returns (cells, boxes) as _unresolved_edges does, the strip RIDGE of the cell wide."""
    cols = mass.shape[1]
    mean = mass / (np.diff(a_e)[:, None] * np.diff(b_e, axis=1))
    near = lambda b, planes: np.any([np.abs(b - x) < 1e-6 for x in planes], axis=0)      # noqa: E731
    found = []
    for edge, on in (("b0", near(b_e[:, :-1], PLANE_B[:2])), ("b1", near(b_e[:, 1:], PLANE_B[1:]))):
        r, c = np.nonzero(on & (mass > 0))
        if not len(r):
            continue
        line = b_e[r, c + (edge == "b1")]
        wo, jac = frame.nodes(a_e[r], a_e[r + 1], line, line, (np.arange(q) + 0.5) / q)
        per_ab = wo[:, 2] if jac is None else wo[:, 2] * jac
        on_edge = (np.maximum(luminance(material.eval(wi, wo)), 0.0) * per_ab).reshape(len(r), -1).max(axis=1)
        ridge = on_edge > EDGE_JUMP * mean[r, c]
        found += [(i, j, edge) for i, j in zip(r[ridge], c[ridge])]
    if not found:
        return np.zeros(0, np.int64), None
    r, c, edge = (np.array(x) for x in zip(*found))
    a0, a1, b0, b1 = a_e[r], a_e[r + 1], b_e[r, c], b_e[r, c + 1]
    w = RIDGE * (b1 - b0)
    return r * cols + c, [a0, a1, np.where(edge == "b1", b1 - w, b0), np.where(edge == "b0", b0 + w, b1)]


def _find_cols(b_edges, row, b):
    """Column of each point within its row: the last column whose left edge is at or below it (the
    first where none is; tables._search's answer for increasing edges), one searchsorted per row
    over its points (the bisection over all points at once indexed a row's edges per point and step)."""
    cols = b_edges.shape[1] - 1
    order = np.argsort(row.astype(np.int16 if cols < 1 << 15 else np.int64), kind="stable")
    starts = np.searchsorted(row[order], np.arange(b_edges.shape[0] + 1))
    col = np.empty(len(b), np.int64)
    for i in range(b_edges.shape[0]):
        at = order[starts[i]:starts[i + 1]]
        col[at] = np.searchsorted(b_edges[i, :cols].astype(np.float64), b[at], side="right") - 1
    return np.clip(col, 0, cols - 1)


def default_phi_bins(material, count):
    """`count` evenly spaced azimuths over one period of the material's rotational symmetry."""
    return np.arange(count) * (material.phi_period / count)


class _Once:
    """fn(*args), computed by the first caller of get(); the others wait for it."""

    def __init__(self, fn, *args):
        self._call, self._lock = (fn, args), threading.Lock()

    @property
    def done(self):
        return self._call is None

    def get(self):
        with self._lock:
            if self._call is not None:
                fn, args = self._call
                self._value, self._call = fn(*args), None
        return self._value


_cache_lock = threading.Lock()


@one_blas_thread()
def build_tables(material, source, theta_bins, rows=64, cols=64, grid=512, lobe_width=None, gamma=0.5,
                 row_share=None, col_share=None, quadrature=4, floor=1e-4, window=1,
                 progress=None, cache=None, phi_bins=None, coords=None):
    """Tables of a material at the given incident elevations (radians) and, for an
    anisotropic material, azimuths `phi_bins` (radians, increasing within [0, phi_period)
    of the material; see default_phi_bins). Each azimuth's bins are built like an isotropic
    material's (`_build_column`) at wi = (theta, phi). coords (tables.py): isotropic "wo" or
    "halfpolar" (the half vector, polar around the mirror direction), anisotropic "halfvector"
    (their default: the half vector, concentric, which holds a thin lobe between phi_i bins)
    or "wo". Default: ISO_COORDS for isotropic tables. row_share, col_share: the share of a segment's
    rows (columns) spread evenly over it, the rest at the quantiles of the points' weight
    (default: SHARES; isotropic tables also share a segment's cells out by weight). window: a
    bin's layout pools the points of the bins within `window` of it (None: of all bins; see
    _build_column).
    """
    if phi_bins is None and not material.isotropic:
        raise FlowBSDFError("an anisotropic material needs bins over phi_i (phi_bins)")
    theta_bins = np.sort(np.asarray(theta_bins, np.float64))
    phis = [0.0] if phi_bins is None else [float(p) for p in phi_bins]
    period = material.phi_period
    if phi_bins is not None and (len(phis) < 1 or np.any(np.diff(phis) <= 0) or phis[0] < 0 or phis[-1] >= period):
        raise FlowBSDFError(f"phi_bins {phis} must be increasing azimuths in [0, {period:g})")
    cache = {} if cache is None else cache      # the source's points per bin (_Once), reusable across builds
    done = [0]

    def step():
        done[0] += 1
        if progress:
            progress(done[0], len(theta_bins) * len(phis))

    opts = dict(rows=rows, cols=cols, grid=grid, lobe_width=lobe_width, gamma=gamma, row_share=row_share,
                col_share=col_share, quadrature=quadrature, floor=floor, window=window, step=step)
    # One azimuth's source points are ~10 MB per bin: with several azimuths, each column's
    # are dropped once it is built (caching them all took > 20 GB for a planned 1:6 GGX).
    coords = coords or (ISO_COORDS if phi_bins is None else "halfvector")
    if coords not in (("wo", "halfpolar") if phi_bins is None else ("wo", "halfvector")):
        raise FlowBSDFError(f"coords {coords!r}: 'wo' or 'halfpolar' for isotropic tables, "
                            "'halfvector' or 'wo' for anisotropic ones")
    kind = "isotropic" if phi_bins is None else "anisotropic"
    opts["row_share"] = SHARES[kind][0] if row_share is None else row_share
    opts["col_share"] = SHARES[kind][1] if col_share is None else col_share
    opts["weighted"] = phi_bins is None
    frame_angle = 0.0
    if coords == "halfvector":      # the phi axis closed: a last bin one period after the first
        phis = phis + [phis[0] + period]
        frame_angle = lobe_axes_angle(source)
    columns = [_build_column(material, source, theta_bins, phi, coords, frame_angle,
                             cache=cache if len(phis) == 1 else {}, **opts)
               for phi in (phis[:-1] if coords == "halfvector" and _closing_turn(period) else phis)]
    if coords == "halfvector" and (turn := _closing_turn(period)):
        columns.append(turn(columns[0]))
    if phi_bins is None:
        return Tables(theta_bins, *columns[0], coords=coords)
    return Tables(theta_bins, *(np.stack(x, axis=1) for x in zip(*columns)), phi_bins=phis, phi_period=period,
                  coords=coords, frame_angle=frame_angle)


def join_groups(groups):
    """One isotropic sampler of consecutive layout groups (Tables of the same coordinates, each
    built on its own: its own cells per segment and layout), each group's first bin at the
    previous group's last angle: theta_i below a boundary is sampled from the lower group, at or
    above it from the upper one (tables.groups_ok), a choice by wi alone. Neighbours of one
    resolution join into one Tables; groups of several resolutions make MixedTables."""
    for lower, upper in zip(groups[:-1], groups[1:]):
        if upper.coords != lower.coords or upper.anisotropic or lower.anisotropic:
            raise FlowBSDFError("layout groups must be isotropic tables of the same coordinates")
        if upper.theta_bins[0] != lower.theta_bins[-1] or len(upper.theta_bins) < 2 or len(lower.theta_bins) < 2:
            raise FlowBSDFError("each layout group starts at the previous one's last angle, two bins or more each")
    runs = [[groups[0]]]
    for g in groups[1:]:
        if (g.rows, g.cols) == (runs[-1][-1].rows, runs[-1][-1].cols):
            runs[-1].append(g)
        else:
            runs.append([g])
    parts = [run[0] if len(run) == 1 else
             Tables(np.concatenate([g.theta_bins for g in run]),
                    *(np.concatenate([getattr(g, n) for g in run]) for n in ("a_edges", "b_edges", "mass", "alpha", "beta", "weights")),
                    coords=run[0].coords)
             for run in runs]
    return parts[0] if len(parts) == 1 else MixedTables(parts)


def group_sizes(theta_bins, resolution):
    """(the bins split into their layout groups at each angle given twice, each group's resolution):
    `resolution` one for all, or one per group."""
    cut = [j + 1 for j in range(len(theta_bins) - 1) if theta_bins[j] == theta_bins[j + 1]]
    parts = np.split(np.asarray(theta_bins, np.float64), cut)
    sizes = [resolution] * len(parts) if np.ndim(resolution) == 0 else list(resolution)
    if len(sizes) != len(parts):
        raise FlowBSDFError(f"{len(sizes)} resolutions for {len(parts)} layout groups")
    return parts, sizes


def build_grouped(material, source, theta_bins, resolution, progress=None, **options):
    """build_tables at theta_bins, where an angle given twice splits them into layout groups:
    each built on its own with one layout for all its bins (window None) at its resolution (one
    for all, or one per group) and joined (join_groups); `progress` counts the groups' bins as
    one build."""
    parts, sizes = group_sizes(theta_bins, resolution)
    if len(parts) == 1:
        return build_tables(material, source, theta_bins, sizes[0], sizes[0], progress=progress, **options)
    starts = np.cumsum([0] + [len(part) for part in parts])
    return join_groups([build_tables(material, source, part, r, r, **{
        **options, "window": None,
        "progress": progress and (lambda done, _, s=s: progress(s + done, len(theta_bins)))})
        for part, r, s in zip(parts, sizes, starts)])


def _row_knots(wi, theta, coords, lobe_width):
    """The row knots of a bin's layout at wi (elevation theta): its edges are placed relative to
    them. Rounded to float32, as the edges are stored: bins whose knots differ by less (the half
    vector's rings move by ~1e-17 with theta_i) get the same edges from the same placement, one
    layout (planner.groups_bytes counts them so)."""
    knots = (CENTRE_ROW_KNOTS if coords == "halfvector" else polar_lobe_knots(wi, lobe_width)
             if coords == "halfpolar" else lobe_knots(theta, lobe_width))
    return np.asarray(knots, np.float32).astype(np.float64)


def _build_column(material, source, theta_bins, phi, coords, frame_angle, rows, cols, grid, lobe_width, gamma, row_share, col_share,
                  quadrature, floor, window, cache, step, weighted):
    """The bins at the elevations theta_bins and azimuth phi: a_edges, b_edges, mass, alpha,
    beta, weights, each with a leading bin axis.

    Edges are anchored to the specular direction: row knots at the mirror direction and,
    given a lobe width, at the lobe zone's ends; column knots at the mirror plane and the
    lobe zone's azimuths. Between knots, a bin's edges sit at the quantiles of the pooled
    points of its neighbours within `window` bins (same phi; None: all bins), in positions
    normalized to each bin's knots: neighbouring bins then place a cell on the same part of the
    lobe, so interpolating them moves the lobe instead of smearing it. With all bins pooled,
    every bin has the same layout between its knots: interpolation then mixes the bins cell by
    cell, which holds features that appear and fade between bins (planner.plan_tables chooses). In the half vector's
    coordinates the specular peak of every wi is the domain's centre: the knots are there
    (concentric: its row and column; polar: a = 0, with rings at the lobe's width,
    polar_lobe_knots, and the column at wi's side, b = pi).
    """
    K = len(theta_bins)
    wis, frames, row_knots, entries, ordered, b_orders = _bin_entries(material, source, theta_bins, phi, coords,
                                                                      frame_angle, grid, lobe_width, gamma, cache)
    n_seg = len(row_knots[0]) - 1
    points = list(_parallel(_Once.get, entries))
    by_seg = list(_parallel(_Once.get, ordered))
    window = K if window is None else window
    near = [tuple(range(max(0, k - window), min(K, k + window + 1))) for k in range(K)]
    # Cells per segment by the weight of all the column's bins: interpolation pairs cells by
    # index, and a lobe zone paired with its outside lost 10-600x (measured with counts per
    # neighbourhood). Anisotropic tables: even, as measured.

    def counts(n, shares):
        return _weighted_counts(n, shares) if weighted else _even_counts(n, len(shares))

    row_counts = counts(rows, _segment_shares(by_seg, n_seg))

    def row_edges(nbrs):       # (per segment in threads where one neighbourhood pools all bins: one layout)
        parts = [by_seg[j] for j in nbrs]
        pooled = _pooled_pieces(parts, range(len(row_counts)))
        return list(_parallel(lambda sc: _pooled_edges(parts, *sc, row_share, pooled[sc[0]]), enumerate(row_counts)))

    a_edges = [_strictly_increasing(_denormalize(shared, knots), 0.0, 1.0)
               for shared, knots in zip(_once_per_neighbourhood(near, row_edges), row_knots)]

    # Per bin: each point's row, and its normalized position within that row's column knots.
    def bin_by_row(k):
        a, b, w, _ = points[k]
        row = np.clip(np.searchsorted(a_edges[k], a, side="right") - 1, 0, rows - 1)
        a_mid = 0.5 * (a_edges[k][:-1].astype(np.float64) + a_edges[k][1:])
        knots = (np.stack([lobe_col_knots(m, lobe_width) for m in a_mid]) if coords == "wo"
                 else np.tile(COL_KNOTS[coords], (rows, 1)))
        seg, r = _normalize_rows(b, knots, row)
        # segment s of row i: group i * n + s (r follows b within each: sorted from b's order)
        return knots, _by_segment(row * (knots.shape[1] - 1) + seg, r, w, rows * (knots.shape[1] - 1),
                                  by=b_orders[k].get())
    by_row = list(_parallel(bin_by_row, range(K)))
    n = by_row[0][0].shape[1] - 1
    shares = _segment_shares([p for _, p in by_row], rows * n).reshape(rows, n)
    col_counts = [counts(cols, row_shares) for row_shares in shares]

    def col_edges(nbrs):       # per row (in threads where one neighbourhood pools all bins: one layout)
        parts = [by_row[j][1] for j in nbrs]
        return list(_parallel(lambda i: [_pooled_edges(parts, i * n + s_, count, col_share)
                                         for s_, count in enumerate(col_counts[i])], range(rows)))

    b_edges = np.empty((K, rows, cols + 1), np.float32)
    for k, shared in enumerate(_once_per_neighbourhood(near, col_edges)):
        for i in range(rows):
            b_edges[k, i] = _denormalize(shared[i], by_row[k][0][i])
        b_edges[k] = _strictly_increasing(b_edges[k], 0.0, TWO_PI)

    def finish(k):
        a, b, _, pm = points[k]
        return _finish_bin(material, wis[k], frames[k], a_edges[k], b_edges[k], a, b, pm, quadrature, floor)
    parts = []
    for part in _parallel(finish, range(K)):
        parts.append(part)
        step()
    mass, alpha, beta, weights = (np.stack(x) for x in zip(*parts))
    return np.stack(a_edges), b_edges, mass, alpha, beta, weights


def _bin_entries(material, source, theta_bins, phi, coords, frame_angle, grid, lobe_width, gamma, cache):
    """(wis, frames, row knots, and the _Once of each bin's points, their order by row segment and
    by b) of _build_column's bins. A bin's points, and their order by row segment (its knots
    decide it: the same in every build of the bin, a probe's pair or a placement's group), are
    each computed once per cache."""
    wis = [spherical_dir(t, phi) for t in theta_bins]
    frames = [_WoFrame(phi) if coords == "wo" else _PolarFrame(wi, phi) if coords == "halfpolar"
              else _HalfFrame(wi, frame_angle) for wi in wis]
    row_knots = [_row_knots(wi, t, coords, lobe_width) for t, wi in zip(theta_bins, wis)]
    n_seg = len(row_knots[0]) - 1
    with _cache_lock:
        entries = [cache.setdefault((float(t), phi, grid, gamma, coords),
                                    _Once(_points, material, source, wi, grid, frame, gamma))
                   for t, wi, frame in zip(theta_bins, wis, frames)]
        ordered = [cache.setdefault((float(t), phi, grid, gamma, coords, knots.tobytes()),
                                    _Once(_row_order, entry, knots, n_seg))
                   for t, entry, knots in zip(theta_bins, entries, row_knots)]
        b_orders = [cache.setdefault((float(t), phi, grid, gamma, coords, "b"), _Once(_b_order, entry))
                    for t, entry in zip(theta_bins, entries)]
    return wis, frames, row_knots, entries, ordered, b_orders


def prefetch_points(material, source, theta_bins, cache, coords=None, grid=512, lobe_width=None, gamma=0.5, **_):
    """The points (and their orders) of isotropic bins at theta_bins into `cache`, as build_tables
    (the same options) computes them, using the threads that its builds in threads would leave
    idle: the planner's round of interval probes needs a new angle's points in both of its builds
    (one computes them, the other waits), so they come first here, a lone bin's grid in halves."""
    _, _, _, entries, ordered, b_orders = _bin_entries(material, source, theta_bins, 0.0, coords or ISO_COORDS,
                                                       0.0, grid, lobe_width, gamma, cache)
    for todo in (entries, ordered + b_orders):
        todo = [e for e in todo if not e.done]
        if len(todo) == 1:
            todo[0].get()
        else:
            list(_parallel(_Once.get, todo))


def _b_order(points):
    """_stable_argsort of a bin's points' b (_Once of _points; None where b has NaN): their order
    within every row's column segments, whatever the rows (_by_segment's `by`)."""
    b = points.get()[1]
    return None if np.isnan(b).any() else _stable_argsort(b).astype(np.int32 if len(b) < 1 << 31 else np.int64)


def _row_order(points, knots, n_seg):
    """_by_segment of a bin's points (_Once of _points) over its row knots."""
    p = points.get()
    return _by_segment(*_normalize(p[0], knots), p[2], n_seg)


def _once_per_neighbourhood(near, compute):
    """[compute(n) for n in near], each distinct neighbourhood computed once: bins that pool the
    same points (both bins of a pair the planner builds) get the same normalized edges."""
    distinct = list(dict.fromkeys(near))
    done = dict(zip(distinct, _parallel(compute, distinct)))
    return [done[n] for n in near]


def _normalize_rows(x, knots, row):
    """Like _normalize, with each point's own knots row (knots: (rows, n_knots)); the segment is
    the count of inner knots at or below x (one searchsorted when every row has the same knots)."""
    inner = knots[:, 1:-1]
    if np.all(inner == inner[:1]):
        seg = np.searchsorted(inner[0], x, side="right")
    else:
        seg = np.sum(x[:, None] >= inner[row], axis=1)
    seg = np.clip(seg, 0, knots.shape[1] - 2)
    lo, hi = knots[row, seg], knots[row, seg + 1]
    return seg, np.clip((x - lo) / (hi - lo), 0.0, 1.0)
