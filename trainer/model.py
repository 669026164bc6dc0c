"""The flow's networks in torch, mirroring bake/core/flow.py (which runs the exported weights in numpy).

Coordinates are the flow coordinates y of bake.core.flow_maps (disk: R²; spherical and slope: (s, phi) on
R x S¹).
  BaseNet      c -> parameters of the base: disk, a diagonal Gaussian in y (or a scale
               mixture of `components`); spherical and slope, a Gaussian in s times a von
               Mises in phi. Fit by likelihood (stage 1).
  VelocityNet  D(y, t, c): SiLU MLP; input [y | (s, cos phi, sin phi)], time features, c.
  FlowNet      both, plus Euler sampling with exact log-dets and RK4 integration.
c are conditioning features of wi (bake.core.flow.cond_features).
"""
import math

import torch
from torch import nn

from bake.core import flow as npflow

LOG_2PI = math.log(2.0 * math.pi)


def time_features(t, n_freq):
    feats = [t]
    for k in range(1, n_freq + 1):
        feats += [torch.sin(math.pi * k * t), torch.cos(math.pi * k * t)]
    return torch.stack(feats, dim=-1)


class MLP(nn.Module):
    """Linear layers (depth hidden layers of `width`) with SiLU between them."""

    def __init__(self, n_in, width, depth, n_out, zero_last=True):
        super().__init__()
        dims = [n_in] + [width] * depth + [n_out]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        if zero_last:
            nn.init.zeros_(self.layers[-1].weight)
            nn.init.zeros_(self.layers[-1].bias)

    def forward(self, h):
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < len(self.layers) - 1:
                h = nn.functional.silu(h)
        return h

    def forward_tangent(self, h, dh):
        """Outputs and forward-mode derivatives; dh (k, n, n_in) -> (out, dout (k, n, n_out))."""
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            h = layer(h)
            dh = dh @ layer.weight.T
            if i < last:
                sig = torch.sigmoid(h)
                dh = dh * (sig * (1.0 + h * (1.0 - sig)))
                h = h * sig
        return h, dh

    def arrays(self, prefix):
        out = {}
        for i, layer in enumerate(self.layers):
            out[f"{prefix}.W{i}"] = layer.weight.detach().cpu().numpy()
            out[f"{prefix}.b{i}"] = layer.bias.detach().cpu().numpy()
        return out


class BaseNet(nn.Module):
    """The conditional base. Disk: a scale mixture of `components` Gaussians sharing the mean
    mu and the axis scales exp(ls) (component k's extra log scale lam_k <= 0, lam_0 = 0), so
    that one base holds a sharp spike and a broad glow; bake.core.flow samples it through its
    radial inverse CDF (a bijection of the unit square). Spherical: Gaussian(s) x von Mises(phi)."""

    def __init__(self, domain, cond_dim, width=32, depth=2, log_sigma_range=(-4.0, 1.5), kappa_max=32.0,
                 components=1):
        super().__init__()
        self.domain = domain
        self.components = int(components) if npflow.planar(domain) else 1
        self.n_out = npflow.base_outputs(domain, self.components)
        self.net = MLP(cond_dim, width, depth, self.n_out, zero_last=True)
        self.log_sigma_range = tuple(float(v) for v in log_sigma_range)
        self.kappa_max = float(kappa_max)
        lo, hi = self.log_sigma_range
        # Start as the standard base (sigma = 1, uniform phi): the ideal base of a Lambertian;
        # extra components start narrower (lam = -1.5 k) with equal weights.
        with torch.no_grad():
            b = self.net.layers[-1].bias
            raw_ls0 = math.log((0.0 - lo) / (hi - 0.0))
            if npflow.planar(domain):
                b[2:4] = raw_ls0
                K = self.components
                for k in range(1, K):
                    frac = 1.5 * k / npflow.LAM_MIN_ABS
                    b[4 + K + k - 1] = math.log(frac / (1.0 - frac))
            else:
                b[1] = raw_ls0
                b[2] = 1.0
                b[4] = -6.0

    def params(self, c):
        """Disk: mu (n,2), ls (n,2), log weights (n,K), lam (n,K). Spherical: mu_s, ls, mu_phi, kappa."""
        out = self.net(c)
        lo, hi = self.log_sigma_range
        if npflow.planar(self.domain):
            K = self.components
            mu, ls = out[:, 0:2], lo + (hi - lo) * torch.sigmoid(out[:, 2:4])
            if K == 1:
                zero = torch.zeros(len(c), 1, dtype=c.dtype, device=c.device)
                return mu, ls, zero, zero
            logw = torch.log_softmax(out[:, 4:4 + K], dim=-1)
            lam = -npflow.LAM_MIN_ABS * torch.sigmoid(out[:, 4 + K:4 + 2 * K - 1])
            lam = torch.cat([torch.zeros_like(lam[:, :1]), lam], dim=-1)
            return mu, ls, logw, lam
        ls = lo + (hi - lo) * torch.sigmoid(out[:, 1])
        mu_phi = torch.atan2(out[:, 3], out[:, 2])
        kappa = self.kappa_max * torch.sigmoid(out[:, 4])
        return out[:, 0], ls, mu_phi, kappa

    def log_prob(self, c, y):
        if npflow.planar(self.domain):
            mu, ls, logw, lam = self.params(c)
            z = (y - mu) * torch.exp(-ls)
            q = (z * z).sum(-1, keepdim=True)
            comp = logw - LOG_2PI - 2.0 * lam - 0.5 * q * torch.exp(-2.0 * lam)
            return torch.logsumexp(comp, dim=-1) - ls.sum(-1)
        mu_s, ls, mu_phi, kappa = self.params(c)
        z = (y[:, 0] - mu_s) * torch.exp(-ls)
        psi = y[:, 1] - mu_phi
        log_i0 = torch.log(torch.special.i0e(kappa)) + kappa
        return -0.5 * z * z - 0.5 * LOG_2PI - ls + kappa * torch.cos(psi) - LOG_2PI - log_i0

    @torch.no_grad()
    def sample(self, c, generator=None):
        """Ancestral sampling (the same distribution bake.core.flow draws through its inverse CDF)."""
        n = len(c)
        if npflow.planar(self.domain):
            mu, ls, logw, lam = self.params(c)
            z = torch.randn(n, 2, generator=generator, dtype=c.dtype).to(c.device)
            if self.components > 1:
                k = torch.multinomial(torch.exp(logw).cpu().float(), 1, generator=generator).to(c.device)
                z = z * torch.exp(torch.gather(lam, 1, k))
            return mu + torch.exp(ls) * z
        mu_s, ls, mu_phi, kappa = self.params(c)
        z = torch.randn(n, generator=generator, dtype=c.dtype).to(c.device)
        psi = sample_von_mises(kappa.cpu(), generator).to(c.device)
        return torch.stack([mu_s + torch.exp(ls) * z, wrap(mu_phi + psi)], dim=-1)


def wrap(a):
    return torch.remainder(a + math.pi, 2.0 * math.pi) - math.pi


@torch.no_grad()
def sample_von_mises(kappa, generator=None):
    """Zero-mean von Mises samples (Best & Fisher rejection), reproducible with `generator`."""
    dtype = kappa.dtype
    kappa = kappa.to(torch.float64)
    n = len(kappa)
    out = torch.zeros(n, dtype=torch.float64)
    todo = torch.arange(n)
    small = kappa < 1e-5
    k = torch.where(small, torch.ones_like(kappa), kappa)
    tau = 1.0 + torch.sqrt(1.0 + 4.0 * k * k)
    rho = (tau - torch.sqrt(2.0 * tau)) / (2.0 * k)
    r = (1.0 + rho * rho) / (2.0 * rho)
    while todo.numel():
        u = torch.rand(3, todo.numel(), generator=generator, dtype=torch.float64)
        z = torch.cos(math.pi * u[0])
        rr, kk = r[todo], k[todo]
        f = (1.0 + rr * z) / (rr + z)
        cc = kk * (rr - f)
        accept = (cc * (2.0 - cc) - u[1] > 0) | (torch.log(cc / u[1]) + 1.0 - cc >= 0)
        theta = torch.sign(u[2] - 0.5) * torch.acos(f.clamp(-1.0, 1.0))
        uni = math.pi * (2.0 * u[2] - 1.0)
        theta = torch.where(small[todo], uni, theta)
        accept = accept | small[todo]
        out[todo[accept]] = theta[accept]
        todo = todo[~accept]
    return out.to(dtype)


class VelocityNet(nn.Module):
    def __init__(self, domain, cond_dim, width=128, depth=4, time_freq=0):
        super().__init__()
        self.domain = domain
        self.time_freq = int(time_freq)
        n_in = npflow.space_dim(domain) + 1 + 2 * self.time_freq + cond_dim
        self.net = MLP(n_in, width, depth, 2, zero_last=True)
        self.width, self.depth = width, depth

    def _input(self, y, t, c):
        if t.dim() == 0:
            t = t.expand(len(y))
        tf = time_features(t, self.time_freq)
        if npflow.planar(self.domain):
            sp = y
        else:
            sp = torch.stack([y[:, 0], torch.cos(y[:, 1]), torch.sin(y[:, 1])], dim=-1)
        return torch.cat([sp, tf, c], dim=-1)

    def forward(self, y, t, c):
        return self.net(self._input(y, t, c))

    def forward_jac(self, y, t, c):
        """D (n,2) and J = dD/dy (n,2,2), J[:, i, j] = dD_i/dy_j (differentiable)."""
        h = self._input(y, t, c)
        n = len(y)
        dh = torch.zeros(2, n, h.shape[1], dtype=h.dtype, device=h.device)
        if npflow.planar(self.domain):
            dh[0, :, 0] = 1.0
            dh[1, :, 1] = 1.0
        else:
            dh[0, :, 0] = 1.0
            dh[1, :, 1] = -torch.sin(y[:, 1])
            dh[1, :, 2] = torch.cos(y[:, 1])
        v, dv = self.net.forward_tangent(h, dh)
        return v, dv.permute(1, 2, 0)


def step_det(J, n_steps):
    """det(I + J/N) = 1 + tr(J)/N + det(J)/N² (computed as the 2x2 determinant)."""
    a = 1.0 / n_steps
    return (1.0 + a * J[:, 0, 0]) * (1.0 + a * J[:, 1, 1]) - a * a * J[:, 0, 1] * J[:, 1, 0]


class FlowNet(nn.Module):
    """Base + velocity, with the settings bake.core.flow needs to rebuild them."""

    def __init__(self, domain, isotropic, vel_width=128, vel_depth=4, time_freq=0, base_width=32,
                 base_depth=2, log_sigma_range=(-4.0, 1.5), kappa_max=32.0, base_components=1):
        super().__init__()
        self.domain, self.isotropic = domain, bool(isotropic)
        cd = npflow.cond_dim(isotropic)
        self.base = BaseNet(domain, cd, base_width, base_depth, log_sigma_range, kappa_max, base_components)
        self.vel = VelocityNet(domain, cd, vel_width, vel_depth, time_freq)
        self.config = dict(domain=domain, isotropic=bool(isotropic), vel_width=vel_width,
                           vel_depth=vel_depth, time_freq=int(time_freq), base_width=base_width,
                           base_depth=base_depth, log_sigma_range=list(log_sigma_range),
                           kappa_max=float(kappa_max), base_components=self.base.components)

    @classmethod
    def from_config(cls, config):
        return cls(**config)

    def displacement(self, y0, y1):
        """y1 - y0, the phi component wrapped to the shortest angle (spherical)."""
        d = y1 - y0
        if not npflow.planar(self.domain):
            d = torch.stack([d[:, 0], wrap(d[:, 1])], dim=-1)
        return d

    def euler(self, c, y0, n_steps, with_logdet=True):
        """N Euler steps; returns y1 (phi unwrapped), sum log|det|, min det."""
        y = y0
        logdet = torch.zeros(len(y), dtype=y.dtype)
        min_det = torch.full((len(y),), float("inf"), dtype=y.dtype)
        for k in range(n_steps):
            t = torch.tensor(k / n_steps, dtype=y.dtype, device=y.device)
            if with_logdet:
                v, J = self.vel.forward_jac(y, t, c)
                det = step_det(J, n_steps)
                min_det = torch.minimum(min_det, det)
                logdet = logdet + torch.log(torch.abs(det))
            else:
                v = self.vel(y, t, c)
            y = y + v / n_steps
        return y, logdet, min_det

    @torch.no_grad()
    def rk4(self, c, y0, n_steps):
        """Accurate integration of dy/dt = D(y, t, c) from t = 0 to 1 (phi unwrapped)."""
        y = y0
        h = 1.0 / n_steps
        for k in range(n_steps):
            t = k * h
            k1 = self.vel(y, torch.tensor(t, dtype=y.dtype, device=y.device), c)
            k2 = self.vel(y + 0.5 * h * k1, torch.tensor(t + 0.5 * h, dtype=y.dtype, device=y.device), c)
            k3 = self.vel(y + 0.5 * h * k2, torch.tensor(t + 0.5 * h, dtype=y.dtype, device=y.device), c)
            k4 = self.vel(y + h * k3, torch.tensor(t + h, dtype=y.dtype, device=y.device), c)
            y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return y

    def arrays(self):
        out = self.base.net.arrays("base")
        out.update(self.vel.net.arrays("vel"))
        return out

    def meta(self, steps, **extra):
        cfg = self.config
        meta = {
            "format": npflow.FORMAT, "version": npflow.VERSION,
            "domain": self.domain, "isotropic": self.isotropic, "steps": int(steps),
            "base": {"width": cfg["base_width"], "depth": cfg["base_depth"],
                     "log_sigma_range": cfg["log_sigma_range"], "kappa_max": cfg["kappa_max"],
                     "components": cfg["base_components"]},
            "velocity": {"width": cfg["vel_width"], "depth": cfg["vel_depth"],
                         "time_freq": cfg["time_freq"], "activation": "silu"},
        }
        meta.update(extra)
        return meta

    def to_numpy(self, steps, **extra):
        """The bake.core.flow.FlowModel of the current weights (float32 as in the file)."""
        import numpy as np
        arrays = {k: v.astype(np.float32) for k, v in self.arrays().items()}
        return npflow.FlowModel(self.meta(steps, **extra), arrays)


@torch.no_grad()
def euler_inverse(net, c, y1, n_steps, tol=1e-10, max_iter=40):
    """Solve the N Euler steps backwards (damped Newton per step, as bake.core.flow does).

    Returns y0, sum_k log|det(I + J_k/N)|, min det, converged mask. Used for the trainer's
    quality checks (torch is several times faster than numpy's BLAS here); run it in float64."""
    a = 1.0 / n_steps
    y = y1.clone()
    n = len(y)
    logdet = torch.zeros(n, dtype=y.dtype)
    min_det = torch.full((n,), float("inf"), dtype=y.dtype)
    converged = torch.ones(n, dtype=torch.bool)
    for k in range(n_steps - 1, -1, -1):
        t = torch.tensor(k / n_steps, dtype=y.dtype, device=y.device)
        target = y
        x = target - a * net.vel(target, t, c)
        scale = 1.0 + target.abs().amax(dim=1)
        det_out = torch.ones(n, dtype=y.dtype)
        done = torch.zeros(n, dtype=torch.bool)
        prev_x, prev_gn = x.clone(), torch.full((n,), float("inf"), dtype=y.dtype)
        dx, lam = torch.zeros_like(x), torch.ones(n, dtype=y.dtype)
        idx = torch.arange(n)
        for _ in range(max_iter):
            if idx.numel() == 0:
                break
            xa = x[idx]
            v, J = net.vel.forward_jac(xa, t, c[idx])
            g = xa + a * v - target[idx]
            gn = g.abs().amax(dim=1)
            worse = ~(gn <= prev_gn[idx] * (1.0 - 1e-4 * lam[idx])) & (gn > 1e-3 * tol * scale[idx])
            worse &= lam[idx] > 1e-4
            wi = idx[worse]
            lam[wi] *= 0.5
            x[wi] = prev_x[wi] - lam[wi, None] * dx[wi]
            keep = ~worse
            bi = idx[keep]
            g, gn, J = g[keep], gn[keep], J[keep]
            m00, m01 = 1.0 + a * J[:, 0, 0], a * J[:, 0, 1]
            m10, m11 = a * J[:, 1, 0], 1.0 + a * J[:, 1, 1]
            det = m00 * m11 - m01 * m10
            step = torch.stack([(m11 * g[:, 0] - m01 * g[:, 1]) / det, (-m10 * g[:, 0] + m00 * g[:, 1]) / det], -1)
            step = torch.where(torch.isfinite(step), step, g)
            prev_x[bi] = x[bi]
            prev_gn[bi] = gn
            dx[bi] = step
            lam[bi] = 1.0
            x[bi] = x[bi] - step
            det_out[bi] = det
            fin = step.abs().amax(dim=1) <= tol * scale[bi]
            done[bi[fin]] = True
            active = torch.ones(n, dtype=torch.bool)
            active[bi[fin]] = False
            idx = idx[active[idx]]
        converged &= done
        min_det = torch.minimum(min_det, det_out)
        logdet += torch.log(det_out.abs())
        y = x
    if not npflow.planar(net.domain):
        y = torch.stack([y[:, 0], wrap(y[:, 1])], dim=-1)
    return y, logdet, min_det, converged
