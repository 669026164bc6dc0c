"""Baked conditional tables: an exact, table-speed sampler per material.

Per incident bin, the table is an adaptive piecewise density on the hemisphere: R rows in
a = 1 - cos(theta_o) and, in each row, C columns in b = phi_o - phi_i (the azimuth relative
to wi's plane; the mirror direction sits at b = pi, so the specular lobe never straddles
the seam); da db = d omega. Cell (i, j) holds mass m_ij, spread over it with a separable
density: in local coordinates x, y in [0, 1], q(x, y) = p_a(x) p_b(y), each a *profile*
(profiles.py): NSEG pieces, log-linear between NSEG + 1 node values, each an exponential.
A profile holds a knee inside a cell (a flank running into a flat tail) that one exponential
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
fading between two positions (a displacement interpolation). The profiles blend as their
node values (profiles.py says why).

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

This is the reference every back end transcribes (the C path, OSL's tables.h, the SVM graph's
tables.py): sample, pdf, invert and eval with the coordinate maps; the cells' profiles are
profiles.py's. Tables in layout groups of their own resolutions are mixed_tables.py's
MixedTables; table files are opened by table_files.open_tables.
"""
import numpy as np

from ..errors import FlowBSDFError
from ..formats import FORMAT
from ..io.exrio import write_exr
from ..materials.base import as_dirs
from ..maths.geometry import atan2, theta_phi
from . import halfvector
from .profiles import K_MAX, NSEG, _valid_profiles, profile_cdf, profile_density, profile_nodes, profile_sample

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


HALF_MAX = 65504.0      # the largest float16


def _stored(x):
    """An array as Tables keeps it: float16 when given so (the builder's profiles and weights,
    tabulate._finish_bin), else float32."""
    x = np.asarray(x)
    return x if x.dtype == np.float16 else x.astype(np.float32)


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


def groups_ok(theta_bins):
    """theta_bins increasing, where an inner angle may appear twice: the last bin of one layout
    group and the first of the next (tabulate.join_groups). theta_i below it blends the lower
    group's bins, at or above it the upper group's: bins are found by the count of those <= theta_i,
    so the empty interval between the two is never used (not at the ends: past the last bin the
    last interval is used, and it must not be empty)."""
    d = np.diff(np.asarray(theta_bins, np.float64))
    return bool(np.all(d >= 0) and (len(d) == 0 or (d[0] > 0 and d[-1] > 0))
                and not np.any((d[:-1] == 0) & (d[1:] == 0)))


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
