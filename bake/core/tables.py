"""Baked conditional tables: an exact, table-speed sampler per material.

Per incident bin, the table is an adaptive piecewise density on the hemisphere: R rows in
a = 1 - cos(theta_o) and, in each row, C columns in b = phi_o - phi_i (the azimuth relative
to wi's plane; the mirror direction sits at b = pi, so the specular lobe never straddles
the seam); da db = d omega. Cell (i, j) holds mass m_ij, spread over it with a separable
density: in local coordinates x, y in [0, 1], q(x, y) = p_a(x) p_b(y), each a *profile*:
NSEG pieces, log-linear between NSEG + 1 node values (each piece an exponential e_k(t) =
k e^(k t) / (e^k - 1), no steeper than K_MAX across a whole cell). An exponential follows a
lobe's flank where a linear slope cannot, and the pieces meet continuously, so a profile
also holds a knee inside a cell (a flank running into a flat tail) that one exponential
cannot (a cell's rv excess over the ideal tabulation sat in such rows: on the bin, 48²,
the cells 2 MB plans missed went from 1.96-3.70x the ideal's rv to 1.06-1.32x, each piece
keeping the marginal's mass, tabulate._piece_masses_kept):

    sample:  u0 -> row by the row CDF, u1 -> column by the row's CDF, the two remainders
             -> x, y by the profiles' inverse CDFs (the piece, then its exponential's),
    pdf:     m_ij p_a(x) p_b(y) / ((a_{i+1} - a_i)(b_{i,j+1} - b_{i,j})),
    invert:  find the cell (binary search), evaluate the CDFs,

are exact and mutually consistent to float precision. The cells tile the whole hemisphere
and every mass is positive, so no direction has pdf 0 and no sample is lost below the
horizon.

How the cells are chosen and filled is tabulate.py's job: edges are quantiles of a
stratified set of directions from a source sampler (the trained flow, or the ideal
tabulation), anchored to the specular direction; masses, profiles and RGB weights are
integrated from the true f·cos per cell by refined quadrature, so the tables follow the
material whatever the source's quality.

Between incident bins edges and masses are interpolated linearly. Interpolated edges
stay increasing (a convex combination of increasing lists), interpolated masses stay a
distribution, so every wi gets an exact table, and a lobe moves with theta_i instead of
fading between two positions (a displacement interpolation).

A profile is stored as the logs of its nodes 1..NSEG over node 0; each bin's is normalized
to integrate to 1 (profile_nodes) and the bins blend node values: at the nodes the blended
density is the mixture of the bins' (the blend follows the mixture, never a steep piece
displaced off the flank it was fitted to: blending exponentials' rates did that, e^-17 below
f·cos, rv 8.5e4 x the ideal's on a measured file; leans, then node values, followed the mixture).

Storage: edges and masses float32; the profiles' logs and the RGB weights float16 as the
builder makes them (weights beyond float16's range stay float32): 22 bytes a cell in each bin,
and its edges (4 more) once per layout: bins whose cells are placed alike (a layout group's,
tabulate._build_column) keep one copy in the file and in `nbytes` (`layouts`). The stored values
define the sampler, whatever their type.

Anisotropic materials (`phi_bins`): bins over theta_i x phi_i, the phi_i bins increasing
azimuths within one period P of the material's rotational symmetry (`phi_period`, 2 pi
unless the material says otherwise; pi for elliptic microfacet lobes), wrapping around.
Each bin is built at its own wi and the four neighbouring bins are blended bilinearly:
weights linear in cos(theta_i) times linear in phi_i, still a convex combination, so
everything above holds. Their cells are over the half vector (`coords` "halfvector",
bake/core/halfvector.py: a thin lobe stays put in it as phi_i turns, where in (a, b)
above it turns with wi's plane and blending smears it); files from before keep (a, b)
("wo"). The C fast path serves both; anisotropic files over wo use the numpy code.

Isotropic tables over the half vector (`coords` "halfpolar", halfvector.polar_from_ab): a
polar grid around the mirror direction, a = the half vector's 1 - cos theta_h over the
valid cap's, b = its azimuth from the side away from wi. A lobe sits at a = 0 for every
theta_i, so blending two bins keeps it there, where over wo a narrow lobe moves from the
pole (a cap of cells) to a blob off it and half-way it is smeared over both (measured
below 6 deg: 20-860x the ideal's rv half-way between bins 6 deg apart, 0.4-3.2x over h).

Per cell the table also keeps the RGB estimator weight W = integral of f·cos over the
cell / its share of the target; `eval` returns W·pdf/cos, the baked BSDF the Cycles back
ends render (their weight f·cos / pdf is W exactly).

One file of ~760 lines on purpose: the reference every back end transcribes (the C path, OSL's
tables.h, the SVM graph's tables.py) reads sample, pdf, invert and eval with the coordinate maps
and profiles they share in one place, as tables.h does.
"""
import functools

import numpy as np

from ..errors import FlowBSDFError
from ..formats import FORMAT, MIXED_FORMAT
from ..io.exrio import read_exr, write_exr
from ..materials.base import as_dirs
from ..maths.geometry import atan2, theta_phi
from . import halfvector

try:        # the optional C fast path (never required: Blender imports bake/ with numpy only)
    from ..maths import fasttables as _fasttables
except Exception:   # noqa: BLE001
    _fasttables = None

FORMAT_VERSION = FORMAT     # bake/formats.py
TWO_PI = 2.0 * np.pi
# The cells' coordinates: (a, b) of wo, or halfvector.py's of h (concentric: anisotropic
# tables; polar: isotropic ones)
COORDS = ("wo", "halfvector", "halfpolar")
H_MAPS = {"halfvector": (halfvector.from_ab, halfvector.to_ab),     # (a, b) <-> wo over h: (from_ab, to_ab)
          "halfpolar": (halfvector.polar_from_ab, halfvector.polar_to_ab)}


def to_ab(wo, phi_ref):
    """Table coordinates of wo: a = 1 - cos(theta) (stable near the pole), b in [0, 2 pi)."""
    z = wo[:, 2]
    a = (wo[:, 0] ** 2 + wo[:, 1] ** 2) / (1.0 + np.maximum(z, 0.0))
    a = np.where(z > 0, np.minimum(a, 1.0), 1.0)
    b = np.mod(atan2(wo[:, 1], wo[:, 0]) - phi_ref + np.pi, TWO_PI)
    return a, b


def from_ab(a, b, phi_ref):
    s = np.sqrt(np.maximum(a * (2.0 - a), 0.0))
    phi = b - np.pi + phi_ref
    return np.stack([s * np.cos(phi), s * np.sin(phi), 1.0 - a], axis=-1)


# Within a cell, each axis has the exponential density k e^(k x) / (e^k - 1) on [0, 1]
# (uniform at k = 0): its CDF, inverse and density. An exponential follows the steep
# flank of a lobe across a cell where a linear slope cannot.
K_MAX = 30.0     # the largest exponential rate across a cell (e^30: steeper than any data)
_SMALL = 1e-4


def exp_cdf(x, k):
    ks = np.where(np.abs(k) < _SMALL, 1.0, k)
    return np.where(np.abs(k) < _SMALL, x + 0.5 * k * (x * x - x), np.expm1(ks * x) / np.expm1(ks))


def exp_inverse_cdf(u, k):
    ks = np.where(np.abs(k) < _SMALL, 1.0, k)
    exact = np.log1p(u * np.expm1(ks)) / ks
    return np.clip(np.where(np.abs(k) < _SMALL, u - 0.5 * k * (u * u - u), exact), 0.0, 1.0)


def exp_density(x, k):
    ks = np.where(np.abs(k) < _SMALL, 1.0, k)
    return np.where(np.abs(k) < _SMALL, 1.0 + k * (x - 0.5), ks * np.exp(ks * x) / np.expm1(ks))


HALF_MAX = 65504.0      # the largest float16

# A cell's profile along each axis: NSEG log-linear pieces through NSEG + 1 node values, stored
# as the logs of nodes 1..NSEG over node 0 (alpha along a, beta along b: (..., NSEG) float16).
NSEG = 3


def profile_nodes(logs):
    """Node values (..., NSEG + 1) of stored logs (..., NSEG), normalized to integrate to 1."""
    L = np.concatenate([np.zeros(logs.shape[:-1] + (1,)), np.asarray(logs, np.float64)], axis=-1)
    V = np.exp(L - L.max(axis=-1, keepdims=True))
    flat = V.reshape(-1, NSEG + 1)
    return (flat / profile_parts(flat)[1][:, None]).reshape(V.shape)


LOG_MEAN_SERIES = 1e-3      # |log(v1 / v0)| below which the log mean takes its series (float32 back ends)


def _log_mean(v0, v1):
    """(v1 - v0) / log(v1 / v0); where the log is small, v0 (1 + l / 2 + l^2 / 6) (error l^3 / 24):
    (r - 1) / log r there lost 0.4 % in OSL's float32 (measured)."""
    r = v1 / v0
    lr = np.log(r)
    small = np.abs(lr) < LOG_MEAN_SERIES
    return v0 * np.where(small, 1.0 + lr * (0.5 + lr / 6.0), (r - 1.0) / np.where(small, 1.0, lr))


def profile_parts(V):
    """Per cell (rows of V, node values > 0): the pieces' masses (N, NSEG) and total."""
    M = _log_mean(V[:, :-1], V[:, 1:]) / NSEG
    return M, M.sum(axis=1)


def profile_sample(u, V):
    """(the place x of u under the profiles V, and their density there, from the piece found)."""
    M, tot = profile_parts(V)
    C = np.cumsum(M, axis=1)
    target = np.clip(u, 0.0, 1.0) * tot
    k = np.minimum(np.sum(C[:, :-1] <= target[:, None], axis=1), NSEG - 1)
    prev = np.where(k > 0, np.take_along_axis(C, np.maximum(k - 1, 0)[:, None], 1)[:, 0], 0.0)
    Mk = np.take_along_axis(M, k[:, None], 1)[:, 0]
    v0 = np.take_along_axis(V, k[:, None], 1)[:, 0]
    v1 = np.take_along_axis(V, (k + 1)[:, None], 1)[:, 0]
    rate = np.log(v1 / v0)
    t = exp_inverse_cdf(np.clip((target - prev) / Mk, 0.0, 1.0), rate)
    return (k + t) / NSEG, v0 * np.exp(t * rate) / tot


def _piece(x, V):
    k = np.clip(np.floor(x * NSEG).astype(np.int64), 0, NSEG - 1)
    t = np.clip(x * NSEG - k, 0.0, 1.0)
    v0 = np.take_along_axis(V, k[:, None], 1)[:, 0]
    v1 = np.take_along_axis(V, (k + 1)[:, None], 1)[:, 0]
    return k, t, v0, v1


def profile_density(x, V):
    k, t, v0, v1 = _piece(x, V)
    return v0 * np.exp(t * np.log(v1 / v0)) / profile_parts(V)[1]


def profile_cdf(x, V):
    M, tot = profile_parts(V)
    k, t, v0, v1 = _piece(x, V)
    C = np.concatenate([np.zeros((len(V), 1)), np.cumsum(M, axis=1)], axis=1)
    return (np.take_along_axis(C, k[:, None], 1)[:, 0]
            + np.take_along_axis(M, k[:, None], 1)[:, 0] * exp_cdf(t, np.log(v1 / v0))) / tot


def _stored(x):
    """An array as Tables keeps it: float16 when given so (the builder's profiles and weights,
    tabulate._finish_bin), else float32."""
    x = np.asarray(x)
    return x if x.dtype == np.float16 else x.astype(np.float32)


def exp_mean(k):
    """The mean of x under the exponential density of rate k on [0, 1]."""
    ks = np.where(np.abs(k) < _SMALL, 1.0, k)
    return np.where(np.abs(k) < _SMALL, 0.5 + k / 12.0, 1.0 / (-np.expm1(-ks)) - 1.0 / ks)


def _valid_profiles(alpha, beta, mass_shape):
    """Profiles' logs (alpha, beta) with one axis of NSEG more than mass, finite, within +-K_MAX
    (a piece's bound times NSEG)."""
    return all(np.shape(x) == (*mass_shape, NSEG) and np.all(np.isfinite(x)) and np.all(np.abs(x) <= K_MAX * 1.01)
               for x in (alpha, beta))


def _search(value, n, edge_at):
    """Per sample, the i in [0, n) with edge_at(i) <= value < edge_at(i + 1) (edges increasing)."""
    lo = np.zeros(len(value), np.int64)
    hi = np.full(len(value), n, np.int64)
    for _ in range(int(np.ceil(np.log2(max(n, 2))))):
        mid = (lo + hi) // 2
        right = edge_at(mid) <= value
        lo = np.where(right, mid, lo)
        hi = np.where(right, hi, mid)
    return lo



# ------------------------------------------------------------------------------ sampling

class Tables:
    """The baked sampler of one material: bins over theta_i, and over phi_i when anisotropic.

    Isotropic arrays: a_edges (K, R+1), b_edges (K, R, C+1), mass (K, R, C), alpha/beta (K, R, C,
    NSEG) (the profiles' logs), weights (K, R, C, 3). Anisotropic ones (phi_bins given, P of them) have a phi axis
    after the theta axis: a_edges (K, P, R+1), and so on. `coords`: what (a, b) are (COORDS).
    """

    name = "tables"
    normalized = True       # pdf() integrates to 1 (the cells tile the hemisphere): no sample is ever lost
    ARRAYS = ("mass", "alpha", "beta")

    def __init__(self, theta_bins, a_edges, b_edges, mass, alpha, beta, weights, meta=None, backend="auto",
                 phi_bins=None, phi_period=TWO_PI, coords="wo", frame_angle=0.0):
        if coords not in COORDS:
            raise FlowBSDFError(f"table coordinates {coords!r} must be one of {list(COORDS)}")
        if (coords == "halfvector" and phi_bins is None) or (coords == "halfpolar" and phi_bins is not None):
            raise FlowBSDFError(f"{coords} tables are " + ("anisotropic" if coords == "halfvector" else "isotropic"))
        self.coords = coords
        self.frame_angle = float(frame_angle)   # halfvector: the lobe's axes from the material's x axis
        self.theta_bins = np.asarray(theta_bins, np.float64)
        self.phi_bins = None if phi_bins is None else np.asarray(phi_bins, np.float64)
        self.phi_period = float(phi_period)
        self.a_edges = np.asarray(a_edges, np.float32)     # (K, [P,] R+1)
        self.b_edges = np.asarray(b_edges, np.float32)     # (K, [P,] R, C+1)
        self.mass = np.asarray(mass, np.float32)           # (K, [P,] R, C)
        self.alpha = _stored(alpha)                        # (K, [P,] R, C, NSEG) the profile along a (logs)
        self.beta = _stored(beta)                          # (K, [P,] R, C, NSEG) the profile along b
        self.weights = _stored(weights)                    # (K, [P,] R, C, 3)
        if not _valid_profiles(self.alpha, self.beta, np.shape(mass)):     # (..., R, C) and (..., R, C, NSEG)
            raise FlowBSDFError(f"alpha and beta are profiles: the logs of {NSEG} nodes over the first, "
                                f"within +-{K_MAX:g}, one more axis than mass")
        self.meta = dict(meta or {})
        self.backend = backend      # "auto" (C when available, see _fast), "numpy", "c"
        self.rows = self.a_edges.shape[-1] - 1
        self.cols = self.b_edges.shape[-1] - 1
        # The working copies have one bin axis: bin k (isotropic), or k * P + p.
        flat = lambda x, tail: x.reshape((-1,) + x.shape[x.ndim - tail:])      # noqa: E731
        # float64 working copies; the stored values (float32, float16) define the sampler exactly.
        self._a = flat(self.a_edges, 1).astype(np.float64)
        self._b = flat(self.b_edges, 2).astype(np.float64)
        # The outer edges are the hemisphere's: exactly 0 and 1 in a, 0 and 2 pi in b
        # (float32(2 pi) exceeds 2 pi, which would wrap the last column's end onto the first).
        self._a[:, 0], self._a[:, -1] = 0.0, 1.0
        self._b[..., 0], self._b[..., -1] = 0.0, TWO_PI
        self._alpha = profile_nodes(flat(self.alpha, 3))     # node values, normalized per bin
        self._beta = profile_nodes(flat(self.beta, 3))
        self._w = flat(self.weights, 3).astype(np.float32)
        m = flat(self.mass, 2).astype(np.float64)
        m /= m.sum(axis=(1, 2), keepdims=True)
        self._m = m
        self._col_cum = np.concatenate([np.zeros(m.shape[:2] + (1,)), np.cumsum(m, axis=2)], axis=2)
        row_mass = self._col_cum[:, :, -1]
        self._row_cdf = np.concatenate([np.zeros((len(m), 1)), np.cumsum(row_mass, axis=1)], axis=1)

    @property
    def anisotropic(self):
        return self.phi_bins is not None

    # -- C fast path ------------------------------------------------------------------
    # sample/pdf/invert/eval hand their inputs to bake/maths/fasttables.py (C, same results to a
    # few ulps, 3-10x faster) when it is loaded and takes them; the numpy code in each method
    # is the reference. backend="numpy" (or FLOWBSDF_NO_C=1 in the environment) keeps to
    # numpy; backend="c" raises when the C library is not available (its reason says why).

    @property
    def _fast(self):
        if self.backend == "numpy" or (self.anisotropic and self.coords != "halfvector"):     # C: not old wo files
            return None
        if _fasttables is None or not _fasttables.AVAILABLE:
            if self.backend == "c":
                raise FlowBSDFError("the C tables library is not available: "
                                    + (_fasttables.REASON if _fasttables else "bake.maths.fasttables did not import"))
            return None
        return _fasttables

    # -----------------------------------------------------------------------------------

    @property
    def layouts(self):
        """(each working bin's layout, the first bin of each layout): bins whose cell edges are
        the same (a layout group's: tabulate.join_groups) share one layout, stored once."""
        B = len(self._a)
        a, b = self.a_edges.reshape(B, -1), self.b_edges.reshape(B, -1)
        seen, index, first = {}, np.empty(B, np.int64), []
        for k in range(B):
            key = a[k].tobytes() + b[k].tobytes()
            if key not in seen:
                seen[key] = len(first)
                first.append(k)
            index[k] = seen[key]
        return index, np.array(first, np.int64)

    @property
    def nbytes(self):
        """The bytes the tables hold as stored: the cells' arrays, the edges once per layout."""
        edges = (self.a_edges.nbytes + self.b_edges.nbytes) // len(self._a) * len(self.layouts[1])
        return edges + sum(x.nbytes for x in (self.mass, self.alpha, self.beta, self.weights))

    def _bins(self, wi):
        """Per sample: the bins to blend, (N, n) indices on the working copies' bin axis and
        (N, n) weights (2 bins isotropic, 4 anisotropic), and the coordinates' reference:
        phi_ref ("wo") or the angle of the frame h is mapped in ("halfvector")."""
        theta, phi = theta_phi(wi)
        K = len(self.theta_bins)
        if K == 1:
            k, t = np.zeros(len(theta), np.int64), np.zeros(len(theta))
        else:
            k = np.clip(np.searchsorted(self.theta_bins, theta, side="right") - 1, 0, K - 2)
            # Weights linear in cos(theta_i): the mirror direction's a = 1 - cos(theta_i), the
            # edges' main anchor, then moves exactly as the interpolated edges do.
            c = np.cos(self.theta_bins)
            t = np.clip((c[k] - np.cos(theta)) / (c[k] - c[k + 1]), 0.0, 1.0)
        corners = [(k, 1.0 - t), (np.minimum(k + 1, K - 1), t)]
        ref = phi + np.pi
        if self.anisotropic:
            P, period, starts = len(self.phi_bins), self.phi_period, self.phi_bins - self.phi_bins[0]
            if self.coords == "halfvector":
                # phi_bins span the period closed (the last at the first + period): phi_i turned
                # back into it by whole periods, the material's symmetry; h is mapped in the
                # frame turned alike, plus the lobe's axes.
                turns = np.floor((phi - self.phi_bins[0]) / period)
                x = phi - self.phi_bins[0] - turns * period
                p = np.clip(np.searchsorted(starts, x, side="right") - 1, 0, P - 2)
                nxt, end = p + 1, starts[p + 1]
                ref = turns * period + self.frame_angle
            else:
                # phi_i within the period, from the first bin; the gap after the last bin wraps to
                # the first one (+ period). x == period after rounding gives s = 1 on bin 0: right.
                x = np.mod(phi - self.phi_bins[0], period)
                p = np.clip(np.searchsorted(starts, x, side="right") - 1, 0, P - 1)
                nxt, end = (p + 1) % P, np.append(starts[1:], period)[p]
            s = np.clip((x - starts[p]) / (end - starts[p]), 0.0, 1.0)
            corners = [(kk * P + pp, wk * wp) for kk, wk in corners for pp, wp in ((p, 1.0 - s), (nxt, s))]
        return (np.stack([c[0] for c in corners], axis=1), np.stack([c[1] for c in corners], axis=1)), ref

    @staticmethod
    def _lerp(table, bins, *idx):
        """The blend of table[bin, *idx] over the bins (a convex combination per sample)."""
        ks, ws = bins
        out = 0.0
        for c in range(ks.shape[1]):
            v = table[(ks[:, c], *idx)]
            out = out + ws[:, c].reshape((-1,) + (1,) * (v.ndim - 1)) * v
        return out

    def _cell(self, bins, i, j):
        """Edges, probability and the blended profiles' node values of cell (i, j) of the
        interpolated table."""
        L = self._lerp
        a0, a1 = L(self._a, bins, i), L(self._a, bins, i + 1)
        b0, b1 = L(self._b, bins, i, j), L(self._b, bins, i, j + 1)
        return a0, a1, b0, b1, L(self._m, bins, i, j), L(self._alpha, bins, i, j), L(self._beta, bins, i, j)

    def sample(self, wi, u):
        if (fast := self._fast) is not None and (out := fast.sample(self, wi, u)) is not None:
            return out      # C fast path; the numpy reference follows
        u = np.atleast_2d(np.asarray(u, np.float64))
        wi, _ = as_dirs(wi, np.empty((len(u), 3)))
        bins, phi_ref = self._bins(wi)
        L = self._lerp
        i = _search(u[:, 0], self.rows, lambda m: L(self._row_cdf, bins, m))
        c0, c1 = L(self._row_cdf, bins, i), L(self._row_cdf, bins, i + 1)
        v = u[:, 1] * (c1 - c0)
        j = _search(v, self.cols, lambda m: L(self._col_cum, bins, i, m))
        d0 = L(self._col_cum, bins, i, j)
        a0, a1, b0, b1, m, pa, pb = self._cell(bins, i, j)
        x, dx = profile_sample(np.clip((u[:, 0] - c0) / (c1 - c0), 0.0, 1.0), pa)
        y, dy = profile_sample(np.clip((v - d0) / m, 0.0, 1.0), pb)
        pdf = m * dx * dy / ((a1 - a0) * (b1 - b0))
        a, b = a0 + x * (a1 - a0), b0 + y * (b1 - b0)
        if self.coords != "wo":
            wo, jac = H_MAPS[self.coords][0](wi, a, b, phi_ref)
            return wo, pdf / jac
        return from_ab(a, b, phi_ref), pdf

    def _locate(self, wi, wo):
        bins, phi_ref = self._bins(wi)
        if self.coords != "wo":
            a, b, jac = H_MAPS[self.coords][1](wi, wo, phi_ref)
        else:
            a, b, jac = *to_ab(wo, phi_ref), 1.0
        L = self._lerp
        i = _search(a, self.rows, lambda m: L(self._a, bins, m))
        j = _search(b, self.cols, lambda m: L(self._b, bins, i, m))
        a0, a1, b0, b1, m, pa, pb = self._cell(bins, i, j)
        x = np.clip((a - a0) / (a1 - a0), 0.0, 1.0)
        y = np.clip((b - b0) / (b1 - b0), 0.0, 1.0)
        pdf = m * profile_density(x, pa) * profile_density(y, pb) / ((a1 - a0) * (b1 - b0)) / jac
        return bins, i, j, x, y, pa, pb, pdf

    def pdf(self, wi, wo):
        if (fast := self._fast) is not None and (out := fast.pdf(self, wi, wo)) is not None:
            return out      # C fast path; the numpy reference follows
        wi, wo = as_dirs(wi, wo)
        pdf = self._locate(wi, wo)[-1]
        return np.where(wo[:, 2] > 0, pdf, 0.0)

    def invert(self, wi, wo):
        if (fast := self._fast) is not None and (out := fast.invert(self, wi, wo)) is not None:
            return out      # C fast path; the numpy reference follows
        wi, wo = as_dirs(wi, wo)
        bins, i, j, x, y, pa, pb, _ = self._locate(wi, wo)
        L = self._lerp
        c0, c1 = L(self._row_cdf, bins, i), L(self._row_cdf, bins, i + 1)
        d0, d1 = L(self._col_cum, bins, i, j), L(self._col_cum, bins, i, j + 1)
        u1 = c0 + profile_cdf(x, pa) * (c1 - c0)
        u2 = (d0 + profile_cdf(y, pb) * (d1 - d0)) / (c1 - c0)
        return np.stack([u1, u2], axis=-1)

    def eval(self, wi, wo):
        """The baked BSDF f (RGB): the cell's estimator weight W x pdf / cos(theta_o)."""
        if (fast := self._fast) is not None and (out := fast.eval(self, wi, wo)) is not None:
            return out      # C fast path; the numpy reference follows
        wi, wo = as_dirs(wi, wo)
        bins, i, j, _, _, _, _, pdf = self._locate(wi, wo)
        w = self._lerp(self._w, bins, i, j)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = w * (pdf / wo[:, 2])[:, None]
        return np.where(((wo[:, 2] > 0) & (wi[:, 2] > 0))[:, None], f, 0.0)

    # -- files -----------------------------------------------------------------------

    def save(self, path):
        meta = {**self.meta, "format": "flowbsdf-tables", "format_version": FORMAT_VERSION,
                "theta_bins": [float(x) for x in self.theta_bins], "rows": self.rows, "cols": self.cols}
        if self.anisotropic:
            meta.update(phi_bins=[float(x) for x in self.phi_bins], phi_period=self.phi_period)
        if self.coords != "wo":
            meta.update(coords=self.coords, frame_angle=self.frame_angle)
        arrays, meta["layouts"] = _file_arrays(self)
        write_exr(path, arrays, meta)


    # -- per working bin, its own rows and columns (MixedTables pads to the largest) ----------

    @property
    def bin_rows(self):
        return np.full(len(self._a), self.rows, np.int64)

    @property
    def bin_cols(self):
        return np.full(len(self._a), self.cols, np.int64)


# A padded working entry (MixedTables) past a group's own rows or columns: above every value a
# search compares with it, so a search finds the last entry at or below its target among the
# group's own (a finite value: blending it with weight 0 must give 0, not NaN).
PAD = 1e30
MIXED_FORMAT_VERSION = MIXED_FORMAT     # the file of a MixedTables (bake/formats.py)
# The formats this FlowBSDF reads: (kind, whether the edges are stored once per layout)
READS = {3: ("plain", False), 4: ("mixed", False), FORMAT_VERSION: ("plain", True),
         MIXED_FORMAT_VERSION: ("mixed", True)}


class MixedTables:
    """Isotropic tables in layout groups of their own resolutions (cells per bin): consecutive
    `parts`, each a Tables over its own bins, each part's first bin at the previous part's last
    angle. theta_i below a boundary is sampled from the lower part, at or above it from the
    upper one (the rule of groups within one Tables, groups_ok): the parts never blend, so each
    is exact on its own and together they are one exact sampler. An easy range of theta_i then
    spends less memory on cells and the hard one more (plan_tables).

    The back ends that read whole arrays (the OSL and SVM textures) see the parts joined, padded
    to the largest part's rows and columns: the working copies below, with `bin_rows` and
    `bin_cols` each bin's own, and PAD past them."""

    name = "tables"
    normalized = True
    anisotropic = False
    phi_bins = None
    phi_period = TWO_PI
    frame_angle = 0.0

    def __init__(self, parts, meta=None, backend="auto"):
        parts = list(parts)
        if len(parts) < 2 or any(not isinstance(p, Tables) or p.anisotropic for p in parts):
            raise FlowBSDFError("mixed tables join two or more isotropic Tables")
        if len({p.coords for p in parts}) != 1:
            raise FlowBSDFError("the parts of mixed tables share their coordinates")
        for lower, upper in zip(parts[:-1], parts[1:]):
            if len(lower.theta_bins) < 2 or len(upper.theta_bins) < 2 or upper.theta_bins[0] != lower.theta_bins[-1]:
                raise FlowBSDFError("each part of mixed tables starts at the previous one's last angle, "
                                    "two bins or more each")
        self.parts = parts
        self.coords = parts[0].coords
        self.theta_bins = np.concatenate([p.theta_bins for p in parts])
        self.bounds = np.array([p.theta_bins[0] for p in parts[1:]])
        self.rows = max(p.rows for p in parts)
        self.cols = max(p.cols for p in parts)
        self.meta = dict(meta or {})
        self.backend = backend

    @property
    def backend(self):
        return self.parts[0].backend

    @backend.setter
    def backend(self, value):
        for p in self.parts:
            p.backend = value

    @property
    def nbytes(self):
        return sum(p.nbytes for p in self.parts)

    def part_at(self, theta_i):
        """The index of the part that samples theta_i (array or scalar)."""
        return np.searchsorted(self.bounds, theta_i, side="right")

    @property
    def _fast(self):
        return self.parts[0]._fast

    def _each(self, method, wi, x):
        """method of the part each wi falls in, per sample (x: the other argument, (N, ...)).
        The C fast path picks the parts itself (fasttables: in C, without the passes below)."""
        if (fast := self._fast) is not None and (out := getattr(fast, method)(self, wi, x)) is not None:
            return out
        x = np.atleast_2d(np.asarray(x, np.float64))
        if np.shape(wi) in ((3,), (1, 3)):     # one direction: one part, wi passed on as it is
            return getattr(self.parts[int(self.part_at(theta_phi(np.reshape(wi, (1, 3)))[0][0]))], method)(wi, x)
        wi, _ = as_dirs(wi, np.empty((len(x), 3)))
        part = self.part_at(theta_phi(wi)[0])
        outs = None
        for p in np.unique(part):
            sel = part == p
            got = getattr(self.parts[p], method)(wi[sel], x[sel])
            got = got if isinstance(got, tuple) else (got,)
            if outs is None:
                outs = [np.empty((len(x),) + g.shape[1:], g.dtype) for g in got]
            for o, g in zip(outs, got):
                o[sel] = g
        return tuple(outs) if len(outs) > 1 else outs[0]

    def sample(self, wi, u):
        return self._each("sample", wi, u)

    def pdf(self, wi, wo):
        return self._each("pdf", wi, wo)

    def invert(self, wi, wo):
        return self._each("invert", wi, wo)

    def eval(self, wi, wo):
        return self._each("eval", wi, wo)

    # -- the parts joined, padded to the largest (the textures' exporters) ------------------

    def _joined(self, name, pad):
        """The parts' working copy `name` side by side, each padded with `pad` to the largest."""
        out = []
        for p in self.parts:
            x = getattr(p, name)
            shape = list(x.shape)
            shape[1] = self.rows + (name in ("_a", "_row_cdf"))
            if x.ndim > 2:
                shape[2] = self.cols + (name in ("_b", "_col_cum"))
            y = np.full(shape, pad, x.dtype)
            y[tuple(slice(0, n) for n in x.shape)] = x
            out.append(y)
        return np.concatenate(out)

    _a = functools.cached_property(lambda self: self._joined("_a", PAD))
    _row_cdf = functools.cached_property(lambda self: self._joined("_row_cdf", PAD))
    _b = functools.cached_property(lambda self: self._joined("_b", PAD))
    _col_cum = functools.cached_property(lambda self: self._joined("_col_cum", PAD))
    _m = functools.cached_property(lambda self: self._joined("_m", 0.0))
    _alpha = functools.cached_property(lambda self: self._joined("_alpha", 1.0))
    _beta = functools.cached_property(lambda self: self._joined("_beta", 1.0))
    _w = functools.cached_property(lambda self: self._joined("_w", 0.0))

    @property
    def bin_rows(self):
        return np.concatenate([p.bin_rows for p in self.parts])

    @property
    def bin_cols(self):
        return np.concatenate([p.bin_cols for p in self.parts])

    # -- files -----------------------------------------------------------------------

    def save(self, path):
        meta = {**self.meta, "format": "flowbsdf-tables", "format_version": MIXED_FORMAT_VERSION,
                "theta_bins": [float(x) for x in self.theta_bins], "rows": self.rows, "cols": self.cols,
                "parts": [{"bins": len(p.theta_bins), "rows": p.rows, "cols": p.cols} for p in self.parts]}
        if self.coords != "wo":
            meta["coords"] = self.coords
        arrays = {}
        for n, (p, about) in enumerate(zip(self.parts, meta["parts"])):
            own, about["layouts"] = _file_arrays(p)
            arrays.update({f"{name}{_suffix(n)}": x for name, x in own.items()})
        write_exr(path, arrays, meta)


def _suffix(part):
    """The file's array names of part n of mixed tables: a_edges, ..., a_edges.1, ..."""
    return f".{part}" if part else ""


def _file_arrays(tab):
    """The 2D arrays a table file holds for tab (one part of mixed tables, or the whole), the
    edges once per layout, and each bin's layout (a list)."""
    B, R, C = len(tab._a), tab.rows, tab.cols
    index, first = tab.layouts
    per = {"mass": 1, "alpha": NSEG, "beta": NSEG}
    return {"a_edges": tab.a_edges.reshape(B, R + 1)[first],
            "b_edges": tab.b_edges.reshape(B, R, C + 1)[first].reshape(len(first) * R, C + 1),
            **{n: getattr(tab, n).reshape(B * R, C * per[n]) for n in tab.ARRAYS},
            "weights": tab.weights.reshape(B * R, C * 3)}, [int(i) for i in index]


def _bins_of(meta, key, path, hi, lo=0.0, closed=True, groups=False):
    """The increasing list meta[key] within [lo, hi] (hi excluded unless closed), or FlowBSDFError.
    groups: an inner angle may appear twice, the boundary of two layout groups (groups_ok)."""
    try:
        bins = np.asarray(meta[key], np.float64)
    except (TypeError, ValueError):
        bins = np.array([np.nan])
    if (bins.ndim != 1 or len(bins) < 1 or not np.all(np.isfinite(bins))
            or not (groups_ok(bins) if groups else np.all(np.diff(bins) > 0))
            or bins[0] < lo or (bins[-1] > hi if closed else bins[-1] >= hi)):
        raise FlowBSDFError(f"{key} {meta[key]!r} must be increasing angles in [{lo:g}, {hi:g}"
                            f"{']' if closed else ')'}{' (an inner one at most twice)' if groups else ''}: "
                            "corrupt file", path)
    return bins


def groups_ok(theta_bins):
    """theta_bins increasing, where an inner angle may appear twice: the last bin of one layout
    group and the first of the next (tabulate.join_groups). theta_i below it blends the lower
    group's bins, at or above it the upper group's: bins are found by the count of those <= theta_i,
    so the empty interval between the two is never used (not at the ends: past the last bin the
    last interval is used, and it must not be empty)."""
    d = np.diff(np.asarray(theta_bins, np.float64))
    return bool(np.all(d >= 0) and (len(d) == 0 or (d[0] > 0 and d[-1] > 0))
                and not np.any((d[:-1] == 0) & (d[1:] == 0)))


def _phi_period(meta, path):
    """The period of phi_bins: 2 pi / n for a whole n (2 pi when absent)."""
    period = meta.get("phi_period", TWO_PI)
    n = TWO_PI / period if isinstance(period, (int, float)) and not isinstance(period, bool) and period > 0 else 0.0
    if not (np.isfinite(n) and n >= 1 - 1e-9 and abs(n - round(n)) < 1e-9):
        raise FlowBSDFError(f"phi_period {period!r} must be 2 pi / n for a whole n: corrupt file", path)
    return float(period)


def open_tables(path):
    """The Tables (or MixedTables) of a table file; FlowBSDFError saying what is wrong with it."""
    arrays, meta = read_exr(path)
    if meta.get("format") != "flowbsdf-tables":
        raise FlowBSDFError("not a FlowBSDF table file", path)
    version = meta.get("format_version")
    if isinstance(version, bool) or version not in READS:
        raise FlowBSDFError(f"table format version {version} (this FlowBSDF reads versions "
                            f"{', '.join(map(str, sorted(READS)))}); re-bake it", path)
    try:
        theta_bins = _bins_of(meta, "theta_bins", path, 0.5 * np.pi, groups=meta.get("phi_bins") is None)
        kind, shared = READS[version]
        if kind == "plain":
            return _open_part(arrays, meta, path, "", theta_bins, int(meta["rows"]), int(meta["cols"]), meta,
                              meta["layouts"] if shared else None)
        parts = meta["parts"]
        counts = [int(p["bins"]) for p in parts]
        if (meta.get("phi_bins") is not None or len(parts) < 2 or sum(counts) != len(theta_bins)
                or any(c < 2 for c in counts)):
            raise FlowBSDFError(f"mixed tables' parts {parts!r} do not cover their {len(theta_bins)} isotropic "
                                "bins: corrupt file", path)
        starts = np.cumsum([0] + counts)
        return MixedTables([_open_part(arrays, meta, path, _suffix(n), theta_bins[s:s + c], int(p["rows"]),
                                       int(p["cols"]), {}, p["layouts"] if shared else None)
                            for n, (p, s, c) in enumerate(zip(parts, starts, counts))], meta)
    except KeyError as e:
        raise FlowBSDFError(f"table file is incomplete (truncated or damaged?): {e} is missing", path) from None
    except (TypeError, ValueError) as e:
        raise FlowBSDFError(f"table metadata is malformed: {e}", path) from None


def _open_part(arrays, meta, path, suffix, theta_bins, R, C, own_meta, layouts=None):
    """The Tables of the arrays named <name><suffix> (a whole file: suffix ""); layouts: each
    bin's row of the edges (None: one per bin)."""
    a, b, w = arrays["a_edges" + suffix], arrays["b_edges" + suffix], arrays["weights" + suffix]
    cells = [arrays[n + suffix] for n in Tables.ARRAYS]
    phi_bins, period = None, TWO_PI
    if meta.get("phi_bins") is not None:       # anisotropic: bins over phi_i within one period
        period = _phi_period(meta, path)
        closed = meta.get("coords") == "halfvector"     # the last bin at the first + period
        phi_bins = _bins_of(meta, "phi_bins", path, 2 * period if closed else period, closed=closed)
        if closed and (len(phi_bins) < 2 or not np.isclose(phi_bins[-1] - phi_bins[0], period)):
            raise FlowBSDFError(f"phi_bins {meta['phi_bins']!r} of halfvector tables must close the period "
                                f"{period:g}: corrupt file", path)
    coords = meta.get("coords", "wo")
    if coords not in COORDS:
        raise FlowBSDFError(f"table coordinates {coords!r} are unknown (this FlowBSDF reads {list(COORDS)}); "
                            "re-bake it", path)
    K, P = len(theta_bins), 1 if phi_bins is None else len(phi_bins)
    B = K * P
    per = [1, NSEG, NSEG]
    shapes = [w.shape] + [c.shape for c in cells]
    if shapes != [(B * R, C * 3)] + [(B * R, C * n) for n in per]:
        raise FlowBSDFError(f"table shapes {shapes} do not match {K} x {P} bins of {R}x{C}", path)
    layouts = np.arange(B) if layouts is None else np.asarray(layouts)
    L = len(a)
    if (layouts.shape != (B,) or layouts.dtype.kind not in "iu" or np.any(layouts < 0)
            or not np.array_equal(np.unique(layouts), np.arange(L))):
        raise FlowBSDFError(f"layouts {layouts.tolist()!r} must name one of the {L} stored cell layouts for each "
                            f"of the {B} bins, each layout used: corrupt file", path)
    if [a.shape, b.shape] != [(L, R + 1), (L * R, C + 1)]:
        raise FlowBSDFError(f"table edge shapes {[a.shape, b.shape]} do not match {L} layouts of {R}x{C}", path)
    if any(x.dtype != np.float32 for x in (a, b, cells[0])):
        raise FlowBSDFError("table edges and masses must be float32: corrupt file", path)
    if not all(np.all(np.isfinite(x)) for x in (a, b, w, *cells)):
        raise FlowBSDFError("table holds NaN or inf", path)
    mass, alpha, beta = cells
    if (np.any(np.diff(a, axis=1) <= 0) or np.any(np.diff(b, axis=1) <= 0) or np.any(mass <= 0)
            or not _valid_profiles(alpha.reshape(*mass.shape, NSEG), beta.reshape(*mass.shape, NSEG), mass.shape)):
        raise FlowBSDFError("table edges not increasing, masses not positive or profiles out of "
                            "range: corrupt file", path)
    lead = (K,) if phi_bins is None else (K, P)
    a, b = a[layouts], b.reshape(L, R, C + 1)[layouts]
    return Tables(theta_bins, a.reshape(*lead, R + 1), b.reshape(*lead, R, C + 1),
                  mass.reshape(*lead, R, C), *(c.reshape(*lead, R, C, NSEG) for c in (alpha, beta)),
                  w.reshape(*lead, R, C, 3), own_meta,
                  phi_bins=phi_bins, phi_period=period, coords=coords, frame_angle=float(meta.get("frame_angle", 0.0)))
