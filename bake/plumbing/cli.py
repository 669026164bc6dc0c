"""The `flowbsdf` command: one subcommand per job.

    library FOLDER --out DIR               an asset library of measured files (blender_addon/artist/library.py,
                                           run as a program of its own)
    check, yardsticks, bake, report, run   here: a manifest, --material, --out (but check)
                                           --out is the output folder (models/, tables/, report/
                                           inside) for train and farm task too
    train                                  the trainer (torch) in a subprocess; its parser is
                                           bake/plumbing/job.py's add_train_arguments
    stress                                 bake/quality/stress.py
    farm openjd, farm task                 bake/plumbing/farm.py
    render, compare                        bake/plumbing/tracer_commands.py (the reference tracer)

A FlowBSDFError ends it with its message and exit code 2; an interrupt with 130.
"""
import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from ..errors import exit_code
from .job import OUT_HELP, TRAIN_PRESETS, add_train_arguments, run_trainer


def cmd_check(args):
    from .manifest import load_manifest
    manifest = load_manifest(args.manifest)
    for entry in manifest.select(args.material):
        material = entry.open()
        print(f"[ok] {entry.name}: {type(material).__name__}, domain {entry.domain}, "
              f"{'isotropic' if material.isotropic else 'anisotropic'}")


def cmd_yardsticks(args):
    from ..quality.report import markdown_table, write_csv, yardstick_rows
    from .manifest import load_manifest
    manifest = load_manifest(args.manifest)
    thetas = tuple(float(t) for t in args.thetas.split(","))
    rows = []
    for entry in manifest.select(args.material):
        rows += yardstick_rows(entry.name, entry.open(), thetas=thetas, n=args.samples)
    table = markdown_table(rows, thetas)
    print(table)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "yardsticks.md").write_text(table + "\n")
        write_csv(rows, out / "yardsticks.csv")
        print(f"[wrote] {out / 'yardsticks.md'}, {out / 'yardsticks.csv'}")


def cmd_bake(args):
    from .manifest import load_manifest
    from .pipeline import bake_manifest
    bake_manifest(load_manifest(args.manifest), args.out, name=args.material, force=args.force)


def cmd_report(args):
    from .reports import report_manifest
    from .manifest import load_manifest
    steps = tuple(int(x) for x in args.steps.split(",") if x.strip())
    written = report_manifest(load_manifest(args.manifest), args.out, name=args.material, n=args.samples,
                              steps=steps)
    print(Path(written["markdown"]).read_text())
    print(f"[wrote] {written['markdown']}")


def cmd_run(args):
    """The main job: train -> bake -> report -> render per material, then one page (bake/plumbing/job.py)."""
    from .job import Job
    from .manifest import load_manifest
    Job(load_manifest(args.manifest), args.out, preset=args.preset, train=not args.no_train,
        render=not args.no_render, samples=args.samples).run(args.material)


# `flowbsdf library` runs the add-on's library (blender_addon/artist/library.py) as its own program: bake/
# never imports the add-on (it is the bottom of the repository), as the add-on runs bake/ in its
# worker Python.
LIBRARY_CODE = """
import sys, bake.errors as errors, blender_addon.artist.library as library
folder, out, quality, blend = sys.argv[1:5]
sys.exit(errors.exit_code(lambda: library.main(folder, out, quality=quality, blend=blend == "1"), "flowbsdf"))
"""


def cmd_library(args):
    """An asset library of a folder of measured files (DIR/library.blend): the Blender add-on's
    blender_addon/artist/library.py, found beside bake/ in a checkout, run in a Python of its own (this
    one, with the checkout first on its path); its exit code is the command's."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "blender_addon" / "artist" / "library.py").is_file():
        from ..errors import FlowBSDFError
        raise FlowBSDFError("`flowbsdf library` needs the Blender add-on's folder (blender_addon) "
                            "beside bake/: run it from a FlowBSDF checkout")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH")) if p)}
    code = subprocess.call([sys.executable, "-c", LIBRARY_CODE, args.folder, args.out, args.quality,
                            "0" if args.no_blend else "1"], env=env)
    if code:
        raise SystemExit(code)      # the library printed why (as `flowbsdf: error: ...`)


def _bake_quietly(manifest_path, out_dir):
    """`flowbsdf stress`'s load run: bake a manifest (the table files written)."""
    from .manifest import load_manifest
    from .pipeline import bake_manifest
    return bake_manifest(load_manifest(manifest_path), out_dir, log=lambda s: None)


def _current_tables(manifest_path, out_dir):
    """`flowbsdf stress`'s load run: a manifest's current tables (None where one is not)."""
    from .manifest import load_manifest
    from .pipeline import open_current_tables
    m = load_manifest(manifest_path)
    return [open_current_tables(e, out_dir, m.path) for e in m.materials]


def build_parser():
    p = argparse.ArgumentParser(prog="flowbsdf", description="Learned BSDF importance sampling.")
    sub = p.add_subparsers(dest="command", required=True)

    def command(name, func, help_, out=True):
        c = sub.add_parser(name, help=help_)
        c.add_argument("manifest")
        c.add_argument("--material", help="only this material of the manifest")
        if out:
            c.add_argument("--out", default="out", help=OUT_HELP)
        c.set_defaults(func=func)
        return c

    command("check", cmd_check, "validate a manifest and open its materials", out=False)
    y = command("yardsticks", cmd_yardsticks, "rv of the baseline and ideal samplers")
    y.add_argument("--samples", type=int, default=1 << 17, help="samples per rv cell")
    y.add_argument("--thetas", default="0,30,60,75,85", help="incident elevations, degrees")
    b = command("bake", cmd_bake, "bake tables into OUT/tables (skips the current ones)")
    b.add_argument("--force", action="store_true", help="rebuild even when the inputs did not change")
    r = command("report", cmd_report, "speed vs error of every sampler (OUT/report)")
    r.add_argument("--samples", type=int, default=1 << 17, help="samples per rv cell")
    r.add_argument("--steps", default="2,4,8", help="Euler step counts of the flow to compare (its trained N is always added)")
    m = command("run", cmd_run, "the main job: train -> bake -> report -> render, one page (OUT/index.html)")
    m.add_argument("--preset", default="fast", choices=TRAIN_PRESETS)
    m.add_argument("--no-train", action="store_true", help="no training: bake from a model already there, else from the ideal tabulation")
    m.add_argument("--no-render", action="store_true", help="no shader-ball renders")
    m.add_argument("--samples", type=int, default=None,
                   help="samples per rv cell of the report (default: the manifest's [run.report], else 16384)")

    lib = sub.add_parser("library", help="bake a folder of measured files (RGL .bsdf, MERL .binary) into a "
                                         "Blender asset library: OUT/library.blend (blender_addon/artist/library.py)")
    lib.add_argument("folder", help="the measured files (subfolders too)")
    lib.add_argument("--out", required=True, help="the library's folder (manifest.toml, tables/, library.blend, "
                                                  "blender_assets.cats.txt)")
    lib.add_argument("--quality", default="final", choices=("draft", "preview", "final"),
                     help="the tables' bake settings (draft: seconds, for tests and layout)")
    lib.add_argument("--no-blend", action="store_true", help="bake only: no library.blend")
    lib.set_defaults(func=cmd_library)

    add_train_arguments(sub.add_parser("train", help="train flow models (torch, in a subprocess: python -m trainer)"))
    from ..quality.stress import add_parser as add_stress
    add_stress(sub, bake=_bake_quietly, current_tables=_current_tables)
    from .farm import add_parser as add_farm        # farm openjd, farm task
    add_farm(sub)
    from .tracer_commands import add_commands as add_tracer_commands   # render, compare
    add_tracer_commands(sub)
    return p


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    if args.command == "train":     # checked by the same parser here, run where torch is
        return run_trainer(argv[1:])
    t0 = time.perf_counter()
    code = exit_code(lambda: args.func(args), "flowbsdf")
    if code == 0:
        print(f"[done] {args.command} in {time.perf_counter() - t0:.1f}s")
    return code


if __name__ == "__main__":
    sys.exit(main())
