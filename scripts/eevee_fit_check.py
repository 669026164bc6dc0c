"""The EEVEE fit (closure_fit: the fit's "eevee", isotropic lobes) against the measured file and
against the fit: per file the median relative L1 of luminance f cos against the FILE of the
fit, of the EEVEE fit and of the fit with its anisotropy dropped (what EEVEE renders of the fit
without its own closures), at the fit's error angles (closure_fit.fit_errors: same samples);
and the seconds of the fit and, inside the same run, of the EEVEE part (_isotropic and its
share of the error evaluation, timed by wrapping them): its cost as a share of the fit's.

    .venv/bin/python scripts/eevee_fit_check.py TABLES_DIR NAME [NAME...] [--rgl DIR] [--json DIR]
"""
import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bake.core.table_files import open_tables  # noqa: E402
from bake.export import closure_fit as cf  # noqa: E402
from bake.materials import open_material  # noqa: E402


def no_anisotropy(fit):
    f = copy.deepcopy(fit)
    f["anisotropy"] = [[0.0] * len(k) for k in f["anisotropy"]]
    return f


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("tables_dir", type=Path)
    ap.add_argument("names", nargs="+")
    ap.add_argument("--rgl", type=Path, default=ROOT.parent / "shared" / "data" / "rgl")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    spent = {"iso": 0.0}
    isotropic = cf._isotropic

    def timed(*a):
        t0 = time.perf_counter()
        try:
            return isotropic(*a)
        finally:
            spent["iso"] += time.perf_counter() - t0
    cf._isotropic = timed
    rows = {}
    for name in args.names:
        tables = open_tables(args.tables_dir / f"{name}.exr")
        material = open_material(str(args.rgl / f"{name}_rgb.bsdf"))
        spent["iso"] = 0.0
        t0 = time.perf_counter()
        fit = cf.fit_closures(tables, material=material)
        secs = time.perf_counter() - t0
        degs = fit["l1_theta_deg"]
        t1 = time.perf_counter()
        (one,) = cf.fit_errors([fit], tables, degs, material, seed=1)
        err_one = time.perf_counter() - t1
        (noaniso,) = cf.fit_errors([no_anisotropy(fit)], tables, degs, material, seed=1)
        t2 = time.perf_counter()
        cf.fit_errors([fit, fit["eevee"]], tables, degs, material, seed=1)
        err_two = time.perf_counter() - t2
        extra = spent["iso"] + max(err_two - err_one, 0.0)
        rows[name] = {"fit": fit["error"], "eevee": fit["eevee"]["error"], "fit_no_anisotropy": float(np.median(noaniso)),
                      "fit_mean": float(np.mean(fit["l1"])), "eevee_mean": float(np.mean(fit["eevee"]["l1"])),
                      "no_anisotropy_mean": float(np.mean(noaniso)),
                      "seconds": round(secs, 2), "eevee_seconds": round(extra, 2)}
        print(name, json.dumps(rows[name]), flush=True)
        if args.json:
            args.json.mkdir(parents=True, exist_ok=True)
            (args.json / f"{name}.fit.json").write_text(json.dumps(fit, indent=1))
    return rows


if __name__ == "__main__":
    main()
