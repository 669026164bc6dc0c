"""Issue-24 bake-time table: Final bakes (plan_tables' defaults, from the ideal tabulation) of
the shared RGL materials, this checkout beside another one, with the tables' rv.

    .venv/bin/python scripts/bake_speed.py [--materials a,b] [--repeat K] [--baseline CHECKOUT]
        [--out DIR] [--memory-budget BYTES] [--models DIR [--grids 512,256]] [--derived DIR] [--all-cores]

Per material: the bake's wall seconds and the process's CPU seconds (each the best of `repeat`; with --baseline the two checkouts
take turns within every repeat, so a load spike hits both), the planned resolution and bin
count, the size in MB, and the tables' rv at theta_i 0/30/60/75/85 (metrics.relative_variance_ref
against the ideal tabulation, 512² directions, as scripts/tables_acceptance.py reports it) with
its ratio to the ideal tabulation's own rv there (issue 22's "within 1.5x the ideal").
--baseline: another FlowBSDF checkout (e.g. `git archive <commit> | tar -x -C DIR`), imported
as `bake_baseline`. --memory-budget: plan_tables' budget (default: Final's), e.g. to cap a sharp
material's bin count for a shorter comparison. --models: also bake from each material's trained
model DIR/<name>.flow.npz (bake source "flow"; a column per point grid of --grids, e.g.
"flow256"), in turns with the ideal-sourced bake. --derived DIR: the bake as `flowbsdf bake` and
the add-on's Bake make it, timed whole: the tables saved to DIR/<label>/<name>.exr and what the
node reads beside them (export/derived.bake_derived: SVM and OSL textures, closure fit against
the file), and the sha256 of every file each kit wrote, compared with the first kit's (a cut that
keeps the outputs: "same"). --all-cores: threads on every core whatever the load (io.threads.
free_workers patched in each kit; on a shared machine it would fall back to one thread): the
wall a bake takes where its cores are idle, as far as a loaded machine shows it. The CPU/wall
column: the cores a bake used. Prints Markdown; asserts nothing (machines and loads differ).
"""
import argparse
import hashlib
import importlib
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))
from baseline import import_baseline  # noqa: E402
from bake.maths.geometry import incident  # noqa: E402
from bake.core.ideal import IdealSampler  # noqa: E402
from bake.core.settings import BakeSettings  # noqa: E402
from bake.core.planner import plan_tables  # noqa: E402
from bake.materials import open_material  # noqa: E402
from bake.materials.rgl import SHARED_FILES, shared_dir  # noqa: E402
from bake.core.metrics import relative_variance_ref  # noqa: E402

THETAS = (0, 30, 60, 75, 85)


def baseline_bake(checkout):
    """(open_material, IdealSampler, plan_tables) of another checkout's `bake`, as `bake_baseline`."""
    import_baseline(checkout)
    mats = importlib.import_module("bake_baseline.materials")
    ideal = importlib.import_module("bake_baseline.core.ideal")
    try:
        planner = importlib.import_module("bake_baseline.core.planner")
    except ModuleNotFoundError:         # a checkout from before bake/core/planner.py
        planner = importlib.import_module("bake_baseline.core.tabulate")
    try:        # a checkout with BakeSettings takes the settings as this one's `planned` does
        settings = importlib.import_module("bake_baseline.core.settings").BakeSettings
        return mats.open_material, ideal.IdealSampler, lambda mat, source, **s: planner.plan_tables(
            mat, source, settings(**s))
    except ModuleNotFoundError:
        return mats.open_material, ideal.IdealSampler, planner.plan_tables


def planned(mat, source, **settings):
    """This checkout's plan_tables with BakeSettings given as keywords, as a baseline checkout's
    (before BakeSettings) takes them."""
    return plan_tables(mat, source, BakeSettings(**settings))


def bake(kit, path, derived=None, **options):
    """(wall seconds, CPU seconds of the process, tables, {file: sha256} of what it wrote) of one
    Final bake with a fresh material and source (nothing cached); derived: (folder, bake_derived),
    the tables saved there and their exports and fit made, within the time."""
    open_mat, source, plan, *kit_options = kit
    t0, c0 = time.perf_counter(), time.process_time()
    mat = open_mat(path)
    tab = plan(mat, source(mat), **options, **(kit_options[0] if kit_options else {}))
    hashes = {}
    if derived:
        folder, bake_derived = derived
        for old in folder.glob(f"{mat.name}.*"):
            old.unlink()
        tab.save(folder / f"{mat.name}.exr")
        bake_derived(folder / f"{mat.name}.exr", material=mat, log=lambda line: None)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if derived:
        hashes = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.glob(f"{mat.name}.*"))}
    return wall, cpu, tab, hashes


def derived_of(checkout=None):
    """export/derived.bake_derived of this checkout or of the baseline (bake_baseline)."""
    return importlib.import_module(("bake_baseline" if checkout else "bake") + ".export.derived").bake_derived


def all_cores(packages):
    """Threads on every core in each of `packages` (bake, bake_baseline), whatever the load."""
    for name in packages:
        importlib.import_module(f"{name}.io.threads").free_workers = lambda cores: cores


def flow_kits(models, grids):
    """A kit per point grid baking from the material's trained model (bake source "flow")."""
    from bake.core.flow import load_model
    source = lambda mat: load_model(Path(models) / f"{mat.name.removesuffix('_rgb')}.flow.npz")  # noqa: E731
    return {f"flow{g}": (open_material, source, planned, {"grid": g}) for g in grids}


def rvs(mat, tab, ideal):
    return [relative_variance_ref(mat, tab, incident(t), ideal, k=512, seed=7)[0] for t in THETAS]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--materials", default=",".join(SHARED_FILES))
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--baseline", help="another FlowBSDF checkout, baked in turns with this one")
    p.add_argument("--out", help="save the tables here (<name>.<label>.exr)")
    p.add_argument("--memory-budget", type=int, help="plan_tables' memory_budget (default: its own)")
    p.add_argument("--models", help="also bake from DIR/<name>.flow.npz (bake source flow)")
    p.add_argument("--grids", default="512", help="with --models: the flow's point grids, e.g. 512,256")
    p.add_argument("--derived", help="also save the tables here and make their exports and fit (timed)")
    p.add_argument("--all-cores", action="store_true", help="threads on every core whatever the load")
    args = p.parse_args()
    options = {} if args.memory_budget is None else {"memory_budget": args.memory_budget}
    kits = {"new": (open_material, IdealSampler, planned)}
    if args.baseline:
        kits = {"old": baseline_bake(args.baseline), **kits}
    if args.models:
        kits.update(flow_kits(args.models, [int(g) for g in args.grids.split(",")]))
    if args.all_cores:
        all_cores(["bake"] + (["bake_baseline"] if args.baseline else []))
    derive = {}
    if args.derived:
        for lab in kits:
            (Path(args.derived) / lab).mkdir(parents=True, exist_ok=True)
            derive[lab] = (Path(args.derived) / lab, derived_of(lab == "old"))
    print(f"load: {os.getloadavg()[0]:.2f} (1 min) at start, {os.cpu_count()} cores", flush=True)
    head = ["material"] + [f"{lab} s" for lab in kits] + (["old/new"] if args.baseline else []) + \
        [f"{lab} cpu s" for lab in kits] + [f"{lab} CPU/wall" for lab in kits] + \
        ([f"{lab} files" for lab in kits] if args.derived else []) + \
        [f"{lab} res x bins, coords" for lab in kits] + [f"{lab} MB" for lab in kits] + \
        [f"{lab} rv {t} (/ideal)" for t in THETAS for lab in kits]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in args.materials.split(","):
        path = shared_dir() / f"{name}.bsdf"
        best, cpu, tables = {lab: np.inf for lab in kits}, {lab: np.inf for lab in kits}, {}
        cores, files = {}, {}
        for r in range(args.repeat):
            for lab, kit in kits.items():
                seconds, cpu_seconds, tables[lab], files[lab] = bake(kit, path, derive.get(lab), **options)
                if seconds < best[lab]:
                    cores[lab] = cpu_seconds / seconds
                best[lab], cpu[lab] = min(best[lab], seconds), min(cpu[lab], cpu_seconds)
                print(f"  {name} {lab} turn {r + 1}: {seconds:.1f} s, {cpu_seconds:.1f} s of CPU "
                      f"(load {os.getloadavg()[0]:.2f})" + "".join(f"\n    {f} {h}" for f, h in files[lab].items()),
                      flush=True)
        mat = open_material(path)
        ideal = IdealSampler(mat)
        rv = {lab: rvs(mat, tab, ideal) for lab, tab in tables.items()}
        ideal_rv = rvs(mat, ideal, ideal)
        if args.out:
            Path(args.out).mkdir(parents=True, exist_ok=True)
            for lab, tab in tables.items():
                tab.save(Path(args.out) / f"{name}.{lab}.exr")
        row = [name.removesuffix("_rgb")] + [f"{best[lab]:.1f}" for lab in kits]
        if args.baseline:
            row.append(f"{best['old'] / best['new']:.2f}")
        row += [f"{cpu[lab]:.1f}" for lab in kits] + [f"{cores[lab]:.2f}" for lab in kits]
        if args.derived:
            first = next(iter(files.values()))
            row += [f"{len(f)}, " + ("same" if f == first else "DIFFER") for f in files.values()]
        row += [f"{tab.rows} x {len(tab.theta_bins)} {getattr(tab, 'coords', 'wo')}" for tab in tables.values()]
        row += [f"{tab.nbytes / 2**20:.2f}" for tab in tables.values()]
        row += [f"{rv[lab][i]:.3g} ({rv[lab][i] / ideal_rv[i]:.2f})" for i in range(len(THETAS)) for lab in kits]
        lines.append("| " + " | ".join(row) + " |")
        print(lines[-1], flush=True)
    print(f"\nFinal bake wall seconds{'' if not options else f' ({options})'}"
          f"{' with its exports and fit' if args.derived else ''}{', threads on all cores' if args.all_cores else ''}, "
          f"best of {args.repeat} (turns interleaved); load at end {os.getloadavg()[0]:.2f}\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
