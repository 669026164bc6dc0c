"""MixedTables: isotropic tables in layout groups of their own resolutions, one exact sampler
made of consecutive Tables (tables.py) that never blend, and their file (MIXED_FORMAT_VERSION;
opened by table_files.open_tables).
"""
import functools

import numpy as np

from ..errors import FlowBSDFError
from ..formats import MIXED_FORMAT
from ..io.exrio import write_exr
from ..materials.base import as_dirs
from ..maths.geometry import theta_phi
from .tables import TWO_PI, Tables, _file_arrays

# A padded working entry (MixedTables) past a group's own rows or columns: above every value a
# search compares with it, so a search finds the last entry at or below its target among the
# group's own (a finite value: blending it with weight 0 must give 0, not NaN).
PAD = 1e30
MIXED_FORMAT_VERSION = MIXED_FORMAT     # the file of a MixedTables (bake/formats.py)


class MixedTables:
    """Isotropic tables in layout groups of their own resolutions (cells per bin): consecutive
    `parts`, each a Tables over its own bins, each part's first bin at the previous part's last
    angle. theta_i below a boundary is sampled from the lower part, at or above it from the
    upper one (the rule of groups within one Tables, tables.groups_ok): the parts never blend, so each
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
