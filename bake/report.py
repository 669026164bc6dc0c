"""The yardstick table: rv of every sampler per material and incident angle (Markdown + CSV)."""
import csv
import time

import numpy as np

from .baselines import CosineSampler, UniformSampler, fit_ggx
from .geometry import incident, luminance
from .ideal import IdealSampler
from .metrics import relative_variance

THETAS_DEG = (0, 30, 60, 75, 85)


def yardstick_rows(name, material, thetas=THETAS_DEG, n=1 << 17, seed=0, extra=(), log=print):
    """One row per (sampler, theta_i): rv and the albedo estimate, plus the quadrature albedo."""
    t0 = time.perf_counter()
    ideal = IdealSampler(material)
    ggx = fit_ggx(material, ideal)
    samplers = [CosineSampler(), ggx, ideal, *extra]
    rows = []
    for theta in thetas:
        wi = incident(theta)
        albedo = float(luminance(ideal.albedo(wi)))
        for sampler in samplers:
            rv, estimate = relative_variance(material, sampler, wi, n=n, seed=seed)
            rows.append({"material": name, "sampler": sampler.name, "theta_i": theta, "rv": rv,
                         "albedo_mc": estimate, "albedo_quadrature": albedo})
    log(f"[yardsticks] {name}: {repr(ggx)}, {time.perf_counter() - t0:.1f}s")
    return rows


def median_rv(rows, sampler):
    return float(np.median([r["rv"] for r in rows if r["sampler"] == sampler]))


def markdown_table(rows, thetas=THETAS_DEG):
    """Materials x theta_i, one rv column block per sampler."""
    samplers = list(dict.fromkeys(r["sampler"] for r in rows))
    materials = list(dict.fromkeys(r["material"] for r in rows))
    rv = {(r["material"], r["sampler"], r["theta_i"]): r["rv"] for r in rows}
    head = "| material | sampler | " + " | ".join(f"{t}°" for t in thetas) + " |"
    lines = [head, "|" + "---|" * (len(thetas) + 2)]
    for m in materials:
        for s in samplers:
            cells = " | ".join(_fmt(rv.get((m, s, t), float("nan"))) for t in thetas)
            lines.append(f"| {m} | {s} | {cells} |")
    lines.append("")
    lines.append("median rv over all cells: " + ", ".join(f"{s} {_fmt(median_rv(rows, s))}" for s in samplers))
    return "\n".join(lines)


def _fmt(x):
    if not np.isfinite(x):
        return "inf" if x > 0 else "nan"
    return f"{x:.3g}" if x >= 1e-3 else f"{x:.2e}"


def write_csv(rows, path):
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
