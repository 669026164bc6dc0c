"""Training: base pretraining -> flow matching (teacher) -> reflow (student), with checkpoints.

    source.draw(n, rng) -> (wi (n,3), x1 (n,2) in the domain's coordinates)

is all the trainer knows about the target: pairs may come from bake.core.ideal (a material's
exact tabulated sampler), a synthetic lobe or anything else. Pairs are converted to flow
coordinates (bake.core.flow), isotropic ones rotated to phi_i = 0.

Stages (each checkpointed in out_dir/ckpt/<stage>.pt, written atomically, resumable):
  base     fit the base distribution by maximum likelihood.
  flow     flow matching, E || D(y_t, t, c) - (y1 - y0) ||², y_t = (1 - t) y0 + t y1, with
           y0 from the (frozen) base and phi differences wrapped to the shortest angle.
  reflow   pairs (y0, ODE(y0)) integrated accurately (RK4) with the best flow model, then
           flow matching on those pairs (a student, optionally smaller), so that few Euler
           steps suffice. The phi displacement of the pairs is kept unwrapped (it is the
           teacher's actual path).
Both flow stages keep an exponential moving average of the weights (`ema`; it cut the
relative variance 2-5x on the synthetic lobes) and stop on a quality check, not on the
loss: every `*_eval_every` steps the EMA model is scored by its negative log-likelihood
(per steradian) of held-out target samples through the exact inverse of its Euler map
(float64), with `flow_eval_steps` steps for the teacher and the final N for the student;
the best weights are kept (a map that folds never beats one that does not) and training
stops after `patience` checks without improvement. The exported file is scored once more
with bake.core.flow itself (numpy) as a cross-check.
"""
import copy
import hashlib
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from bake.core import flow as npflow
from bake.core import flow_maps
from bake.core.domains import get_domain
from bake.errors import FlowBSDFError

from .model import FlowNet, euler_inverse, step_det

PRESETS = {
    # ~1 min on 2 CPU cores: tests and demos.
    "fast": dict(
        teacher=dict(vel_width=64, vel_depth=3), student=None,
        batch=2048, base_steps=300, base_lr=1e-2,
        flow_steps=1500, flow_lr=2e-3, flow_eval_every=250, flow_eval_steps=16,
        reflow_pairs=1 << 16, reflow_ode_steps=32, reflow_steps=1000, reflow_lr=1e-3,
        reflow_eval_every=250, patience=4, holdout=2048, ema=0.995,
    ),
    # ~4 min for an isotropic material on 2 CPU cores (what it trades: trainer/README.md, Presets).
    "balanced": dict(
        teacher=dict(vel_width=128, vel_depth=4), student=dict(vel_width=32, vel_depth=3),
        batch=2048, base_steps=600, base_lr=1e-2,
        flow_steps=3000, flow_lr=2e-3, flow_eval_every=500, flow_eval_steps=16,
        reflow_pairs=1 << 17, reflow_ode_steps=24, reflow_steps=8000, reflow_lr=2e-3,
        reflow_eval_every=1000, patience=4, holdout=4096, ema=0.999,
    ),
    # The paper's recipe scaled to a workstation: a large teacher distilled into a small student.
    "paper": dict(
        teacher=dict(vel_width=256, vel_depth=6), student=dict(vel_width=64, vel_depth=4),
        batch=8192, base_steps=2000, base_lr=5e-3,
        flow_steps=40000, flow_lr=1e-3, flow_eval_every=2000, flow_eval_steps=64,
        reflow_pairs=1 << 20, reflow_ode_steps=64, reflow_steps=20000, reflow_lr=5e-4,
        reflow_eval_every=1000, patience=5, holdout=8192, ema=0.999,
    ),
}

COMMON = dict(
    seed=0, steps=None, time_freq=0, base_width=32, base_depth=2, log_sigma_range=(-4.0, 1.5),
    kappa_max=32.0, base_components=1, warmup=100, min_lr_frac=0.05, ckpt_every=250, fold_penalty=10.0,
    fold_margin=0.2, grad_clip=1.0, min_frac=0.5, defensive="auto",
)
# fold_penalty, fold_margin: the student's map must not fold on the probes (_probe_starts) either, or the
# checks keep an early checkpoint (cc_nothern_aurora, spherical: weight 0 -> held-out rv 0.28 instead of
# 0.18; weight 1 or margin 0.05 still folded 5e-5 to 2e-3 of the probes; see trainer/README.md).
# defensive = "auto": the uniform share of the final sampler (bake.core.flow, "Defensive mixture") is the
# one of these with the lowest held-out relative variance; a number fixes it. Never below 1 %:
# the held-out set cannot see regions rarer than ~1 / DEFENSIVE_SAMPLES (ilm_solo_m_68, slope:
# held-out preferred 0, but rv at 75 deg was 0.61 bare and 0.135 at 0.01); the floor costs at
# most 1 % of (1 + rv).
DEFENSIVE_CHOICES = (0.01, 0.02, 0.05, 0.1)
DEFENSIVE_SAMPLES = 1 << 15
PROBE_SPREAD = 2.0            # fold probes: the base broadened this many times (see _probe_starts)
DEFAULT_STEPS = {"disk": 4, "spherical": 8, "slope": 8}
STAGES = ("base", "flow", "reflow")
# The settings each stage's result depends on (beyond those of the stages before it).
STAGE_KEYS = {
    "base": ("seed", "teacher", "time_freq", "base_width", "base_depth", "log_sigma_range", "kappa_max", "base_components",
             "batch", "base_steps", "base_lr", "warmup", "min_lr_frac", "grad_clip"),
    "flow": ("flow_steps", "flow_lr", "flow_eval_every", "flow_eval_steps", "patience", "ema", "holdout",
             "min_frac"),
    "reflow": ("student", "steps", "reflow_pairs", "reflow_ode_steps", "reflow_steps", "reflow_lr",
               "reflow_eval_every", "fold_penalty", "fold_margin"),
}


def make_settings(preset="balanced", domain="disk", **overrides):
    if preset not in PRESETS:
        raise FlowBSDFError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
    s = dict(COMMON)
    s.update(copy.deepcopy(PRESETS[preset]))
    s["preset"] = preset
    for k, v in overrides.items():
        if k not in s:
            raise FlowBSDFError(f"unknown training setting {k!r}")
        s[k] = v
    if s["steps"] is None:
        s["steps"] = DEFAULT_STEPS[domain]
    d = s["defensive"]
    if d != "auto" and not (isinstance(d, (int, float)) and not isinstance(d, bool) and 0 <= d <= npflow.MAX_DEFENSIVE):
        raise FlowBSDFError(f"training setting defensive = {d!r}: expected \"auto\" or a number in "
                            f"[0, {npflow.MAX_DEFENSIVE}]")
    return s


class TrainingInterrupted(Exception):
    """Raised by `stop_at` (tests) after the checkpoint is written."""


# --------------------------------------------------------------------------- data

class PreparedSource:
    """Wraps a source: canonical isotropic frame, flow coordinates, torch tensors."""

    def __init__(self, source, domain, isotropic):
        self.source, self.domain, self.isotropic = source, domain, isotropic
        self.map = flow_maps.MAPS[domain]
        self._pool = None       # (c, y) of the source's whole pool, where it has one

    def prepare(self, wi, x1):
        wi = np.asarray(wi, np.float64)
        x1 = np.asarray(x1, np.float64)
        wi = wi / np.linalg.norm(wi, axis=-1, keepdims=True)
        if self.isotropic:
            phi_i = np.arctan2(wi[:, 1], wi[:, 0])
            if np.any(phi_i != 0.0):
                if get_domain(self.domain).name == "disk":    # disk coordinates of wo (slope flows too)
                    c, s = np.cos(-phi_i), np.sin(-phi_i)
                    x1 = np.stack([c * x1[:, 0] - s * x1[:, 1], s * x1[:, 0] + c * x1[:, 1]], axis=-1)
                else:
                    x1 = np.stack([x1[:, 0], x1[:, 1] - phi_i], axis=-1)
        c = npflow.cond_features(wi, self.isotropic)
        y1 = self.map.from_domain(x1, npflow.canonical_wi(c, self.isotropic))
        ok = np.all(np.isfinite(y1), axis=1) & (wi[:, 2] > 0)
        return c[ok], y1[ok]

    def draw(self, n, rng):
        if hasattr(self.source, "pool"):
            # A finite pool: converted once (the conversion cost ~4 ms of a ~15 ms training step).
            if self._pool is None:
                self._pool = self.prepare(*self.source.pool())
                if len(self._pool[0]) == 0:
                    raise FlowBSDFError("the training data source returned no valid pairs")
            c, y = self._pool
            k = rng.integers(0, len(c), n)
            return c[k], y[k]
        cs, ys, have = [], [], 0
        for _ in range(100):
            wi, x1 = self.source.draw(n - have, rng)
            c, y = self.prepare(wi, x1)
            cs.append(c)
            ys.append(y)
            have += len(c)
            if have >= n:
                break
        else:
            raise FlowBSDFError("the training data source keeps returning invalid pairs")
        return np.concatenate(cs)[:n], np.concatenate(ys)[:n]


def _t(a):
    return torch.as_tensor(np.asarray(a), dtype=torch.float32)


# --------------------------------------------------------------------------- trainer

class Trainer:
    def __init__(self, source, out_dir, settings=None, domain="disk", isotropic=True, name="material",
                 meta=None, progress=True, log=None, device="cpu", stop_at=None):
        self.settings = settings or make_settings("balanced", domain)
        self.domain, self.isotropic, self.name = domain, bool(isotropic), name
        self.data = PreparedSource(source, domain, self.isotropic)
        self.out_dir = Path(out_dir)
        self.ckpt_dir = self.out_dir / "ckpt"
        self.meta_extra = dict(meta or {})
        self.progress = progress
        self.log = log or (lambda msg: None)
        self.device = torch.device(device)
        self.stop_at = stop_at
        self.steps = int(self.settings["steps"])
        self.timings = {}
        self.metrics = {}
        # Each stage's checkpoint is valid for the settings it depends on (and those of the
        # stages before it): changing, say, the reflow settings keeps the trained teacher.
        common = {"domain": domain, "isotropic": self.isotropic, "source": self.meta_extra.get("source")}
        self.fingerprints, keys = {}, dict(common)
        for stage in STAGES:
            keys.update({k: self.settings[k] for k in STAGE_KEYS[stage]})
            blob = json.dumps(keys, sort_keys=True, default=str)
            self.fingerprints[stage] = hashlib.sha256(blob.encode()).hexdigest()[:16]

    # ----------------------------------------------------------------- helpers

    def new_net(self, arch, salt=0):
        """A freshly initialized network (deterministic: seeded from the settings' seed)."""
        s = self.settings
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(s["seed"] * 7919 + salt)
            return self._new_net(arch)

    def _new_net(self, arch):
        s = self.settings
        return FlowNet(self.domain, self.isotropic, vel_width=arch["vel_width"], vel_depth=arch["vel_depth"],
                       time_freq=s["time_freq"], base_width=s["base_width"], base_depth=s["base_depth"],
                       log_sigma_range=s["log_sigma_range"], kappa_max=s["kappa_max"],
                       base_components=s["base_components"]).to(self.device)

    def lr_at(self, step, total, lr):
        s = self.settings
        if step < s["warmup"]:
            return lr * (step + 1) / s["warmup"]
        frac = min(1.0, (step - s["warmup"]) / max(1, total - s["warmup"]))
        return lr * (s["min_lr_frac"] + (1 - s["min_lr_frac"]) * 0.5 * (1 + math.cos(math.pi * frac)))

    def ckpt_path(self, stage):
        return self.ckpt_dir / f"{stage}.pt"

    def save_ckpt(self, stage, state):
        self.ckpt_dir.mkdir(parents=True, exist_ok=True)
        state = dict(state, stage=stage, fingerprint=self.fingerprints[stage])
        path = self.ckpt_path(stage)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(state, tmp)
        os.replace(tmp, path)

    def load_ckpt(self, stage):
        path = self.ckpt_path(stage)
        if not path.is_file():
            return None
        try:
            state = torch.load(path, map_location=self.device, weights_only=False)
        except Exception as e:  # a torn or foreign file: start the stage over
            self.log(f"[{stage}] ignoring unreadable checkpoint {path}: {e}")
            return None
        if state.get("fingerprint") != self.fingerprints[stage]:
            self.log(f"[{stage}] checkpoint {path} is from other settings: starting the stage over")
            return None
        return state

    def _progress(self, total, desc, initial=0):
        from tqdm import tqdm
        return tqdm(total=total, initial=initial, desc=desc, disable=not self.progress, leave=True,
                    dynamic_ncols=True, unit="step")

    def _maybe_stop(self, stage, step):
        if self.stop_at is not None and tuple(self.stop_at) == (stage, step):
            raise TrainingInterrupted(f"stopped at {stage} step {step}")

    def holdout(self):
        if not hasattr(self, "_holdout"):
            rng = np.random.default_rng([self.settings["seed"], 7919])
            c, y = self.data.draw(self.settings["holdout"], rng)
            self._holdout = (c, y, flow_maps.MAPS[self.domain].log_dw_dy(y, npflow.canonical_wi(c, self.isotropic)))
        return self._holdout

    def evaluate(self, net, steps, fold_repeats=1):
        """Held-out NLL per steradian with `steps` Euler steps (exact inverse, float64 torch),
        plus the fraction of forward samples whose map folds (fold_repeats x holdout samples)
        and of Newton failures."""
        c, y, log_dw = self.holdout()
        net64 = copy.deepcopy(net).double().cpu()
        ct, yt = torch.from_numpy(c), torch.from_numpy(y)
        with torch.no_grad():
            y0, logdet, min_det_inv, conv = euler_inverse(net64, ct, yt, steps)
            log_p = (net64.base.log_prob(ct, y0) - logdet).numpy() - log_dw
            conv = conv.numpy()
            bad = ~np.isfinite(log_p) | ~conv
            nll = float(-np.mean(np.where(bad, -50.0, log_p)))
            gen = torch.Generator().manual_seed(104729)
            folds, probe_folds = [], []
            for _ in range(fold_repeats):
                y0f = net64.base.sample(ct, gen)
                folds.append(net64.euler(ct, y0f, steps)[2])
                probe_folds.append(net64.euler(ct, self._probe_starts(net64, ct, gen), steps)[2])
            min_det = torch.cat(folds)
            probe_fold = float(torch.mean((torch.cat(probe_folds) <= 0).double()))
        # "fold" counts a fold anywhere pdf() may be asked (the probes), not only where samples go.
        return {"nll": nll, "fold": max(float(torch.mean((min_det <= 0).double())), probe_fold),
                "fold_sampled": float(torch.mean((min_det <= 0).double())), "fold_probe": probe_fold,
                "fold_inv": float(torch.mean((min_det_inv <= 0).double())), "not_converged": int(np.sum(~conv))}

    def evaluate_numpy(self, net, steps):
        """The same NLL from the exported numpy model (bake.core.flow), as a cross-check."""
        c, y, log_dw = self.holdout()
        model = net.to_numpy(steps)
        y0, logdet, _, conv = model.flow_inverse(c, y)
        log_p = model.base_log_prob(c, y0) - logdet - log_dw
        return float(-np.mean(np.where(np.isfinite(log_p) & conv, log_p, -50.0)))

    # ----------------------------------------------------------------- stages

    def run(self):
        t_start = time.time()
        net = self.stage_base()
        teacher = self.stage_flow(net)
        student = self.stage_reflow(teacher)
        self.timings["total"] = time.time() - t_start
        return self.export(student)

    def stage_base(self):
        s = self.settings
        stage = "base"
        net = self.new_net(s["teacher"])
        state = self.load_ckpt(stage)
        opt = torch.optim.Adam(net.base.parameters(), lr=s["base_lr"], foreach=True)
        rng = np.random.default_rng([s["seed"], 1])
        step, elapsed = 0, 0.0
        if state is not None:
            net.load_state_dict(state["net"])
            opt.load_state_dict(state["opt"])
            rng.bit_generator.state = state["rng"]
            step, elapsed = state["step"], state["elapsed"]
            if state["done"]:
                self.timings[stage] = elapsed
                self.metrics["base_nll"] = state.get("nll")
                self.log(f"[{stage}] done already (checkpoint)")
                return net
        total = s["base_steps"]
        t0 = time.time() - elapsed
        bar = self._progress(total, "1/3 base", step)
        loss = None
        while step < total:
            for g in opt.param_groups:
                g["lr"] = self.lr_at(step, total, s["base_lr"])
            c, y = self.data.draw(s["batch"], rng)
            loss = -net.base.log_prob(_t(c).to(self.device), _t(y).to(self.device)).mean()
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.base.parameters(), s["grad_clip"] * 10)
            opt.step()
            step += 1
            bar.update(1)
            if step % 50 == 0:
                bar.set_postfix(nll=f"{loss.item():.4f}")
            if step % s["ckpt_every"] == 0 or step == total:
                self.save_ckpt(stage, dict(net=net.state_dict(), opt=opt.state_dict(), rng=rng.bit_generator.state,
                                           step=step, elapsed=time.time() - t0, done=False))
                self._maybe_stop(stage, step)
        bar.close()
        c, y, log_dw = self.holdout()
        with torch.no_grad():
            lp = net.base.log_prob(_t(c).to(self.device), _t(y).to(self.device)).cpu().numpy()
            nll = float(-(lp - log_dw).mean())
        self.timings[stage] = time.time() - t0
        self.metrics["base_nll"] = nll
        self.save_ckpt(stage, dict(net=net.state_dict(), opt=opt.state_dict(), rng=rng.bit_generator.state,
                                   step=step, elapsed=self.timings[stage], done=True, nll=nll))
        self.log(f"[{stage}] held-out NLL of the base {nll:.4f} ({self.timings[stage]:.0f} s)")
        return net

    def _fm_stage(self, stage, net, batch_fn, total, lr, eval_every, eval_steps, desc, rng_key, penalty=0.0):
        """Flow-matching loop shared by 'flow' and 'reflow' (batch_fn(rng, gen) -> c, y0, y1)."""
        s = self.settings
        params = list(net.vel.parameters())
        opt = torch.optim.Adam(params, lr=lr, foreach=True)
        rng = np.random.default_rng([s["seed"], rng_key])
        gen = torch.Generator().manual_seed(s["seed"] * 1000 + rng_key)
        ema = copy.deepcopy(net) if s["ema"] > 0 else None
        step, elapsed = 0, 0.0
        best = {"score": math.inf, "net": copy.deepcopy(net.state_dict()), "step": 0, "eval": None}
        history, since_best = [], 0
        state = self.load_ckpt(stage)
        if state is not None and state.get("pairs_only"):
            state = None
        if state is not None:
            net.load_state_dict(state["net"])
            opt.load_state_dict(state["opt"])
            rng.bit_generator.state = state["rng"]
            gen.set_state(state["gen"])
            if ema is not None:
                ema.load_state_dict(state["ema"])
            step, elapsed = state["step"], state["elapsed"]
            best, history, since_best = state["best"], state["history"], state["since_best"]
            if state["done"]:
                net.load_state_dict(best["net"])
                self.timings[stage] = elapsed
                self.metrics[stage] = {"best": best["eval"], "best_step": best["step"], "history": history}
                self.log(f"[{stage}] done already (checkpoint)")
                return net
        if state is None:
            # The start (zero velocity: the base alone; or the teacher a student is copied from) is
            # a candidate too: where training never beats it (a near-Lambertian material), keep it.
            ev = self.evaluate(net, eval_steps)
            ev.update(step=0, loss=float("nan"), time=0.0)
            history.append(ev)
            best = {"score": ev["nll"], "folds": ev["fold"] > 0, "net": copy.deepcopy(net.state_dict()),
                    "step": 0, "eval": ev}
        t0 = time.time() - elapsed
        bar = self._progress(total, desc, step)
        stopped = False
        while step < total and not stopped:
            for g in opt.param_groups:
                g["lr"] = self.lr_at(step, total, lr)
            c, y0, y1 = batch_fn(rng, gen)
            d = net.displacement(y0, y1) if stage == "flow" else y1 - y0
            t = torch.rand(len(c), generator=gen).to(self.device)
            yt = y0 + t[:, None] * d
            v = net.vel(yt, t, c)
            pen = self._fold_penalty(net, c, gen) if penalty > 0 else torch.zeros(())
            loss = (v - d).pow(2).sum(-1).mean() + penalty * pen
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, s["grad_clip"], foreach=True)
            opt.step()
            if ema is not None:
                decay = min(s["ema"], (1.0 + step) / (10.0 + step))
                with torch.no_grad():
                    for pe, p in zip(ema.vel.parameters(), net.vel.parameters()):
                        pe.lerp_(p, 1.0 - decay)
            step += 1
            bar.update(1)
            if step % 25 == 0:
                bar.set_postfix(loss=f"{loss.item():.4f}", best=f"{best['score']:.4f}")
            if step % eval_every == 0 or step == total:
                cur = ema if ema is not None else net
                ev = self.evaluate(cur, eval_steps, fold_repeats=16 if stage == "reflow" else 1)
                ev.update(step=step, loss=float(loss.item()), time=time.time() - t0)
                history.append(ev)
                # A map that folds has a wrong pdf there: any fold-free checkpoint beats it.
                better = (ev["fold"] > 0, ev["nll"]) < (best.get("folds", True), best["score"] - 1e-4)
                if better:
                    best = {"score": ev["nll"], "folds": ev["fold"] > 0, "net": copy.deepcopy(cur.state_dict()),
                            "step": step, "eval": ev}
                    since_best = 0
                else:
                    since_best += 1
                bar.set_postfix(loss=f"{loss.item():.4f}", nll=f"{ev['nll']:.4f}", best=f"{best['score']:.4f}")
                # Early steps score worse than the near-identity start (the EMA lags and the field
                # is still rough): patience only counts once min_frac of the stage has run.
                if since_best >= s["patience"] and step >= s["min_frac"] * total:
                    stopped = True
            if step % s["ckpt_every"] == 0 or step == total or stopped:
                self.save_ckpt(stage, dict(net=net.state_dict(), opt=opt.state_dict(), rng=rng.bit_generator.state,
                                           gen=gen.get_state(), ema=None if ema is None else ema.state_dict(),
                                           step=step, elapsed=time.time() - t0, best=best, history=history,
                                           since_best=since_best, done=False, **self._stage_extra(stage)))
                self._maybe_stop(stage, step)
        bar.close()
        net.load_state_dict(best["net"])
        self.timings[stage] = time.time() - t0
        self.metrics[stage] = {"best": best["eval"], "best_step": best["step"], "history": history}
        self.save_ckpt(stage, dict(net=net.state_dict(), opt=opt.state_dict(), rng=rng.bit_generator.state,
                                   gen=gen.get_state(), ema=None if ema is None else ema.state_dict(),
                                   step=step, elapsed=self.timings[stage], best=best, history=history,
                                   since_best=since_best, done=True, **self._stage_extra(stage)))
        be = best["eval"] or {}
        self.log(f"[{stage}] best held-out NLL {best['score']:.4f} at step {best['step']} "
                 f"(N={eval_steps}, fold {be.get('fold', float('nan')):.2%}) in {self.timings[stage]:.0f} s")
        return net

    def _probe_starts(self, net, c, gen):
        """Start points that cover where pdf() can be asked, not only where the base samples:
        the base broadened PROBE_SPREAD x in its scale and, on R x S¹, uniform in phi. A
        concentrated spherical base (kappa 7-24 at grazing wi) leaves the antipode of its mean
        all but unsampled (probability ~1e-6 to 1e-20), so neither the loss nor a fold check on
        base samples sees the map there, and it folded (aurora, 85 deg: 28 % of that swath)."""
        with torch.no_grad():
            if npflow.planar(self.domain):
                mu = net.base.params(c)[0]
                return mu + PROBE_SPREAD * (net.base.sample(c, gen) - mu)
            mu_s, ls, _, _ = net.base.params(c)
            z = torch.rand(len(c), generator=gen, dtype=c.dtype).to(c.device)
            return torch.stack([mu_s + PROBE_SPREAD * torch.exp(ls) * torch.randn(len(c), generator=gen, dtype=c.dtype).to(c.device),
                                (2 * z - 1) * math.pi], dim=-1)

    def _fold_penalty(self, net, c, gen):
        """mean relu(fold_margin - det(I + J/N))² on the N-step map's own trajectories, started
        from _probe_starts (the base's low-density flanks, where folds hide, are probed too);
        evaluated at one random step k per batch."""
        s, n_steps = self.settings, self.steps
        cp = c[: max(256, len(c) // 4)]
        y = self._probe_starts(net, cp, gen)
        with torch.no_grad():
            k = int(torch.randint(n_steps, (1,), generator=gen))
            for j in range(k):
                y = y + net.vel(y, torch.tensor(j / n_steps, device=cp.device), cp) / n_steps
        _, J = net.vel.forward_jac(y, torch.tensor(k / n_steps, device=cp.device), cp)
        return torch.relu(s["fold_margin"] - step_det(J, n_steps)).pow(2).mean()

    def _stage_extra(self, stage):
        if stage == "reflow" and getattr(self, "_pairs", None) is not None:
            return {"pairs": self._pairs, "teacher_hash": self._teacher_hash}
        return {}

    def stage_flow(self, net):
        s = self.settings
        for p in net.base.parameters():
            p.requires_grad_(False)

        def batch(rng, gen):
            c, y1 = self.data.draw(s["batch"], rng)
            c = _t(c).to(self.device)
            y0 = net.base.sample(c, gen)
            return c, y0, _t(y1).to(self.device)

        return self._fm_stage("flow", net, batch, s["flow_steps"], s["flow_lr"], s["flow_eval_every"],
                              s["flow_eval_steps"], "2/3 flow", 2)

    def make_pairs(self, teacher):
        """Reflow pairs: wi and y0 ~ base(wi), y1 = RK4 solution of the teacher's ODE."""
        s = self.settings
        rng = np.random.default_rng([s["seed"], 3])
        gen = torch.Generator().manual_seed(s["seed"] * 1000 + 3)
        n, chunk = s["reflow_pairs"], 8192
        cs, y0s, y1s = [], [], []
        bar = self._progress(n, "3/3 reflow pairs")
        for i in range(0, n, chunk):
            m = min(chunk, n - i)
            c, _ = self.data.draw(m, rng)
            c = _t(c).to(self.device)
            y0 = teacher.base.sample(c, gen)
            y1 = teacher.rk4(c, y0, s["reflow_ode_steps"])
            cs.append(c)
            y0s.append(y0)
            y1s.append(y1)
            bar.update(m)
        bar.close()
        return {"c": torch.cat(cs), "y0": torch.cat(y0s), "y1": torch.cat(y1s)}

    def stage_reflow(self, teacher):
        s = self.settings
        stage = "reflow"
        self._teacher_hash = hashlib.sha256(b"".join(
            v.detach().cpu().numpy().tobytes() for v in teacher.state_dict().values())).hexdigest()[:16]
        state = self.load_ckpt(stage)
        if state is not None and state.get("teacher_hash") == self._teacher_hash and "pairs" in state:
            self._pairs = state["pairs"]
        else:
            t0 = time.time()
            self._pairs = self.make_pairs(teacher)
            self.timings["pairs"] = time.time() - t0
            self.log(f"[reflow] {len(self._pairs['c'])} pairs in {self.timings['pairs']:.0f} s")
            self.save_ckpt(stage, dict(pairs=self._pairs, teacher_hash=self._teacher_hash, step=0, done=False,
                                       pairs_only=True))
            state = None
        if s["student"] is None:
            student = copy.deepcopy(teacher)
        else:
            student = self.new_net(s["student"], salt=1)
            student.base.load_state_dict(teacher.base.state_dict())
        for p in student.base.parameters():
            p.requires_grad_(False)
        pairs = self._pairs
        npairs = len(pairs["c"])

        def batch(rng, gen):
            idx = torch.as_tensor(rng.integers(0, npairs, s["batch"]))
            return pairs["c"][idx], pairs["y0"][idx], pairs["y1"][idx]

        return self._fm_stage(stage, student, batch, s["reflow_steps"], s["reflow_lr"],
                              s["reflow_eval_every"], self.steps, "3/3 reflow", 4, penalty=s["fold_penalty"])

    # ----------------------------------------------------------------- export

    def export(self, net):
        s = self.settings
        final = self.evaluate(net, self.steps, fold_repeats=32)
        final["nll_numpy"] = self.evaluate_numpy(net, self.steps)
        if abs(final["nll_numpy"] - final["nll"]) > 1e-3:
            self.log(f"warning: numpy and torch held-out NLL differ: {final['nll_numpy']:.6f} vs {final['nll']:.6f}")
        settings = {k: (list(v) if isinstance(v, tuple) else v) for k, v in s.items()}
        meta = net.meta(self.steps, material={"name": self.name, **self.meta_extra.get("material", {})},
                        training={"settings": settings, "timings_s": self.timings,
                                  "torch": torch.__version__, "device": str(self.device)},
                        metrics={"holdout_nll": final["nll_numpy"], "holdout_nll_torch": final["nll"], "fold_fraction": final["fold"],
                                 "base_nll": self.metrics.get("base_nll"),
                                 "teacher": (self.metrics.get("flow") or {}).get("best"),
                                 "student": (self.metrics.get("reflow") or {}).get("best")})
        for k, v in self.meta_extra.items():
            if k != "material":
                meta.setdefault(k, v)
        if final["fold"] > 0:
            self.log(f"warning: the {self.steps}-step map folds for {final['fold']:.3%} of held-out samples "
                     "(their pdf is wrong): train with fold_penalty > 0 or more steps")
        meta["defensive"], meta["metrics"]["defensive_rv"] = self.choose_defensive(net.to_numpy(self.steps))
        path = self.out_dir / f"{_safe(self.name)}.flow.npz"
        npflow.save_model(path, meta, net.arrays())
        self.log(f"wrote {path} (held-out NLL {final['nll']:.4f}, fold {final['fold']:.2%})")
        return path

    def choose_defensive(self, model):
        """(defensive share, {share: held-out rv}). rv(eps) = E_p[p / q_eps] - 1 over pairs drawn
        from the target p (the source's normalized density, e.g. the ideal tabulation), q_eps =
        (1 - eps) q + eps / (2 pi): the chi-square divergence the renders pay, which the NLL the
        stages minimize does not see in the far tails."""
        if self.settings["defensive"] != "auto":
            return float(self.settings["defensive"]), {}
        source = self.data.source
        if not hasattr(source, "density"):
            self.log(f"defensive share {DEFENSIVE_CHOICES[0]:g}: the training source has no density to score others")
            return DEFENSIVE_CHOICES[0], {}
        wi, x1 = source.draw(DEFENSIVE_SAMPLES, np.random.default_rng([self.settings["seed"], 4099]))
        wo = get_domain(self.domain).to_dir(x1)
        p = source.density(wi, wo)
        q = model.with_defensive(0.0).pdf(wi, wo)
        scores = {}
        for eps in DEFENSIVE_CHOICES:
            with np.errstate(divide="ignore"):
                ratio = np.where(p > 0, p / npflow.with_uniform_share(q, eps), 0.0)
            scores[eps] = float(np.mean(ratio) - 1.0)
        best = min(scores, key=lambda e: (scores[e], e))
        self.log("held-out rv by defensive share: " + ", ".join(f"{e:g}: {r:.4g}" for e, r in scores.items())
                 + f" -> {best:g}")
        return best, {f"{e:g}": r for e, r in scores.items()}


def _safe(name):
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in str(name)) or "material"


def train(source, out_dir, preset="balanced", domain="disk", isotropic=True, name="material", meta=None,
          progress=True, log=print, device="cpu", stop_at=None, **overrides):
    """Train a flow for `source` and write out_dir/<name>.flow.npz; returns its path."""
    torch.manual_seed(0)
    settings = make_settings(preset, domain, **overrides)
    trainer = Trainer(source, out_dir, settings, domain=domain, isotropic=isotropic, name=name, meta=meta,
                      progress=progress, log=log, device=device, stop_at=stop_at)
    return trainer.run()
