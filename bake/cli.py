"""The `flowbsdf` command."""
import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from .errors import FlowBSDFError


def cmd_check(args):
    from .manifest import load_manifest
    manifest = load_manifest(args.manifest)
    for entry in manifest.select(args.material):
        material = entry.open()
        print(f"[ok] {entry.name}: {type(material).__name__}, domain {entry.domain}, "
              f"{'isotropic' if material.isotropic else 'anisotropic'}")


def cmd_yardsticks(args):
    from .manifest import load_manifest
    from .report import markdown_table, write_csv, yardstick_rows
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


def cmd_run(args):
    """The main job on a manifest. For now: the yardstick table of the existing samplers."""
    args.thetas = "0,30,60,75,85"
    cmd_yardsticks(args)


def cmd_train(args, rest):
    """Training needs torch: run the trainer as a subprocess (as the Blender add-on does)."""
    python = os.environ.get("FLOWBSDF_TRAIN_PYTHON", sys.executable)
    return subprocess.call([python, "-m", "trainer", "train", *rest])


def build_parser():
    p = argparse.ArgumentParser(prog="flowbsdf", description="Learned BSDF importance sampling.")
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("check", help="validate a manifest and open its materials")
    c.add_argument("manifest")
    c.add_argument("--material")
    c.set_defaults(func=cmd_check)

    for name, func, help_ in [("yardsticks", cmd_yardsticks, "rv of the baseline and ideal samplers"),
                              ("run", cmd_run, "the main job on a manifest")]:
        y = sub.add_parser(name, help=help_)
        y.add_argument("manifest")
        y.add_argument("--material")
        y.add_argument("--samples", type=int, default=1 << 17, help="samples per rv cell")
        y.add_argument("--out", default="out", help="folder for the tables")
        if name == "yardsticks":
            y.add_argument("--thetas", default="0,30,60,75,85", help="incident elevations, degrees")
        y.set_defaults(func=func)

    sub.add_parser("train", help="train flow models (python -m trainer train --help)", add_help=False)
    return p


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["train"]:
        return cmd_train(None, argv[1:])
    args = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        args.func(args)
    except FlowBSDFError as e:
        print(f"flowbsdf: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("flowbsdf: interrupted", file=sys.stderr)
        return 130
    print(f"[done] {args.command} in {time.perf_counter() - t0:.1f}s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
