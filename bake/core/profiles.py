"""The cells' 1-D profiles: the density a table spreads a cell's mass with along each axis.

In local coordinates x in [0, 1] across a cell, a profile is NSEG pieces, log-linear between
NSEG + 1 node values: each piece an exponential e_k(t) = k e^(k t) / (e^k - 1) (uniform at
k = 0), no steeper than K_MAX across a whole cell. An exponential follows a lobe's flank where a
linear slope cannot, and the pieces meet continuously, so a profile also holds a knee inside a
cell (a flank running into a flat tail) that one exponential cannot. Tables (tables.py) gives
each cell two, p_a(x) p_b(y); here their CDF, inverse CDF and density, which the back ends port
(the C path, OSL's tables.h, the SVM graph's tables.py).

A profile is stored as the logs of its nodes 1..NSEG over node 0; each bin's is normalized
to integrate to 1 (profile_nodes) and the bins blend node values: at the nodes the blended
density is the mixture of the bins' (the blend follows the mixture, never a steep piece
displaced off the flank it was fitted to: blending exponentials' rates did that, e^-17 below
f·cos, rv 8.5e4 x the ideal's on a measured file; leans, then node values, followed the mixture).
"""
import numpy as np

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


def exp_mean(k):
    """The mean of x under the exponential density of rate k on [0, 1]."""
    ks = np.where(np.abs(k) < _SMALL, 1.0, k)
    return np.where(np.abs(k) < _SMALL, 0.5 + k / 12.0, 1.0 / (-np.expm1(-ks)) - 1.0 / ks)


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


def _valid_profiles(alpha, beta, mass_shape):
    """Profiles' logs (alpha, beta) with one axis of NSEG more than mass, finite, within +-K_MAX
    (a piece's bound times NSEG)."""
    return all(np.shape(x) == (*mass_shape, NSEG) and np.all(np.isfinite(x)) and np.all(np.abs(x) <= K_MAX * 1.01)
               for x in (alpha, beta))
