"""Relative variance vs Euler steps N, with and without reflow.

Synthetic GGX lobe (trains, or resumes from the checkpoints in OUT):

    .venv/bin/python scripts/flow_rv_table.py disk 0.2 balanced /tmp/rv_disk [JSON overrides]

prints rv = Var[q/p] / E[q/p]² per theta_i for the teacher (stage 2, no reflow) and the
reflowed student, each at several N, with the fraction of samples whose Euler map folds.

A trained model against its TRUE material (no training, nothing written):

    .venv/bin/python scripts/flow_rv_table.py trained CKPT_DIR MATERIAL [--model FILE.flow.npz]
        [--steps 2,4,8,16,32] [--thetas 0,30,60,75,85] [--samples 32768] [--seed 5]

CKPT_DIR is a training folder's ckpt/ (base.pt, flow.pt, reflow.pt); MATERIAL the material
file it was trained on (.bsdf / .binary). The teacher is flow.pt's best weights, the student
reflow.pt's; the architecture comes from the model file's training settings (default: the
*.flow.npz next to CKPT_DIR, else the weights' shapes). Each cell is the rv of the one-sample
estimator lum(f)·cos / pdf of the flow's own N-step sampler with its exact N-step pdf
(float64 torch, the same protocol as bake.core.metrics.sample_weights: lost samples count as 0),
against material.eval, plus the share of samples with det(I + J/N) <= 0 at some step.
"""
import trainer  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse
import copy
import glob
import json
import os
import sys
import time

import numpy as np
import torch

from bake.core import flow as F
from bake.core import flow_maps
from bake.maths import special
from trainer.synthetic import GGXReflection
from trainer.train import COMMON, Trainer, make_settings


def flow_samples(net, theta, n_steps, n=1 << 15, seed=5):
    """wi (3,), y1 (n,2) flow coordinates, log pdf (n,) per steradian, min det (n,) of the
    N-step Euler sampler (float64)."""
    net64 = copy.deepcopy(net).double()
    wi = np.array([np.sin(theta), 0.0, np.cos(theta)])
    c = torch.from_numpy(np.broadcast_to(F.cond_features(wi, True), (n, 2)).copy())
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        y0 = net64.base.sample(c, gen)
        lp0 = net64.base.log_prob(c, y0)
        y1, logdet, min_det = net64.euler(c, y0, n_steps)
    y1 = y1.numpy()
    cmap = flow_maps.MAPS[net.domain]
    if not F.planar(net.domain):
        y1[:, 1] = special.wrap_angle(y1[:, 1])
    wi_rows = np.broadcast_to(wi, (n, 3))
    log_p = (lp0 - logdet).numpy() - cmap.log_dw_dy(y1, wi_rows)
    return wi, y1, log_p, min_det.numpy()


def flow_directions(net, wi, y1):
    """wo of flow coordinates y1 and whether each is above the horizon (slope maps lose some)."""
    wo = flow_maps.MAPS[net.domain].to_dir(y1, np.broadcast_to(wi, (len(y1), 3)))
    return wo, wo[:, 2] > 0


def rv_torch(net, src, theta, n_steps, n=1 << 15, seed=5):
    wi, y1, log_p, min_det = flow_samples(net, theta, n_steps, n, seed)
    wo, ok = flow_directions(net, wi, y1)
    w = np.where(ok, src.density(wi, wo) / np.exp(log_p), 0.0)
    return w.var() / w.mean() ** 2, float(np.mean(min_det <= 0))


def synthetic_main(argv):
    domain, alpha, preset, out = argv[0], float(argv[1]), argv[2], argv[3]
    over = json.loads(argv[4]) if len(argv) > 4 else {}
    src = GGXReflection(domain, alpha=alpha, alpha_slope=0.5, theta_max_deg=80)
    tr = Trainer(src, out, make_settings(preset, domain, **over), domain=domain, name="ggx", log=print)
    teacher = copy.deepcopy(tr.stage_flow(tr.stage_base()))
    student = tr.stage_reflow(copy.deepcopy(teacher))
    tr.export(student)
    print("timings (s):", {k: round(v, 1) for k, v in tr.timings.items()})
    thetas = (0, 30, 60, 75)
    print("rv/fold at theta_i =", thetas)
    for name, net in (("teacher", teacher), ("student", student)):
        for n_steps in (1, 2, 4, 8, 16, 64):
            cells = [rv_torch(net, src, np.radians(t), n_steps) for t in thetas]
            print(f"{name:8s} N={n_steps:3d} " + " ".join(f"{r:9.3f}/{f:.2%}" for r, f in cells), flush=True)


# --------------------------------------------------------------------------- trained models

def _mlp_shape(state, prefix):
    """(width, depth, n_in, n_out) of an MLP from its state dict entries."""
    idx = sorted({int(k[len(prefix):].split(".")[0]) for k in state if k.startswith(prefix)})
    w = [state[f"{prefix}{i}.weight"] for i in idx]
    return w[0].shape[0], len(w) - 1, w[0].shape[1], w[-1].shape[0]


def net_from_state(state, domain, isotropic, settings):
    """A FlowNet holding `state` (architecture from the weights' shapes; the base's scalar
    settings, which are not in the weights, from `settings`)."""
    from trainer.model import FlowNet
    vw, vd, vin, _ = _mlp_shape(state, "vel.net.layers.")
    bw, bd, _, bout = _mlp_shape(state, "base.net.layers.")
    cd = F.cond_dim(isotropic)
    time_freq = (vin - F.space_dim(domain) - 1 - cd) // 2
    comps = 1
    while F.planar(domain) and F.base_outputs(domain, comps) < bout:
        comps += 1
    net = FlowNet(domain, isotropic, vel_width=vw, vel_depth=vd, time_freq=time_freq, base_width=bw,
                  base_depth=bd, log_sigma_range=settings["log_sigma_range"], kappa_max=settings["kappa_max"],
                  base_components=comps)
    net.load_state_dict(state)
    return net.eval()


def load_trained(ckpt_dir, model_path=None):
    """(teacher, student, meta of the model file or None) from a training folder's ckpt/."""
    if model_path is None:   # <out>/<name>.train/ckpt -> <out>/<name>.train/*.flow.npz or <out>/<name>.flow.npz
        train_dir = os.path.dirname(os.path.abspath(ckpt_dir.rstrip("/")))
        found = sorted(glob.glob(os.path.join(train_dir, "*.flow.npz")))
        if not found and train_dir.endswith(".train"):
            found = glob.glob(train_dir[: -len(".train")] + ".flow.npz")
        model_path = found[0] if len(found) == 1 else None
    meta = F.load_model(model_path).meta if model_path else None
    settings = dict(COMMON)
    domain, isotropic = "disk", True
    if meta is not None:
        settings.update(meta.get("training", {}).get("settings", {}))
        domain, isotropic = meta["domain"], bool(meta["isotropic"])
    nets = []
    for stage in ("flow", "reflow"):
        state = torch.load(os.path.join(ckpt_dir, f"{stage}.pt"), map_location="cpu", weights_only=False)
        if not state.get("done"):
            raise SystemExit(f"{stage}.pt in {ckpt_dir} is not a finished stage")
        # At the end of a stage the checkpoint's net is its best (EMA) weights.
        nets.append(net_from_state(state["best"]["net"], domain, isotropic, settings))
    return nets[0], nets[1], meta, model_path


def material_weights(material, wi, y1, log_p, domain):
    """w = lum(f)·cos / pdf as bake.core.metrics.sample_weights (lost samples: 0)."""
    from bake.maths.geometry import luminance
    wo = flow_maps.MAPS[domain].to_dir(y1, np.broadcast_to(wi, (len(y1), 3)))
    with np.errstate(over="ignore"):
        pdf = np.exp(log_p)
    ok = (pdf > 0) & (wo[:, 2] > 0) & np.isfinite(pdf)
    wo_safe = np.where(ok[:, None], wo, np.array([0.0, 0.0, 1.0]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ok, luminance(material.eval(wi, wo_safe)) * np.maximum(wo_safe[:, 2], 0) / pdf, 0.0)


def crosscheck(net, model_file_arrays, theta, n_steps, domain, k=64, seed=11):
    """max relative difference between torch's forward pdf and bake.core.flow's inverse pdf (numpy,
    the exported float32 weights evaluated at n_steps) on k samples, and how many of them fold.
    Where the N-step map folds it is not injective: the forward pdf p0/|det| is then not the
    sampler's density and the inverse may find another preimage, so they may disagree."""
    wi, y1, log_p, min_det = flow_samples(net, theta, n_steps, k, seed)
    model = net.to_numpy(n_steps)
    if model_file_arrays is not None:   # the student: check it is the exported file's weights
        for key, v in net.arrays().items():
            assert np.array_equal(v.astype(np.float32), model_file_arrays[key]), key
    wo = flow_maps.MAPS[domain].to_dir(y1, np.broadcast_to(wi, (len(y1), 3)))
    ok = wo[:, 2] > 0                   # slope maps lose samples below the horizon: pdf 0 both ways
    p_np = model.pdf(wi, wo[ok])
    return float(np.max(np.abs(p_np / np.exp(log_p[ok]) - 1.0))), int(np.sum(min_det <= 0))


def trained_main(argv):
    ap = argparse.ArgumentParser(prog="flow_rv_table.py trained")
    ap.add_argument("ckpt_dir")
    ap.add_argument("material")
    ap.add_argument("--model", default=None, help="the trained model file (for its settings; default: found)")
    ap.add_argument("--steps", default="2,4,8,16,32")
    ap.add_argument("--thetas", default="0,30,60,75,85")
    ap.add_argument("--samples", type=int, default=1 << 15)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-baseline", action="store_true", help="skip the cosine-sampler row")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from bake.materials import open_material
    steps = [int(s) for s in args.steps.split(",")]
    thetas = [float(t) for t in args.thetas.split(",")]
    material = open_material(args.material)
    teacher, student, meta, model_path = load_trained(args.ckpt_dir, args.model)
    domain = teacher.domain
    name = (meta or {}).get("material", {}).get("name", os.path.basename(args.material))
    print(f"material {name} ({args.material}); checkpoints {args.ckpt_dir}; model file {model_path}")
    print(f"teacher vel {teacher.config['vel_width']}x{teacher.config['vel_depth']}, "
          f"student vel {student.config['vel_width']}x{student.config['vel_depth']}, domain {domain}, "
          f"trained N={(meta or {}).get('steps')}; {args.samples} samples/cell, seed {args.seed}, "
          f"torch threads {torch.get_num_threads()}, load {os.getloadavg()[0]:.2f}", flush=True)
    # Cross-checks: the student is the exported file; torch pdf == bake.core.flow's exact pdf.
    file_arrays = None
    if model_path:
        with np.load(model_path, allow_pickle=False) as z:
            file_arrays = {k: z[k] for k in z.files if k.startswith(("base.", "vel."))}
    for label, net, arrs in (("teacher", teacher, None), ("student", student, file_arrays)):
        errs = [crosscheck(net, arrs, np.radians(60.0), n, domain) for n in (steps[0], steps[-1])]
        print(f"crosscheck {label}: max |pdf_numpy / pdf_torch - 1| at N={steps[0]},{steps[-1]} (64 samples, "
              f"60°): {errs[0][0]:.2e} ({errs[0][1]} folded), {errs[1][0]:.2e} "
              f"({errs[1][1]} folded)" + (" (weights == model file)" if arrs else ""), flush=True)
    head = "| model | N | " + " | ".join(f"{t:g}°" for t in thetas) + " | fold % (max) | s |"
    lines = [head, "|---" * (len(thetas) + 4) + "|"]
    if not args.no_baseline:
        from bake.core.baselines import CosineSampler
        from bake.maths.geometry import incident
        from bake.core.metrics import sample_weights
        cells = []
        for t in thetas:
            w = sample_weights(material, CosineSampler(), incident(t), args.samples, seed=args.seed)
            cells.append(w.var() / w.mean() ** 2)
        lines.append("| cosine | - | " + " | ".join(f"{r:.4g}" for r in cells) + " | - | - |")
        print(lines[-1], flush=True)
    results = {}
    for label, net in (("teacher", teacher), ("student", student)):
        for n_steps in steps:
            t0 = time.time()
            cells, folds = [], []
            for t in thetas:
                wi, y1, log_p, min_det = flow_samples(net, np.radians(t), n_steps, args.samples, args.seed)
                w = material_weights(material, wi, y1, log_p, domain)
                cells.append(float(w.var() / w.mean() ** 2))
                folds.append(float(np.mean(min_det <= 0)))
            results[(label, n_steps)] = (cells, folds)
            lines.append(f"| {label} | {n_steps} | " + " | ".join(f"{r:.4g}" for r in cells)
                         + f" | {100 * max(folds):.3f} | {time.time() - t0:.0f} |")
            print(lines[-1], f"  folds per theta: {['%.4f' % f for f in folds]}  load {os.getloadavg()[0]:.2f}",
                  flush=True)
    print()
    print(f"### {name}\n")
    print("\n".join(lines))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "trained":
        trained_main(sys.argv[2:])
    else:
        synthetic_main(sys.argv[1:])
