"""Learned flow samplers, numpy only: exact sampling, densities and inverses of a trained model.

A model maps u in [0,1)² to an outgoing direction wo, conditioned on the incident
direction wi, in three bijective pieces:

    u --(inverse CDF of the base)--> y0 --(N Euler steps of the velocity MLP)--> y1
      --(fixed coordinate map, flow_maps.py)--> wo

Flow coordinates y live on an unbounded space: flow_maps.py (disk, spherical, slope) maps
them to directions, and its docstring says how.

Base (conditioned on wi through a small MLP): disk, a diagonal Gaussian (or a scale
mixture) in y; spherical and slope, a Gaussian in s times a von Mises in phi. u maps to it
through the inverse CDFs (special.py: ndtri for the Gaussian, numerical inversion of the von
Mises CDF).

Each Euler step y_{k+1} = y_k + D(y_k, t_k, c) / N, t_k = k / N, multiplies the density by
1 / det(I + J_k / N), J_k = dD/dy (2x2, analytic forward-mode derivatives of the MLP), so

    log p_y(y1) = log p0(y0) - sum_k log det(I + J_k / N).

The inverse solves every Euler step exactly backwards by Newton's method. Isotropic
materials are conditioned on theta_i only: wi is rotated to phi_i = 0 and wo rotated back.

Precision: sample/pdf/invert agree to float precision (invert(sample(u)) == u, pdf(sample)
== returned pdf, ~1e-12). u is a double in [0,1): u = 0 is clipped to 1e-17 (z = -8.5) and
the upper tail resolves only down to 1 - u ~ 1e-16 (z ~ 8.2), so for directions whose base
point lies beyond that (probability < 1e-15) invert() saturates and sample(invert(wo)) is
only approximately wo; pdf(wo) stays exact there.
The slope map recovers h from wo + wi, which a float64 wo holds only to
~1e-16 absolute: within ~1e-5 rad of the mirror direction pdf/invert agree with sample to
~1e-9 instead of 1e-12, and within 1e-12 rad (u at its extremes) only to ~1e-2.
Defensive mixture: a model may carry `defensive` = eps in [0, MAX_DEFENSIVE] (chosen by the trainer
on held-out relative variance; 0 in version-1 files): sample() then draws wo uniformly over the
hemisphere with probability eps (u1 < eps) and from the flow otherwise (u1 rescaled), and every
density is the mixture's, (1 - eps) p_flow + eps / (2 pi). Why: the rv of a flow alone can be
infinite where the target has heavier tails than the flow's pdf: measured data keeps f·cos > 0
up to the horizon, where a disk flow's pdf vanishes like cos; a GGX lobe's density in the slope
map decays exponentially toward the mirror direction (s -> -inf), a Gaussian in s faster. The
uniform share bounds w = f·cos / pdf by 2 pi f·cos / eps. The sampler is then two-to-one:
invert() returns the flow component's u (in [eps, 1) x [0, 1)); sample(invert(wo)) == wo still.
If det(I + J/N) <= 0 somewhere the Euler map folds (not a bijection there, pdf wrong):
`last_stats["fold_fraction"]` reports it; trained models are checked for it.

File format: one `.npz` (no pickles) holding float32 weight arrays `base.W0`, `base.b0`,
..., `vel.W0`, ... (torch's Linear layout, (out, in)) and `meta`, a JSON string with
`format` = "flowbsdf-flow", `version`, `domain`, `isotropic`, `steps`, the architecture
and whatever training facts the trainer records (material fingerprint, preset, metrics).
All arithmetic here is float64.
"""
import copy
import json
import math
import zipfile
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from ..maths.special import (LOG_2PI, logsumexp, log_normal_pdf, mix_radial_cdf, mix_radial_icdf, ndtr, ndtri,
                             vm_cdf, vm_icdf, vm_log_pdf, vm_terms, wrap_angle)
from ..maths.warps import rotate_z
from .baselines import UniformSampler
from .domains import get_domain
from .flow_maps import MAPS

FORMAT = "flowbsdf-flow"
VERSION = 2                      # 2 added `defensive`; version-1 files load with defensive = 0
READS_VERSIONS = (1, 2)
MAX_DEFENSIVE = 0.5
UNIFORM_PDF = 0.5 / math.pi      # uniform over the hemisphere, per steradian
# u is clipped into [U_MIN, 1 - 2^-53] so that u = 0 (probability 2^-53) maps to a finite point.
U_MIN = 1e-17
# Disk base mixtures: component k's log scale relative to the broadest, lam_k, lies in (-LAM_MIN_ABS, 0].
LAM_MIN_ABS = 8.0


def with_uniform_share(pdf, eps):
    """The defensive mixture's density from the flow's own: (1 - eps) pdf + eps uniform."""
    return (1.0 - eps) * pdf + eps * UNIFORM_PDF if eps else pdf


def _check_defensive(eps, path=None):
    if not 0.0 <= float(eps) <= MAX_DEFENSIVE:
        raise FlowBSDFError(f"defensive weight {eps} must be in [0, {MAX_DEFENSIVE}]", path)
    return float(eps)


def planar(domain):
    """Whether a domain's flow space is the plane R² (disk), not R x S¹ (spherical, slope)."""
    return domain == "disk"


def base_outputs(domain, components=1):
    """Outputs of the base MLP: disk mu(2), log sigma(2) [, K weight logits, K-1 lam logits]; others 5."""
    if not planar(domain):
        return 5
    return 4 if components == 1 else 4 + 2 * components - 1

def canonical_wi(c, isotropic):
    """The incident direction of conditioning features (isotropic: rotated to phi_i = 0)."""
    c = np.asarray(c, dtype=np.float64)
    if isotropic:
        return np.stack([c[..., 0], np.zeros_like(c[..., 0]), c[..., 1]], axis=-1)
    return c


# --------------------------------------------------------------------------- features

def cond_features(wi, isotropic):
    """Conditioning features of (unit) incident directions: isotropic (sin, cos theta_i), else wi."""
    wi = np.asarray(wi, dtype=np.float64)
    if isotropic:
        return np.stack([np.hypot(wi[..., 0], wi[..., 1]), wi[..., 2]], axis=-1)
    return wi.copy()


def cond_dim(isotropic):
    return 2 if isotropic else 3


def time_features(t, n_freq):
    """[t, sin(pi k t), cos(pi k t) for k = 1..n_freq]."""
    t = np.asarray(t, dtype=np.float64)
    feats = [t]
    for k in range(1, n_freq + 1):
        feats += [np.sin(np.pi * k * t), np.cos(np.pi * k * t)]
    return np.stack(feats, axis=-1)


def space_dim(domain):
    return 2 if planar(domain) else 3


# --------------------------------------------------------------------------- MLPs

def _silu_and_grad(a):
    sig = 0.5 * (1.0 + np.tanh(0.5 * a))
    return a * sig, sig * (1.0 + a * (1.0 - sig))


class MLP:
    """Linear layers with SiLU between them (none after the last), float64."""

    def __init__(self, weights, biases):
        self.W = [np.asarray(w, dtype=np.float64) for w in weights]
        self.b = [np.asarray(b, dtype=np.float64) for b in biases]

    @property
    def n_in(self):
        return self.W[0].shape[1]

    @property
    def n_out(self):
        return self.W[-1].shape[0]

    def __call__(self, h):
        last = len(self.W) - 1
        for i, (W, b) in enumerate(zip(self.W, self.b)):
            h = h @ W.T + b
            if i < last:
                h = h * (0.5 * (1.0 + np.tanh(0.5 * h)))
        return h

    def with_jacobian(self, h, dh):
        """Outputs and their derivatives: dh (k, n, n_in) are k input tangents; returns (out, dout (k, n, n_out))."""
        return self.continue_jacobian(h @ self.W[0].T + self.b[0], dh @ self.W[0].T)

    def continue_jacobian(self, a, da):
        """Like with_jacobian, from the first layer's pre-activation a (n, w) and its tangents
        da (k, n or 1, w) (broadcast: a tangent that is the same for every row costs nothing)."""
        last = len(self.W) - 1
        if last == 0:
            return a, np.broadcast_to(da, (da.shape[0], a.shape[0], a.shape[1]))
        for i in range(1, last + 1):
            a, g = _silu_and_grad(a)
            da = da * g
            a = a @ self.W[i].T + self.b[i]
            da = da @ self.W[i].T
        return a, da


# --------------------------------------------------------------------------- the model

class FlowModel:
    """A trained conditional flow: sample(wi, u) -> (wo, pdf), pdf(wi, wo), invert(wi, wo) -> u.

    Attributes: `domain` (the bake.core.domains object), `domain_name`, `isotropic`, `steps`
    (Euler steps N; `with_steps(n)` gives a copy with another N), `meta` (the file's
    metadata dict), `path`. After each call `last_stats` holds diagnostics: the fraction of
    samples whose Euler map folds (det(I + J/N) <= 0 at some step) and, for pdf/invert,
    how many Newton solves did not converge.
    """

    name = "flow"

    def __init__(self, meta, arrays, path=None):
        self.meta = meta
        self.path = None if path is None else str(path)
        self.domain_name = meta["domain"]
        self.domain = get_domain(self.domain_name)
        self.map = MAPS[self.domain_name]
        self.isotropic = bool(meta["isotropic"])
        self.steps = int(meta["steps"])
        base, vel = meta["base"], meta["velocity"]
        self.time_freq = int(vel.get("time_freq", 0))
        self.log_sigma_range = tuple(float(v) for v in base["log_sigma_range"])
        self.kappa_max = float(base.get("kappa_max", 0.0))
        lo_hi = self.log_sigma_range
        if len(lo_hi) != 2 or not all(math.isfinite(v) for v in lo_hi) or not lo_hi[0] < lo_hi[1]:
            raise FlowBSDFError(f"base log_sigma_range {list(lo_hi)} must be two finite numbers, low < high",
                                self.path)
        if not (math.isfinite(self.kappa_max) and self.kappa_max >= 0):
            raise FlowBSDFError(f"base kappa_max {self.kappa_max} must be finite and >= 0", self.path)
        if self.time_freq < 0:
            raise FlowBSDFError(f"velocity time_freq {self.time_freq} must be >= 0", self.path)
        self.defensive = _check_defensive(meta.get("defensive", 0.0), self.path)
        self.planar = planar(self.domain_name)
        self.components = int(base.get("components", 1)) if self.planar else 1
        self.base_net = MLP(*_layers(arrays, "base", meta, self.path))
        self.vel_net = MLP(*_layers(arrays, "vel", meta, self.path))
        self.last_stats = {}
        self._check_dims()

    def _check_dims(self):
        cd = cond_dim(self.isotropic)
        n_base_out = base_outputs(self.domain_name, self.components)
        if self.base_net.n_in != cd or self.base_net.n_out != n_base_out:
            raise FlowBSDFError(f"base network has shape {self.base_net.n_in}->{self.base_net.n_out}, "
                                f"expected {cd}->{n_base_out} for this domain/conditioning", self.path)
        n_in = space_dim(self.domain_name) + 1 + 2 * self.time_freq + cd
        if self.vel_net.n_in != n_in or self.vel_net.n_out != 2:
            raise FlowBSDFError(f"velocity network has shape {self.vel_net.n_in}->{self.vel_net.n_out}, "
                                f"expected {n_in}->2", self.path)

    def with_steps(self, n):
        if int(n) < 1:
            raise FlowBSDFError(f"steps must be >= 1, not {n}")
        other = copy.copy(self)
        other.steps = int(n)
        other.last_stats = {}
        return other

    def with_defensive(self, eps):
        """A copy with another defensive (uniform) mixture weight; 0 gives the bare flow."""
        other = copy.copy(self)
        other.defensive = _check_defensive(eps)
        other.last_stats = {}
        return other

    def __repr__(self):
        name = self.meta.get("material", {}).get("name", "?")
        return f"<FlowModel {name} {self.domain_name} N={self.steps}>"

    # ----------------------------------------------------------------- conditioning

    def _canonical(self, wi, n):
        wi = np.asarray(wi, dtype=np.float64)
        wi = np.broadcast_to(np.atleast_2d(wi), (n, 3)) if wi.ndim == 1 or len(wi) == 1 else wi
        if len(wi) != n:
            raise FlowBSDFError(f"wi has {len(wi)} rows but there are {n} samples")
        wi = wi / np.linalg.norm(wi, axis=-1, keepdims=True)
        ok = wi[:, 2] > 0.0
        if self.isotropic:
            phi_i = np.arctan2(wi[:, 1], wi[:, 0])
        else:
            phi_i = np.zeros(n)
        c = cond_features(wi, self.isotropic)
        return c, phi_i, ok

    def base_params(self, c):
        """The base's parameters per row: disk (mu (n,2), log_sigma (n,2), log weights (n,K),
        lam (n,K)); spherical (mu_s, log_sigma_s, mu_phi, kappa), each (n,)."""
        out = self.base_net(c)
        lo, hi = self.log_sigma_range
        if self.planar:
            K = self.components
            ls = lo + (hi - lo) * _sigmoid(out[:, 2:4])
            if K == 1:
                zero = np.zeros((len(c), 1))
                return out[:, 0:2], ls, zero, zero
            logits = out[:, 4:4 + K]
            logw = logits - logsumexp(logits)[:, None]
            lam = np.concatenate([np.zeros((len(c), 1)), -LAM_MIN_ABS * _sigmoid(out[:, 4 + K:])], axis=1)
            return out[:, 0:2], ls, logw, lam
        ls = lo + (hi - lo) * _sigmoid(out[:, 1])
        mu_phi = np.arctan2(out[:, 3], out[:, 2])
        kappa = self.kappa_max * _sigmoid(out[:, 4])
        return out[:, 0], ls, mu_phi, kappa

    @staticmethod
    def _mix_log_density(z, logw, lam):
        q = np.sum(z * z, axis=-1)
        return logsumexp(logw - LOG_2PI - 2.0 * lam - 0.5 * q[:, None] * np.exp(-2.0 * lam))

    # ----------------------------------------------------------------- base distribution
    # Disk, one component: u -> z per axis through the normal inverse CDF. Several components:
    # polar, |z|² from the mixture's radial inverse CDF (u1) and the angle 2 pi u2 - pi.

    def base_from_u(self, c, u):
        """u in [0,1)² -> y0 and log p0(y0)."""
        u = np.clip(np.asarray(u, dtype=np.float64), U_MIN, 1.0 - 2.0 ** -53)
        if self.planar:
            mu, ls, logw, lam = self.base_params(c)
            if self.components == 1:
                z = ndtri(u)
                return mu + np.exp(ls) * z, np.sum(log_normal_pdf(z) - ls, axis=-1)
            r = np.sqrt(mix_radial_icdf(u[:, 0], logw, lam))
            ang = 2.0 * np.pi * u[:, 1] - np.pi
            z = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=-1)
            return mu + np.exp(ls) * z, self._mix_log_density(z, logw, lam) - np.sum(ls, axis=-1)
        mu_s, ls, mu_phi, kappa = self.base_params(c)
        z = ndtri(u[:, 0])
        psi = vm_icdf(u[:, 1], kappa, vm_terms(float(np.max(kappa, initial=0.0))))
        y0 = np.stack([mu_s + np.exp(ls) * z, wrap_angle(mu_phi + psi)], axis=-1)
        return y0, log_normal_pdf(z) - ls + vm_log_pdf(psi, kappa)

    def base_to_u(self, c, y0):
        """y0 -> u and log p0(y0)."""
        if self.planar:
            mu, ls, logw, lam = self.base_params(c)
            z = (y0 - mu) * np.exp(-ls)
            if self.components == 1:
                return ndtr(z), np.sum(log_normal_pdf(z) - ls, axis=-1)
            u1 = mix_radial_cdf(np.sum(z * z, axis=-1), logw, lam)
            u2 = (np.arctan2(z[:, 1], z[:, 0]) + np.pi) / (2.0 * np.pi)
            u = np.stack([u1, np.where(u2 >= 1.0, 0.0, u2)], axis=-1)
            return u, self._mix_log_density(z, logw, lam) - np.sum(ls, axis=-1)
        mu_s, ls, mu_phi, kappa = self.base_params(c)
        z = (y0[:, 0] - mu_s) * np.exp(-ls)
        psi = wrap_angle(y0[:, 1] - mu_phi)
        u1 = vm_cdf(psi, kappa, vm_terms(float(np.max(kappa, initial=0.0))))
        u1 = np.where(u1 >= 1.0, u1 - 1.0, u1)
        u = np.stack([ndtr(z), np.clip(u1, 0.0, None)], axis=-1)
        return u, log_normal_pdf(z) - ls + vm_log_pdf(psi, kappa)

    def base_log_prob(self, c, y0):
        return self.base_to_u(c, y0)[1]

    # ----------------------------------------------------------------- velocity

    def _vel_input(self, y, t, c):
        n = len(y)
        tf = time_features(np.full(n, t), self.time_freq)
        if self.planar:
            sp = y
        else:
            sp = np.stack([y[:, 0], np.cos(y[:, 1]), np.sin(y[:, 1])], axis=-1)
        return np.concatenate([sp, tf, c], axis=-1)

    def velocity(self, y, t, c):
        return self.vel_net(self._vel_input(y, t, c))

    def velocity_jac(self, y, t, c):
        """D(y, t, c) (n,2) and J = dD/dy (n,2,2), J[:, i, j] = dD_i / dy_j."""
        h = self._vel_input(y, t, c)
        W0 = self.vel_net.W[0]
        a = h @ W0.T + self.vel_net.b[0]
        if self.planar:
            da = W0.T[:2, None, :]                       # d a / d y_j: the same for every row
        else:
            da = np.stack([np.broadcast_to(W0[:, 0], a.shape),
                           -np.sin(y[:, 1])[:, None] * W0[:, 1] + np.cos(y[:, 1])[:, None] * W0[:, 2]])
        v, dv = self.vel_net.continue_jacobian(a, da)
        return v, np.transpose(dv, (1, 2, 0))

    def _step_det(self, J, n_steps):
        a = 1.0 / n_steps
        return (1.0 + a * J[:, 0, 0]) * (1.0 + a * J[:, 1, 1]) - a * a * J[:, 0, 1] * J[:, 1, 0]

    # ----------------------------------------------------------------- flow in y

    def flow_forward(self, c, y0, steps=None):
        """N Euler steps from y0: returns y1, sum_k log det(I + J_k/N), min_k det."""
        n_steps = self.steps if steps is None else int(steps)
        y = np.array(y0, dtype=np.float64)
        logdet = np.zeros(len(y))
        min_det = np.full(len(y), np.inf)
        for k in range(n_steps):
            v, J = self.velocity_jac(y, k / n_steps, c)
            det = self._step_det(J, n_steps)
            min_det = np.minimum(min_det, det)
            with np.errstate(invalid="ignore", divide="ignore"):
                logdet += np.log(np.abs(det))
            y = y + v / n_steps
        if not self.planar:
            y[:, 1] = wrap_angle(y[:, 1])
        return y, logdet, min_det

    def flow_inverse(self, c, y1, steps=None, tol=1e-13, max_iter=60):
        """Solve the Euler steps backwards: returns y0, sum_k log det, min det, converged mask."""
        n_steps = self.steps if steps is None else int(steps)
        y = np.array(y1, dtype=np.float64)
        logdet = np.zeros(len(y))
        min_det = np.full(len(y), np.inf)
        converged = np.ones(len(y), bool)
        for k in range(n_steps - 1, -1, -1):
            x, det, ok = self._solve_step(c, y, k / n_steps, n_steps, tol, max_iter)
            converged &= ok
            min_det = np.minimum(min_det, det)
            with np.errstate(invalid="ignore", divide="ignore"):
                logdet += np.log(np.abs(det))
            y = x
        if not self.planar:
            y[:, 1] = wrap_angle(y[:, 1])
        return y, logdet, min_det, converged

    def _solve_step(self, c, target, t, n_steps, tol, max_iter):
        """x with x + D(x, t)/N = target: damped Newton from x = target - D(target, t)/N.

        One Jacobian evaluation per iteration (a step whose residual grows is halved).
        Returns x, det(I + J(x)/N) (J from the last linearization, |dx| <= tol there) and
        the converged mask."""
        a = 1.0 / n_steps
        n = len(target)
        x = target - a * self.velocity(target, t, c)
        det_out = np.ones(n)
        done = np.zeros(n, bool)
        scale = 1.0 + np.abs(target).max(axis=1)
        idx = np.arange(n)
        prev_x = x.copy()
        prev_gn = np.full(n, np.inf)
        dx = np.zeros_like(x)
        lam = np.ones(n)
        for _ in range(max_iter):
            if idx.size == 0:
                break
            xa = x[idx]
            v, J = self.velocity_jac(xa, t, c[idx])
            g = xa + a * v - target[idx]
            gn = np.max(np.abs(g), axis=1)
            worse = ~(gn <= prev_gn[idx] * (1.0 - 1e-4 * lam[idx])) & (gn > 1e-3 * tol * scale[idx])
            worse &= lam[idx] > 1e-4
            # Rows that got worse: halve the last step and try again.
            wi = idx[worse]
            lam[wi] *= 0.5
            x[wi] = prev_x[wi] - lam[wi, None] * dx[wi]
            # Rows that improved: a full Newton step from here.
            keep = ~worse
            bi = idx[keep]
            g, gn, J = g[keep], gn[keep], J[keep]
            m00, m01 = 1.0 + a * J[:, 0, 0], a * J[:, 0, 1]
            m10, m11 = a * J[:, 1, 0], 1.0 + a * J[:, 1, 1]
            det = m00 * m11 - m01 * m10
            with np.errstate(invalid="ignore", divide="ignore"):
                step = np.stack([(m11 * g[:, 0] - m01 * g[:, 1]) / det,
                                 (-m10 * g[:, 0] + m00 * g[:, 1]) / det], axis=-1)
            step = np.where(np.isfinite(step), step, g)
            prev_x[bi] = x[bi]
            prev_gn[bi] = gn
            dx[bi] = step
            lam[bi] = 1.0
            x[bi] = x[bi] - step
            det_out[bi] = det
            fin = np.max(np.abs(step), axis=1) <= tol * scale[bi]
            done[bi[fin]] = True
            active = np.ones(n, bool)
            active[bi[fin]] = False
            idx = idx[active[idx]]
        if idx.size:
            # Accept the stragglers whose residual is at rounding level.
            v, J = self.velocity_jac(x[idx], t, c[idx])
            gn = np.max(np.abs(x[idx] + a * v - target[idx]), axis=1)
            det_out[idx] = self._step_det(J, n_steps)
            done[idx[gn <= 1e-11 * scale[idx]]] = True
        return x, det_out, done

    def fold_scan(self, wi, n=1 << 15, spread=2.0, seed=0):
        """Fraction of probe points whose N-step map folds (det(I + J/N) <= 0 at some step).

        sample()'s `last_stats["fold_fraction"]` only sees where the base puts samples; pdf() and
        invert() run the map backwards from any wo, so a fold anywhere makes them disagree with
        sample() (several preimages; Newton returns one of them, or none). Probes: the base
        broadened `spread` x in its scale and, on R x S¹, uniform in phi, which covers the
        antipode of a concentrated von Mises (kappa 7-24 at grazing wi: probability 1e-6 to
        1e-20, never sampled, yet folded in trained models)."""
        rng = np.random.default_rng(seed)
        c, _, _ = self._canonical(wi, n)
        if self.planar:
            mu, ls, _, _ = self.base_params(c)
            y0 = mu + spread * np.exp(ls) * rng.standard_normal((n, 2))
        else:
            mu_s, ls, _, _ = self.base_params(c)
            y0 = np.stack([mu_s + spread * np.exp(ls) * rng.standard_normal(n),
                           rng.uniform(-np.pi, np.pi, n)], axis=-1)
        min_det = np.concatenate([self.flow_forward(c[i:i + self.CHUNK], y0[i:i + self.CHUNK])[2]
                                  for i in range(0, n, self.CHUNK)])
        return float(np.mean(min_det <= 0.0))

    # ----------------------------------------------------------------- public API

    CHUNK = 8192   # rows per batch: keeps the (2, n, width) tangents in cache

    def _chunked(self, fn, wi, rows):
        """Run fn(wi_chunk, rows_chunk) -> (tuple of arrays, stats) over row chunks."""
        n = len(rows)
        wi = np.asarray(wi, dtype=np.float64)
        per_row = wi.ndim == 2 and len(wi) == n and n > 1
        outs, stats = [], []
        for i in range(0, max(n, 1), self.CHUNK):
            j = min(n, i + self.CHUNK)
            o, st = fn(wi[i:j] if per_row else wi, rows[i:j])
            outs.append(o)
            stats.append(st)
        self.last_stats = {"n": n, "fold_fraction": float(sum(st["folds"] for st in stats) / max(n, 1))}
        if "min_det" in stats[0]:
            self.last_stats["min_det"] = float(min(st["min_det"] for st in stats))
        if "not_converged" in stats[0]:
            self.last_stats["not_converged"] = int(sum(st["not_converged"] for st in stats))
        return tuple(np.concatenate(parts) for parts in zip(*outs))

    def sample(self, wi, u):
        """wo (n,3) and pdf (n,) (per steradian) for u (n,2) in [0,1)² and wi (3,) or (n,3)."""
        u = np.atleast_2d(np.asarray(u, dtype=np.float64))
        eps = self.defensive
        if eps == 0.0:
            return self._chunked(self._sample, wi, u)
        n = len(u)
        wi = np.asarray(wi, dtype=np.float64)
        per_row = wi.ndim == 2 and len(wi) == n and n > 1
        uni = u[:, 0] < eps
        wo, pdf, stats = np.zeros((n, 3)), np.zeros(n), {"n": n, "fold_fraction": 0.0}
        f = np.flatnonzero(~uni)
        if len(f):
            wo[f], pdf_flow = self._chunked(self._sample, wi[f] if per_row else wi,
                                            np.stack([(u[f, 0] - eps) / (1.0 - eps), u[f, 1]], axis=-1))
            stats = dict(self.last_stats, n=n)     # folds: a share of the flow's samples
            pdf[f] = np.where(pdf_flow > 0, with_uniform_share(pdf_flow, eps), 0.0)
        d = np.flatnonzero(uni)
        if len(d):
            wi_d = wi[d] if per_row else wi
            wo[d] = UniformSampler().sample(wi_d, np.stack([u[d, 0] / eps, u[d, 1]], axis=-1))[0]
            pdf[d] = self.pdf(wi_d, wo[d])
        self.last_stats = stats
        return wo, pdf

    def _sample(self, wi, u):
        n = len(u)
        c, phi_i, ok = self._canonical(wi, n)
        y0, logp0 = self.base_from_u(c, u)
        y1, logdet, min_det = self.flow_forward(c, y0)
        wi_c = canonical_wi(c, self.isotropic)
        wo = self.map.to_dir(y1, wi_c)
        log_pdf = logp0 - logdet - self.map.log_dw_dy(y1, wi_c)
        with np.errstate(over="ignore"):
            pdf = np.where(ok & self.map.valid(wo), np.exp(log_pdf), 0.0)
        if self.isotropic:
            wo = rotate_z(wo, phi_i)
        return (wo, pdf), {"folds": int(np.sum(min_det <= 0.0)),
                           "min_det": float(np.min(min_det)) if n else np.inf}

    def _inverse(self, wi, wo):
        wo = np.atleast_2d(np.asarray(wo, dtype=np.float64))
        return self._chunked(self._inverse_chunk, wi, wo)

    def _inverse_chunk(self, wi, wo):
        n = len(wo)
        c, phi_i, ok = self._canonical(wi, n)
        if self.isotropic:
            wo = rotate_z(wo, -phi_i)
        valid = ok & self.map.valid(wo)
        wo_safe = np.where(valid[:, None], wo, np.array([0.0, 0.0, 1.0]))
        wi_c = canonical_wi(c, self.isotropic)
        y1 = self.map.from_dir(wo_safe, wi_c)
        y0, logdet, min_det, conv = self.flow_inverse(c, y1)
        u, logp0 = self.base_to_u(c, y0)
        log_pdf = logp0 - logdet - self.map.log_dw_dy(y1, wi_c)
        return (u, log_pdf, valid), {"folds": int(np.sum(min_det <= 0.0)),
                                     "not_converged": int(np.sum(~conv & valid))}

    def pdf(self, wi, wo):
        """Density (per steradian) of sample() at wo; 0 below the horizon."""
        _, log_pdf, valid = self._inverse(wi, wo)
        with np.errstate(over="ignore"):
            p = np.exp(log_pdf)
        return np.where(valid, with_uniform_share(p, self.defensive), 0.0)

    def invert(self, wi, wo):
        """u with sample(wi, u) = wo (NaN where wo is below the horizon); with a defensive
        share, the flow component's u."""
        u, _, valid = self._inverse(wi, wo)
        if self.defensive:
            u = np.stack([self.defensive + (1.0 - self.defensive) * u[:, 0], u[:, 1]], axis=-1)
        return np.where(valid[:, None], u, np.nan)


def _sigmoid(a):
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(a, dtype=np.float64)))


# --------------------------------------------------------------------------- files

def _layers(arrays, prefix, meta, path):
    weights, biases = [], []
    i = 0
    while f"{prefix}.W{i}" in arrays:
        if f"{prefix}.b{i}" not in arrays:
            raise FlowBSDFError(f"model file lacks {prefix}.b{i}", path)
        W, b = arrays[f"{prefix}.W{i}"], arrays[f"{prefix}.b{i}"]
        if W.ndim != 2 or b.shape != (W.shape[0],):
            raise FlowBSDFError(f"{prefix} layer {i} has bad shapes {W.shape}, {b.shape}", path)
        if weights and W.shape[1] != weights[-1].shape[0]:
            raise FlowBSDFError(f"{prefix} layer {i} takes {W.shape[1]} inputs but layer {i - 1} "
                                f"gives {weights[-1].shape[0]}", path)
        if not (np.all(np.isfinite(W)) and np.all(np.isfinite(b))):
            raise FlowBSDFError(f"{prefix} layer {i} holds non-finite weights", path)
        weights.append(W)
        biases.append(b)
        i += 1
    if not weights:
        raise FlowBSDFError(f"model file has no {prefix} network", path)
    return weights, biases


def save_model(path, meta, arrays):
    """Write a model file atomically (temp file + rename). arrays: name -> ndarray."""
    path = Path(path)
    meta = dict(meta)
    meta.setdefault("format", FORMAT)
    meta.setdefault("version", VERSION)
    payload = {k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()}
    payload["meta"] = np.array(json.dumps(meta, sort_keys=True))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **payload)
    tmp.replace(path)
    return path


MAX_STEPS = 4096                 # Euler steps a model may ask for (trained ones use 4-64)
MAX_ARRAY_ELEMENTS = 1 << 24     # per weight array (the largest preset's are ~1e5)


def _check_npz_sizes(path):
    """Read every member's .npy header and refuse arrays larger than the member's bytes or
    than any model needs, before numpy allocates them (a forged header would otherwise
    ask for terabytes: MemoryError)."""
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():
            with z.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                        else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read(fh)
            count = math.prod(shape)
            if count > MAX_ARRAY_ELEMENTS or count * dtype.itemsize > info.file_size:
                raise ValueError(f"array {info.filename.removesuffix('.npy')!r} announces shape {shape} "
                                 f"({count * dtype.itemsize} bytes) but its member holds {info.file_size} "
                                 f"bytes (limit {MAX_ARRAY_ELEMENTS} elements)")


def load_model(path):
    """Load a model file written by the trainer; FlowBSDFError names the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError("model file not found", path)
    try:
        _check_npz_sizes(path)
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as e:
        raise FlowBSDFError(f"not a FlowBSDF model file (cannot read it as .npz: {e})", path) from None
    except MemoryError:
        raise FlowBSDFError("not a FlowBSDF model file (an array too large to load)", path) from None
    if "meta" not in arrays:
        raise FlowBSDFError("not a FlowBSDF model file (no metadata)", path)
    try:
        meta = json.loads(str(arrays.pop("meta")[()]))
    except (ValueError, TypeError) as e:
        raise FlowBSDFError(f"model metadata is not valid JSON: {e}", path) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise FlowBSDFError(f"not a FlowBSDF model file (format {got!r}, expected {FORMAT!r})", path)
    if meta.get("version") not in READS_VERSIONS:
        raise FlowBSDFError(f"model file version {meta.get('version')!r} is not supported "
                            f"(this build reads versions {list(READS_VERSIONS)}); retrain or update FlowBSDF", path)
    for key in ("domain", "isotropic", "steps", "base", "velocity"):
        if key not in meta:
            raise FlowBSDFError(f"model metadata lacks {key!r}", path)
    if meta["domain"] not in MAPS:
        raise FlowBSDFError(f"model domain {meta['domain']!r} is unknown (expected one of {sorted(MAPS)})", path)
    if not isinstance(meta["steps"], int) or not 1 <= meta["steps"] <= MAX_STEPS:
        raise FlowBSDFError(f"model steps {meta['steps']!r} must be an integer in [1, {MAX_STEPS}]", path)
    for k, v in arrays.items():
        if v.dtype.kind != "f":
            raise FlowBSDFError(f"array {k!r} has dtype {v.dtype}, expected floats", path)
    try:
        return FlowModel(meta, arrays, path)
    except (KeyError, TypeError, ValueError) as e:
        raise FlowBSDFError(f"malformed model metadata: {e!r}", path) from None
