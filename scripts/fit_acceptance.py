"""How far the closure fit (what EEVEE, Cycles with OSL off and lamp-lit GPU renders show) is
from the MEASURED FILE: relative L1 of luminance f cos, int |Y(f_fit) - Y(f_file)| cos dw /
int Y(f_file) cos dw (bake/export/closure_fit.fit_error: importance-sampled, the tables lead
the samples to the file's lobes), at view angles 0/30/60/75/85 deg and between the fit's knots
(7.5, 22.5, 45, 54, 67.5, 76, 82.5 deg), per file: an older fit file beside the new one when
given (--old DIR: <name>.fit.json of FIT_VERSION 4, one Diffuse + one GGX lobe), the new fit
made now from the tables, its seconds, and its EEVEE fit (FIT_VERSION 8: isotropic lobes, what
the node's EEVEE output renders). Last column (`between`): the most the fit's own error half-way
between two knots (its `l1`: every knot and midpoint up to 88 deg) exceeds the mean of those two
knots' errors, and where: a fit whose lobes change identity between knots is good at both and
poor half-way (irid_flake_paint1's 82.5 deg before the relabelling: +0.12).

    .venv/bin/python scripts/fit_acceptance.py TABLES_DIR [--old DIR] [--rgl DIR] [--material NAME ...]
        [--variant full|ac|ab|a|c|b|none] [--json DIR]

--variant (the FIT_VERSION 7 parts, for their ablation): a = tilted GGX lobes, b = the 4th GGX
lobe, c = a tilted Diffuse; full = abc (the default, the shipped fit); none = FIT_VERSION 6's
closures (3 lobes, no tilts). --json DIR: the new fits written there as <name>.fit.json.

TABLES_DIR holds `flowbsdf bake`'s <name>.exr of RGL files named <name>_rgb.bsdf in --rgl.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bake.maths.geometry import luminance  # noqa: E402
from bake.core.table_files import open_tables  # noqa: E402
from bake.export import closure_fit as cf  # noqa: E402
from bake.materials import open_material  # noqa: E402

ON = (0.0, 30.0, 60.0, 75.0, 85.0)
BETWEEN = (7.5, 22.5, 45.0, 54.0, 67.5, 76.0, 82.5)


def old_eval(fit, wi, wo):
    """FIT_VERSION 4's f: kd / pi + ks f_ggx(alpha), all three lerped in x (roughness lerped)."""
    x = 1.0 - wi[2]
    kd = np.array([np.interp(x, fit["x"], np.asarray(fit["diffuse"])[:, c]) for c in range(3)])
    ks = np.array([np.interp(x, fit["x"], np.asarray(fit["specular"])[:, c]) for c in range(3)])
    r = np.interp(x, fit["x"], fit["roughness"])
    with np.errstate(divide="ignore", invalid="ignore"):
        spec = np.where(wo[:, 2] > 0, cf.ggx_fcos(wi, wo, r * r) / wo[:, 2], 0.0)
    return np.where((wo[:, 2] > 0)[:, None], kd / np.pi + ks * spec[:, None], 0.0)


def l1(f_eval, tables, material, deg):
    knot = cf._Knot(tables, np.radians(deg), seed=11)
    f = material.eval(knot.wi, knot.wo) * knot.wo[:, 2:3]
    ff = f_eval(knot.wi, knot.wo) * knot.wo[:, 2:3]
    return float(knot.w @ np.abs(luminance(ff - f)) / (knot.w @ luminance(f)))


def between_excess(fit):
    """(excess, deg): the largest l1 half-way between knots less the mean of its two knots' l1."""
    degs, l1 = fit["l1_theta_deg"], fit["l1"]
    knots = set(fit["theta_deg"])
    out = [(l1[i] - 0.5 * (l1[i - 1] + l1[i + 1]), d) for i, d in enumerate(degs)
           if d not in knots and 0 < i < len(degs) - 1]
    return max(out) if out else (0.0, float("nan"))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tables_dir", type=Path)
    ap.add_argument("--old", type=Path)
    ap.add_argument("--rgl", type=Path, default=ROOT.parent / "shared" / "data" / "rgl")
    ap.add_argument("--material", nargs="*")
    ap.add_argument("--variant", default="full", choices=["full", "ac", "ab", "a", "c", "b", "none"])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    parts = "abc" if args.variant == "full" else ("" if args.variant == "none" else args.variant)
    cf.TILT_GGX, cf.TILT_DIFFUSE = "a" in parts, "c" in parts
    cf.LOBES, cf.VIEW_ALIGNED = (4, 3) if "b" in parts else (3, 2)
    print(f"variant {args.variant}: GGX tilts {cf.TILT_GGX}, Diffuse tilt {cf.TILT_DIFFUSE}, {cf.LOBES} GGX lobes")
    degs = sorted(ON + BETWEEN)
    print("relative L1 of luminance f cos against the file; columns: view angle (deg); * between knots")
    print(f"{'file':20s} {'fit':5s} " + " ".join(f"{d:5.1f}{'*' if d in BETWEEN else ' '}" for d in degs)
          + "  median  s    between")
    med = {"old": [], "new": [], "eevee": []}
    for path in sorted(args.tables_dir.glob("*.exr")):
        name = path.stem
        if "." in name or (args.material and name not in args.material):
            continue
        rgl = args.rgl / f"{name}_rgb.bsdf"
        if not rgl.is_file():
            continue
        tables, material = open_tables(path), open_material(str(rgl))
        rows = []
        if args.old and (args.old / f"{name}.fit.json").is_file():
            old = json.loads((args.old / f"{name}.fit.json").read_text())
            rows.append(("old", lambda wi, wo, old=old: old_eval(old, wi, wo), None, None))
        t0 = time.perf_counter()
        new = cf.fit_closures(tables, material=material)
        seconds = time.perf_counter() - t0
        if args.json:
            args.json.mkdir(parents=True, exist_ok=True)
            (args.json / f"{name}.fit.json").write_text(json.dumps(new, indent=1))
        rows.append(("new", lambda wi, wo: cf.eval_fit(new, wi, wo), seconds, new))
        rows.append(("eevee", lambda wi, wo: cf.eval_fit(new["eevee"], wi, wo), None, new["eevee"]))   # what EEVEE renders
        for label, f_eval, sec, fit in rows:
            vals = [l1(f_eval, tables, material, d) for d in degs]
            on = [v for d, v in zip(degs, vals) if d in ON]
            med[label].append(on)
            print(f"{name[:20]:20s} {label:5s} " + " ".join(f"{v:6.3f}" for v in vals)
                  + f"  {np.median(vals):6.3f}" + (f" {sec:4.1f}" if sec else "     ")
                  + ("  {:+.3f} at {:g}".format(*between_excess(fit)) if fit else ""), flush=True)
    for label, rows in med.items():
        if rows:
            a = np.array(rows)
            print(f"median over files and the five angles ({label}): {np.median(a):.3f}; per angle "
                  + " ".join(f"{d:.0f}: {v:.3f}" for d, v in zip(ON, np.median(a, axis=0))))


if __name__ == "__main__":
    main()
