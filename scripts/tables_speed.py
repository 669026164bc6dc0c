"""Issue-24 speed table: sample+pdf throughput of the baked tables beside Mitsuba's `measured`.

    .venv/bin/python scripts/tables_speed.py [--tables DIR] [--materials a,b] [--n N] [--repeat K]
        [--baseline CHECKOUT] [--clock wall|cpu]

Per shared RGL material: the tables in DIR/<name>.exr (baked from the ideal tabulation and
saved there when missing, as scripts/tables_acceptance.py does) and Mitsuba's sampler on the
same file. Each is timed on one thread, sample() then pdf() on the samples, with one wi per
call (40 degrees) and with a new wi per sample (uniform in cos theta and phi). The samplers
take turns within every repeat (interleaved, so a load spike hits all of them) and the best
of the repeats counts. --baseline: another FlowBSDF checkout (e.g. `git archive <commit> |
tar -x -C DIR`), whose Tables, on the same files, are timed in the same turns: before and
after in one run. --clock cpu times each call by the process's CPU time (all its threads)
instead of the wall clock: on a shared machine under load the wall clock also counts the time
the scheduler gives to other processes, which best-of-N cannot remove when the load stays high.
Prints samples/s and ratios; asserts nothing (machines and loads differ).
"""
import argparse
import importlib
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))       # this checkout's bake, not an installed one (pip install -e elsewhere)
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))
from baseline import import_baseline  # noqa: E402
from conftest import RGL_FILES, rgl_dir  # noqa: E402

from bake.maths import fasttables  # noqa: E402
from bake.quality.bench import random_incident, single_threaded  # noqa: E402
from bake.maths.geometry import incident  # noqa: E402
from bake.core.table_files import open_tables  # noqa: E402


def load_tables(path, name):
    if not path.is_file():
        from bake.core.ideal import IdealSampler
        from bake.materials import open_material
        from bake.core.planner import plan_tables
        print(f"[bake] {name}: no {path}, baking from the ideal tabulation", flush=True)
        mat = open_material(rgl_dir() / f"{name}.bsdf")
        plan_tables(mat, IdealSampler(mat)).save(path)
    return open_tables(path)


def baseline_package(checkout):
    """The module of open_tables and the fasttables module of another checkout's `bake`
    (scripts/baseline.py)."""
    import_baseline(checkout)
    try:
        fast = importlib.import_module("bake_baseline.maths.fasttables")
    except ModuleNotFoundError:         # a checkout from before bake/maths/
        fast = importlib.import_module("bake_baseline.core.fasttables")
    try:
        return importlib.import_module("bake_baseline.core.table_files"), fast
    except ModuleNotFoundError:         # a checkout from before bake/core/table_files.py
        return importlib.import_module("bake_baseline.core.tables"), fast


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def seconds(fn, clock="wall"):
    now = CLOCKS[clock]
    t0 = now()
    fn()
    return now() - t0


def time_turns(samplers, wi, u, repeat, clock="wall"):
    """{label: sample+pdf samples/s}, best of `repeat` turns; every turn times each sampler once."""
    best = {label: np.inf for label in samplers}
    wos = {}
    for label, s in samplers.items():      # warm-up: JIT compilation, the C library's views
        with single_threaded(s):
            wos[label] = s.sample(wi, u)[0]
            s.pdf(wi, wos[label])
    for _ in range(repeat):
        for label, s in samplers.items():
            with single_threaded(s):
                t = seconds(lambda: s.sample(wi, u), clock) + seconds(lambda: s.pdf(wi, wos[label]), clock)
            best[label] = min(best[label], t)
    return {label: len(u) / t for label, t in best.items()}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tables", default="/tmp/flowbsdf_speed_tables", help="folder of baked tables (<name>.exr)")
    p.add_argument("--materials", default=",".join(RGL_FILES))
    p.add_argument("--n", type=int, default=1 << 17, help="samples per call")
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--baseline", help="another FlowBSDF checkout, timed beside this one")
    p.add_argument("--clock", choices=sorted(CLOCKS), default="wall",
                   help="wall: elapsed time; cpu: the process's CPU time (a loaded machine)")
    args = p.parse_args()
    from bake.quality.mitsuba_peer import MitsubaMeasuredSampler
    print(f"tables: {fasttables.REASON if fasttables.load() else fasttables.REASON}")
    base = None
    if args.baseline:
        base_tables, base_fast = baseline_package(args.baseline)
        base_fast.load()
        print(f"baseline: {base_fast.REASON}")
    out = Path(args.tables)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    u = rng.random((args.n, 2))
    modes = {"one wi": incident(40.0, 0.3), "new wi per sample": random_incident(args.n, seed=5)}
    labels = ["tables"] + (["baseline"] if args.baseline else []) + ["mitsuba"]
    head = ["material", "MB"] + [f"{m}: {x}" for m in modes for x in
                                 [f"{lab} M/s" for lab in labels] + ["tables/mitsuba"]
                                 + (["baseline/mitsuba", "tables/baseline"] if args.baseline else [])]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    ratios = {m: [] for m in modes}
    for name in args.materials.split(","):
        path = out / f"{name}.exr"
        tab = load_tables(path, name)
        samplers = {"tables": tab}
        if args.baseline:
            base = base_tables.open_tables(path)
            samplers["baseline"] = base
        samplers["mitsuba"] = MitsubaMeasuredSampler(rgl_dir() / f"{name}.bsdf")
        row = [name.removesuffix("_rgb"), f"{tab.nbytes / 1e6:.2f}"]
        for mode, wi in modes.items():
            rate = time_turns(samplers, wi, u, args.repeat, args.clock)
            row += [f"{rate[lab] / 1e6:.2f}" for lab in labels]
            row.append(f"{rate['tables'] / rate['mitsuba']:.2f}")
            ratios[mode].append(rate["tables"] / rate["mitsuba"])
            if args.baseline:
                row += [f"{rate['baseline'] / rate['mitsuba']:.2f}", f"{rate['tables'] / rate['baseline']:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
        print(lines[-1], flush=True)
    print(f"\nsample+pdf, samples/s (M/s), one thread, n = {args.n}, best of {args.repeat} interleaved turns, "
          f"{args.clock} clock\n")
    print("\n".join(lines))
    for mode, r in ratios.items():
        print(f"{mode}: tables at or above Mitsuba on {sum(x >= 1 for x in r)}/{len(r)}; "
              f"tables/mitsuba min {min(r):.2f}, median {np.median(r):.2f}")


if __name__ == "__main__":
    main()
