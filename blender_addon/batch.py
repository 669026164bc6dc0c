"""Batch baking for farms: scan the open .blend, bake (train only when asked), bind, save.

    blender -b scene.blend -c flowbsdf bake [options]                                   (4.2+)
    blender -b scene.blend --python-expr "import flowbsdf.batch as b; b.main()" -- bake [options]
        (3.4+, legacy add-on installed as `flowbsdf`; from a checkout, put its folder on
         sys.path and import blender_addon.batch instead)

Commands: `scan` (write the manifest, print what each material needs and whether its
tables are current), `bake` (the whole job), `validate` (reference tracer vs Cycles:
MSE, SSIM and a side-by-side image in <out>/validate/) and `farm openjd --job-dir DIR`
(scan, then write an Open Job Description job bundle that trains/bakes each material on a
farm and assembles this file: `flowbsdf farm openjd` in the worker Python, bake/plumbing/farm.py;
--blender, --addon-dir: Blender and the add-on's folder on the farm) and `library FOLDER --out DIR
[--quality draft|preview|final] [--python PY]` (an asset library of a folder of measured files:
the bake in the worker Python, then DIR/library.blend in this Blender; blender_addon/artist/library.py;
no .blend needs to be open, the open one is replaced). Options:
    --python PY        the Python that bakes (numpy + OpenEXR) and trains (torch + FlowBSDF's
                       trainer); else FLOWBSDF_PYTHON, the preference, the Python Blender reports
    --train MODE       never (default; a material whose tables are From: Trained model must have
                       one), always (train those without a model first), auto (when PY has torch)
    --out DIR          output folder (default: the scene's, //flowbsdf)
    --material NAME    only this Blender material (repeatable)
    --save-as PATH     save there instead of over the opened file;  --no-save: do not save
    --no-bind          bake only (tables, OSL textures, fits); nodes not bound, nothing saved
    --spp N, --size W  validate: Cycles' samples per pixel (the reference takes 4x), image width
Every line printed ends with a newline; progress lines start with `[progress K/N]`, the
add-on's own with `[flowbsdf]`. Exit code 0 on success, 1 on any failure (with an
`[flowbsdf] error:` line saying what failed).

The node binds in every supported Blender: where Blender's Python has no numpy and Cycles no
OSL (Debian's 3.4), the worker's bake writes the fit and OSL texture, and the node reads the
fit's JSON and holds the fit only (see render/node.py); a Blender that compiles OSL adds the OSL
back end when it opens the saved file. Each bound material's back end is logged.
"""
import argparse
import contextlib
import os
import subprocess
import sys

import bpy

from . import deps
from .artist import jobs, scan, worker


def log(message):
    print(f"[flowbsdf] {message}", flush=True)


def _parser():
    p = argparse.ArgumentParser(prog="blender -b FILE -c flowbsdf", add_help=True,
                                description="Scan, train, bake and bind FlowBSDF materials.")
    p.add_argument("command", choices=["scan", "bake", "validate", "farm"])
    p.add_argument("engine", nargs="?", choices=["openjd"], help="farm: the job format")
    p.add_argument("--python", default=None)
    p.add_argument("--train", choices=["auto", "always", "never"], default=None)
    p.add_argument("--out", default=None)
    p.add_argument("--material", action="append", default=None)
    p.add_argument("--save-as", default=None)
    p.add_argument("--no-save", action="store_true")
    p.add_argument("--spp", type=int, default=None, help="validate: Cycles' samples (reference: 4x)")
    p.add_argument("--size", type=int, default=None, help="validate: image width in pixels")
    p.add_argument("--no-bind", action="store_true",
                   help="bake only: nodes not bound, file not saved")
    p.add_argument("--job-dir", default=None, help="farm openjd: the job folder to write")
    p.add_argument("--blender", default=None, help="farm openjd: Blender on the farm (default: this one)")
    p.add_argument("--addon-dir", default="", help="farm openjd: folder holding the `flowbsdf` add-on on the "
                                                  "farm (default: the installed one)")
    return p


class BatchError(RuntimeError):
    pass


def _filter(rows, names):
    if not names:
        return rows
    missing = set(names) - {r["material"].name for r in rows}
    if missing:
        raise BatchError(f"not learned materials used by rendered objects: {', '.join(sorted(missing))}")
    return [r for r in rows if r["material"].name in names]


def _run_job(python, args, extra_paths):
    job = worker.Job(python, args, extra_paths)
    job.run(echo=True)
    return job.lines


def run(argv):
    if argv[:1] == ["library"]:
        return _library(argv[1:])
    try:
        args = _parser().parse_args(argv)
    except SystemExit as e:            # argparse: usage error or --help
        return 0 if e.code in (0, None) else 1
    with _python_env(args.python):
        return _run(args)


@contextlib.contextmanager
def _python_env(python):
    """The worker's Python set to `python` (--python) for the command, as it was afterwards."""
    saved = os.environ.get(deps.ENV_PYTHON)
    if python:
        os.environ[deps.ENV_PYTHON] = python
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop(deps.ENV_PYTHON, None)
        else:
            os.environ[deps.ENV_PYTHON] = saved


def _run(args):
    scene = bpy.context.scene
    if args.command == "validate":
        return _validate(scene, args)
    if args.command == "farm":
        return _farm(scene, args)
    try:
        if args.out:
            scene.flowbsdf.out_dir = os.path.abspath(args.out)
        train = args.train or "never"
        source = bpy.data.filepath or "(unsaved file)"
        log(f"{args.command} {source}")
        rows, manifest, out = jobs.prepare(scene)
        rows = _filter(rows, args.material)
        log(f"{len(rows)} learned material(s) in use; manifest {manifest}")
        if jobs.unsaved_problem(scene):
            log(f"unsaved file: the tables go to {out}")
        from .artist import prefs
        p = prefs.get()
        python = worker.python_for(p, need_train=(train == "always"), where="batch")
        log(f"worker Python: {deps.describe(python, *_explicit(p))}")
        names = sorted({r["name"] for r in rows}) if args.material else ()
        if args.command == "scan":
            lines = _run_job(python, jobs.status_args(manifest, out), worker.extra_paths(p))
        else:
            lines = _run_job(python, jobs.bake_args(manifest, out, train, names), worker.extra_paths(p))
        statuses = jobs.after_status(scene, rows, manifest, lines)
        for row in rows:
            info = statuses.get(row["name"], {})
            log(f"{row['material'].name} -> {row['name']}: {scan.state_of(info) if info else 'unknown'}; "
                f"needs {scan.needs_text(info) if info else '?'}")
        if args.command == "scan":
            return 0
        if args.no_bind:
            log("tables baked; nodes not bound (--no-bind), file not saved")
            log("done")
            return 0
        bound = jobs.bind(rows, statuses)
        log(f"bound {len(bound)} material(s): {', '.join(bound)}")
        for line in _node_report(scene, rows):
            log(line)
        if args.no_save:
            log("not saved (--no-save)")
        elif args.save_as:
            bpy.ops.wm.save_as_mainfile(filepath=os.path.abspath(args.save_as))
            log(f"saved {bpy.data.filepath}")
        elif bpy.data.filepath:
            bpy.ops.wm.save_mainfile()
            log(f"saved {bpy.data.filepath}")
        else:
            raise BatchError("nothing to save: open a .blend or pass --save-as PATH")
    except (BatchError, worker.JobError, scan.ScanError, jobs.BindError, OSError, RuntimeError) as e:
        return _error(e)
    log("done")
    return 0


def _validate(scene, args):
    from .artist import validate
    try:
        if args.out:
            scene.flowbsdf.out_dir = os.path.abspath(args.out)
        log(f"validate {bpy.data.filepath or '(unsaved file)'}")
        job, folder, notes = validate.prepare(scene, spp=args.spp, size=args.size, where="batch")
        for note in notes:
            log(f"note: {note}")
        job.run(echo=True)
        result = validate.parse_result(job.lines)
    except (worker.JobError, scan.ScanError, validate.ExportError, OSError, RuntimeError) as e:
        return _error(e)
    log(f"validate: MSE {result['mse']:.4g}, SSIM {result['ssim']:.4f}; side by side: {result['image']}")
    return 0


def _farm(scene, args):
    """`farm openjd --job-dir DIR`: scan the scene (its manifest), then the CLI's `farm openjd`
    (bake/plumbing/farm.py) in the worker Python writes the job bundle with an Assemble step for this file."""
    try:
        if args.engine != "openjd" or not args.job_dir:
            raise BatchError("usage: farm openjd --job-dir DIR [--out DIR] [--train MODE] [--save-as PATH]")
        if not bpy.data.filepath:
            raise BatchError("save the .blend first: the farm opens it from shared storage")
        if args.out:
            scene.flowbsdf.out_dir = os.path.abspath(args.out)
        rows, manifest, out = jobs.prepare(scene)
        log(f"{len(rows)} learned material(s) in use; manifest {manifest}")
        from .artist import prefs
        p = prefs.get()
        python = worker.python_for(p)
        cmd = [str(python), "-m", "bake.plumbing.cli", "farm", "openjd", manifest, "--scene", bpy.data.filepath,
               "--out", os.path.abspath(args.job_dir), "--shared", out, "--python", str(python),
               "--train", args.train or scene.flowbsdf.train.lower(),
               "--blender", args.blender or bpy.app.binary_path or "blender", "--addon-dir", args.addon_dir]
        if args.save_as:
            cmd += ["--save-as", os.path.abspath(args.save_as)]
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                              text=True, env=deps.worker_env(python, worker.extra_paths(p)))
        print(proc.stdout, end="", flush=True)
        if proc.returncode != 0:
            tail = [ln for ln in proc.stdout.splitlines() if ln.strip()][-1:] or ["no output"]
            raise BatchError(f"the job was not written (exit code {proc.returncode}): {tail[0]}")
    except (BatchError, worker.JobError, scan.ScanError, OSError, RuntimeError) as e:
        return _error(e)
    log("done")
    return 0


def _library(argv):
    """`library FOLDER --out DIR`: the folder's manifest (blender_addon/artist/library.py), its bake in the
    worker Python (tables, textures, fit, preview; current ones skipped), then DIR/library.blend."""
    from .artist import library, prefs
    p = argparse.ArgumentParser(prog="blender -b -c flowbsdf library",
                                description="An asset library (DIR/library.blend) of a folder of measured files.")
    p.add_argument("folder")
    p.add_argument("--out", required=True, help="the library's folder")
    p.add_argument("--quality", choices=list(library.QUALITY), default="final", help="the tables' bake settings")
    p.add_argument("--python", default=None, help="the Python that bakes (numpy + OpenEXR)")
    p.add_argument("--blend-only", action="store_true",
                   help="no bake: library.blend from the tables baked already (the panel's second step)")
    try:
        args = p.parse_args(argv)
    except SystemExit as e:
        return 0 if e.code in (0, None) else 1
    try:
        with _python_env(args.python):
            return _build_library(args)
    except (BatchError, library.LibraryError, worker.JobError, OSError, RuntimeError) as e:
        return _error(e)


def _build_library(args):
    """The library command's work: the manifest, the bake in the worker, then library.blend."""
    from .artist import library, prefs
    items, manifest = library.prepare(args.folder, args.out, args.quality)
    out = os.path.abspath(args.out)
    log(f"library: {len(items)} measured file(s) in {os.path.abspath(args.folder)}; manifest {manifest}")
    failed = []
    if not args.blend_only:
        prefs_ = prefs.get()
        python = worker.python_for(prefs_, where="batch")
        log(f"worker Python: {deps.describe(python, *_explicit(prefs_))}")
        job = worker.Job(python, jobs.bake_args(str(manifest), out), worker.extra_paths(prefs_))
        try:
            job.run(echo=True)
        except worker.JobError:
            failed = sorted({ln.split(":", 1)[0][len("[fail] "):] for ln in job.lines if ln.startswith("[fail] ")})
            if not failed:
                raise
    if args.blend_only:             # the panel's second step: its words while Blender writes it
        print(f"[progress 1/1] writing {library.BLEND_NAME} ({len(items)} material(s))", flush=True)
    library.build([i for i in items if i["name"] not in failed], out, log=log)
    if failed:
        raise BatchError(f"not baked, left out of the library: {', '.join(failed)}")
    log("done")
    return 0


def _explicit(p):
    """(explicit, probe) of the Python the batch chose, for deps.describe."""
    python, explicit = deps.candidate(p.python_path if p else "")
    return explicit, deps.probe(python, worker.extra_paths(p))


def _error(e):
    """Print the failure (and its details) on stdout and stderr; exit code 1."""
    details = getattr(e, "details", "")
    for stream in (sys.stdout, sys.stderr):
        print(f"[flowbsdf] error: {e}", file=stream, flush=True)
        if details:
            print(f"[flowbsdf] {details}", file=stream, flush=True)
    return 1


def _node_report(scene, rows):
    """One line per bound material: what its Learned BSDF node renders in this scene and Blender."""
    from .render import binding, node
    lines = []
    for mat in dict.fromkeys(r["material"] for r in rows):
        group = next((n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeGroup"
                      and n.node_tree is not None and binding.TREE_KEY in n.node_tree.keys()), None)
        if group is not None:
            info = binding.read(group.node_tree)
            err = info.get("fit_error", -1.0)
            fit = f"fit error {err:.3f}" if err >= 0 else "no fit"
            problems = f"; problems: {info['problems']}" if info.get("problems") else ""
            lines.append(f"{mat.name}: node {group.node_tree.name!r} renders {node.node_status(group, scene)}; "
                         f"{fit}; OSL back end {'in the node' if info.get('has_osl') else 'not in the node'}"
                         f"{problems}")
    return lines


def cli_command(argv):
    """`blender -c flowbsdf ...` (registered by the add-on on Blender 4.2+)."""
    return run(list(argv))


def _ensure_registered():
    if not hasattr(bpy.types.Scene, "flowbsdf"):
        import importlib
        importlib.import_module(__package__).register()


def main(argv=None):
    """Entry point for `--python-expr`: the arguments after `--`; exits Blender with the code."""
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    try:
        _ensure_registered()
        code = run(argv)
    except Exception as e:      # noqa: BLE001 - Blender would exit 0 after a traceback
        import traceback
        traceback.print_exc()
        print(f"[flowbsdf] error: {type(e).__name__}: {e}", flush=True)
        code = 1
    sys.stdout.flush()
    if bpy.app.background:
        sys.exit(code)
    return code
