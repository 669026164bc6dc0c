"""Relative variance vs Euler steps N, with and without reflow, on a synthetic GGX lobe.

    .venv/bin/python scripts/flow_rv_table.py disk 0.2 balanced /tmp/rv_disk [JSON overrides]

Trains (or resumes from the checkpoints in OUT) and prints rv = Var[q/p] / E[q/p]² per
theta_i for the teacher (stage 2, no reflow) and the reflowed student, each at several
N, with the fraction of samples whose Euler map folds.
"""
import trainer  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)

import copy
import json
import sys

import numpy as np
import torch

from bake import flow as F
from trainer.synthetic import GGXReflection
from trainer.train import Trainer, make_settings


def rv_torch(net, src, theta, n_steps, n=1 << 15, seed=5):
    net64 = copy.deepcopy(net).double()
    wi = np.array([np.sin(theta), 0.0, np.cos(theta)])
    c = torch.from_numpy(np.broadcast_to(F.cond_features(wi, True), (n, 2)).copy())
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        y0 = net64.base.sample(c, gen)
        lp0 = net64.base.log_prob(c, y0)
        y1, logdet, min_det = net64.euler(c, y0, n_steps)
    y1 = y1.numpy()
    cmap = F.MAPS[net.domain]
    if net.domain == "spherical":
        y1[:, 1] = F.wrap_angle(y1[:, 1])
    wo = cmap.to_dir(y1)
    log_p = (lp0 - logdet).numpy() - cmap.log_dw_dy(y1)
    w = src.density(wi, wo) / np.exp(log_p)
    return w.var() / w.mean() ** 2, float((min_det <= 0).double().mean())


def main(argv):
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


if __name__ == "__main__":
    main(sys.argv[1:])
