"""The search guides the OSL and SVM textures store (osl_export, svm_export): where a binary search
over cumulative sums may start, and how far it may run within a corner's own rows and columns."""
import numpy as np


def guide(cum, totals, count):
    """(count, 2) brackets over the last axis of the cumulative sums `cum` (n_bins, n + 1)
    whose totals are `totals` (n_bins,): for u in [g, g + 1) / count, the index searched for
    (the last i with sum_b w_b cum_b[i] <= u sum_b w_b totals_b, any weights w >= 0) lies in
    [lo, hi). Bins of total 0 add nothing to the blend and are left out."""
    n = cum.shape[1] - 1
    live = totals > 0
    if not live.any():
        return np.tile([0.0, n], (count, 1))
    cum, totals = cum[live], totals[live]
    g = np.arange(count)
    # cum is non-decreasing: counting the entries below / above a fraction finds the last
    # index below it and the first above it, per bin and g.
    below = np.sum(cum[:, None, :] < (g / count)[None, :, None] * totals[:, None, None], axis=2)
    above = np.sum(cum[:, None, :] > ((g + 1) / count)[None, :, None] * totals[:, None, None], axis=2)
    lo = np.maximum(below - 1, 0).min(0)
    hi = np.minimum(n + 1 - above, n).max(0)
    # One index more on each side: the shader's target carries float32 rounding (its column
    # target u1 (c1 - c0) comes from the row CDF, not from the row's own sums).
    return np.stack([np.maximum(lo - 1, 0), np.minimum(hi + 1, n)], axis=1).astype(np.float64)


def own_size(tables, bins):
    """A corner's rows and columns: its bins' own (MixedTables pads its parts' to the largest).
    Its bins share them, but at the boundary of two parts (two bins at one angle, never blended):
    that corner's searches stay within the smaller's."""
    return int(tables.bin_rows[bins].min()), int(tables.bin_cols[bins].min())
