"""Opening table files (.exr): open_tables, the versions it reads, and the checks that name what is
wrong with a damaged file. Writing is the samplers' own: Tables.save (tables.py), MixedTables.save
(mixed_tables.py).
"""
import numpy as np

from ..errors import FlowBSDFError
from ..io.exrio import read_exr
from .mixed_tables import MIXED_FORMAT_VERSION, MixedTables, _suffix
from .profiles import NSEG, _valid_profiles
from .tables import COORDS, FORMAT_VERSION, TWO_PI, Tables, groups_ok

# The formats this FlowBSDF reads: (kind, whether the edges are stored once per layout)
READS = {3: ("plain", False), 4: ("mixed", False), FORMAT_VERSION: ("plain", True),
         MIXED_FORMAT_VERSION: ("mixed", True)}


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
