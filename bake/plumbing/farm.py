"""Farm jobs on existing engines: an Open Job Description template, and the task it runs.

    flowbsdf farm openjd MANIFEST|SHOT.blend --out JOB_DIR [--shared DIR] [--train auto|always|never]
                         [--python PY] [--blender BLENDER] [--addon-dir DIR] [--save-as PATH]
    flowbsdf farm task MANIFEST --material NAME --out SHARED [--train MODE] [--stage all|train|bake] [--openjd]

`farm openjd` writes a job bundle (OpenJD `jobtemplate-2023-09`, as AWS Deadline Cloud runs it):
    JOB_DIR/template.json          steps "Bake" (one task per material; more than 1024 materials
                                   are split over steps "Bake 1 of K", ... since a STRING task
                                   parameter holds at most 1024 values) and, for a .blend,
                                   "Assemble" (after every Bake step: binds the nodes, saves)
    JOB_DIR/parameter_values.json  the values at submission, Deadline's job-bundle form
    JOB_DIR/params.json            the same as a plain map: `openjd run ... --job-param file://...`
The shared folders are PATH parameters, so the farm's path mapping rules (Deadline storage
profiles, `openjd run --path-mapping-rules`) translate them on each worker; their defaults are
relative to the bundle (OpenJD forbids absolute defaults and walking up), given where the
target lies inside JOB_DIR, else the parameter is required.

For a .blend, the scene is scanned by the add-on's batch command in Blender (`farm openjd`,
which writes the manifest and calls back into this module with `--scene`): one writer here.

`farm task` is one material's task: train if needed (per the manifest's train settings and
--train; the trainer runs in FLOWBSDF_TRAIN_PYTHON or this Python), then bake the tables and
what the Blender node reads beside them, every file written atomically into the shared
folder. With --openjd, progress and failure are OpenJD protocol lines on stdout
(`openjd_progress: N`, `openjd_status: ...`, `openjd_fail: ...`); a failure exits non-zero
(2 for FlowBSDF's errors), failing that task only.
"""
import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

from ..errors import FlowBSDFError
from ..io.files import atomic_path
from .job import OUT_HELP

SPEC_VERSION = "jobtemplate-2023-09"
MAX_TASK_VALUES = 1024           # OpenJD: a STRING task parameter's range holds at most 1024 values
TRAIN_MODES = ("auto", "always", "never")
STAGES = ("all", "train", "bake")
TEMPLATE, VALUES, PARAMS = "template.json", "parameter_values.json", "params.json"


# -- the job bundle ---------------------------------------------------------------------------

def blender_expr(addon_dir="{{Param.AddonDir}}"):
    """The `--python-expr` that runs the add-on's batch command (Blender 3.4+): `flowbsdf` from
    addon_dir when given, else the installed add-on."""
    return (f"import sys; d = r'''{addon_dir}'''; d and sys.path.insert(0, d); "
            "import flowbsdf.batch as b; b.main()")


def _param(name, kind, description, default=None, **extra):
    p = {"name": name, "type": kind, "description": description, **extra}
    if default is not None:
        p["default"] = default
    return p


def _path_param(name, object_type, data_flow, description, value, job_dir):
    """A PATH parameter. OpenJD takes only relative defaults that stay inside the bundle: the value
    relative to job_dir where it lies inside, "" for an empty value, else none (then required)."""
    default = ""
    if value:
        try:
            default = os.path.relpath(value, job_dir)
        except ValueError:          # another drive (Windows)
            default = None
        if default is not None and (default == os.pardir or default.startswith(os.pardir + os.sep)):
            default = None
    return _param(name, "PATH", description, default, objectType=object_type, dataFlow=data_flow)


def _chunks(names):
    return [names[i:i + MAX_TASK_VALUES] for i in range(0, len(names), MAX_TASK_VALUES)]


def job_template(names, job_dir, manifest, shared, python, train, scene=None, save_as=None,
                 blender="blender", addon_dir=""):
    """(template, parameter values) of the job: Bake step(s), and Assemble when a scene is given."""
    if not names:
        raise FlowBSDFError("no materials to bake (all optional sources missing?)", manifest)
    if train not in TRAIN_MODES:
        raise FlowBSDFError(f"--train must be one of {TRAIN_MODES}, not {train!r}")
    values = {"Manifest": manifest, "SharedOut": shared, "Python": python, "Train": train}
    params = [
        _path_param("Manifest", "FILE", "IN", "The FlowBSDF manifest: the materials to model",
                    manifest, job_dir),
        _path_param("SharedOut", "DIRECTORY", "INOUT", "Shared output folder: models/ and tables/",
                    shared, job_dir),
        _param("Python", "STRING", "A Python with FlowBSDF on the workers (with torch to train)", "python3"),
        _param("Train", "STRING", "auto: train where the manifest wants a model and the Python has "
               "torch; always; never (bake from the ideal tabulation)", train, allowedValues=list(TRAIN_MODES)),
    ]
    task_args = ["-m", "bake.plumbing.cli", "farm", "task", "{{Param.Manifest}}",
                 "--material", "{{Task.Param.Material}}",
                 "--out", "{{Param.SharedOut}}", "--train", "{{Param.Train}}", "--openjd"]
    chunks = _chunks(list(names))
    steps = []
    for k, chunk in enumerate(chunks, 1):
        steps.append({
            "name": "Bake" if len(chunks) == 1 else f"Bake {k} of {len(chunks)}",
            "description": "One task per material: train if needed, then bake its tables",
            "parameterSpace": {"taskParameterDefinitions": [
                {"name": "Material", "type": "STRING", "range": chunk}]},
            "script": {"actions": {"onRun": {"command": "{{Param.Python}}", "args": task_args}}},
        })
    if scene is not None:
        values.update(Scene=scene, SaveAs=save_as or default_save_as(scene), Blender=blender, AddonDir=addon_dir)
        params += [
            _path_param("Scene", "FILE", "IN", "The shot .blend", scene, job_dir),
            _path_param("SaveAs", "FILE", "OUT", "Where Assemble saves the bound .blend", values["SaveAs"], job_dir),
            _param("Blender", "STRING", "The Blender executable on the workers (3.4+)", "blender"),
            _path_param("AddonDir", "DIRECTORY", "IN", "Folder holding the `flowbsdf` add-on "
                        "(empty: the one installed in that Blender)", addon_dir, job_dir),
        ]
        steps.append({
            "name": "Assemble",
            "description": "Bind every learned material's node to its tables and save the .blend",
            "dependencies": [{"dependsOn": s["name"]} for s in steps],
            "script": {"actions": {"onRun": {"command": "{{Param.Blender}}", "args": [
                "-b", "{{Param.Scene}}", "--python-expr", blender_expr(), "--", "bake", "--train", "never",
                "--out", "{{Param.SharedOut}}", "--python", "{{Param.Python}}", "--save-as", "{{Param.SaveAs}}"]}}},
        })
    title = Path(scene or manifest).name
    template = {"specificationVersion": SPEC_VERSION,
                "name": f"FlowBSDF {title} ({len(names)} material{'s' if len(names) != 1 else ''})",
                "description": "Written by `flowbsdf farm openjd`: per material train + bake into the shared "
                               "folder" + (", then Assemble binds and saves the .blend" if scene else ""),
                "parameterDefinitions": params, "steps": steps}
    return template, values


def default_save_as(scene):
    """Beside the shot (its // paths stay valid), never over the artist's file."""
    scene = Path(scene)
    return str(scene.with_name(scene.stem + ".flowbsdf.blend"))


def _write_json(path, data):
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")


def write_openjd(manifest_path, job_dir, shared=None, python=None, train="auto", scene=None, save_as=None,
                 blender="blender", addon_dir="", log=print):
    """Write the job bundle for a manifest (and its .blend, if given); returns the template path."""
    from .manifest import load_manifest
    manifest = load_manifest(manifest_path)
    names = [e.name for e in manifest.select(log=log)]
    job_dir = Path(job_dir).absolute()
    shared = shared or Path(manifest_path).absolute().parent / "out"
    absolute = lambda p: str(Path(p).absolute()) if p else None  # noqa: E731
    template, values = job_template(
        names, str(job_dir), absolute(manifest_path), absolute(shared), python or sys.executable, train,
        scene=absolute(scene), save_as=absolute(save_as), blender=blender, addon_dir=absolute(addon_dir) or "")
    job_dir.mkdir(parents=True, exist_ok=True)
    _write_json(job_dir / TEMPLATE, template)
    _write_json(job_dir / VALUES, {"parameterValues": [{"name": k, "value": v} for k, v in values.items()]})
    _write_json(job_dir / PARAMS, values)
    steps = ", ".join(f"{s['name']} ({len(s['parameterSpace']['taskParameterDefinitions'][0]['range'])} tasks)"
                      if "parameterSpace" in s else s["name"] for s in template["steps"])
    log(f"[farm] {len(names)} material(s); steps: {steps}")
    log(f"[wrote] {job_dir / TEMPLATE}, {job_dir / VALUES}, {job_dir / PARAMS}")
    log(f"[farm] run here: openjd run {job_dir / TEMPLATE} --job-param file://{job_dir / PARAMS} "
        f"--step {template['steps'][-1]['name']!r} --run-dependencies")
    return job_dir / TEMPLATE


def openjd_from_blend(blend, job_dir, shared=None, python=None, train="auto", save_as=None, blender=None,
                      addon_dir=""):
    """Scan the .blend in Blender (the add-on's batch `farm openjd`), which writes the manifest and
    calls write_openjd back with --scene. Raises FlowBSDFError when Blender fails."""
    blender = blender or os.environ.get("FLOWBSDF_BLENDER") or "blender"
    python = python or sys.executable
    addon_dir = str(Path(addon_dir).absolute()) if addon_dir else ""
    cmd = [blender, "-b", str(blend), "--python-expr", blender_expr(addon_dir), "--", "farm", "openjd",
           "--job-dir", str(Path(job_dir).absolute()), "--python", python, "--train", train,
           "--blender", blender, "--addon-dir", addon_dir]
    for flag, value in (("--out", shared), ("--save-as", save_as)):
        if value:
            cmd += [flag, str(Path(value).absolute())]
    try:
        code = subprocess.call(cmd)
    except OSError as e:
        raise FlowBSDFError(f"cannot run Blender ({blender}): {e}; pass --blender or set FLOWBSDF_BLENDER") from None
    if code != 0:
        raise FlowBSDFError(f"Blender's scan of the scene failed (exit code {code}; see its lines above)", blend)


# -- one material's task ------------------------------------------------------------------------

class Report:
    """Task progress: OpenJD protocol lines (openjd=True) or plain `[progress N%]` lines."""

    def __init__(self, openjd=False):
        self.openjd = openjd

    def progress(self, percent, status=None):
        percent = round(min(max(percent, 0.0), 100.0), 1)
        if self.openjd:
            print(f"openjd_progress: {percent:g}", flush=True)
            if status:
                print(f"openjd_status: {status}", flush=True)
        else:
            print(f"[progress {percent:g}%] {status or ''}".rstrip(), flush=True)

    def fail(self, message):
        print(f"openjd_fail: {message}" if self.openjd else f"[fail] {message}", flush=True)

    def log(self, line):
        print(line, flush=True)


def trainer_python():
    return os.environ.get("FLOWBSDF_TRAIN_PYTHON") or sys.executable


def can_train(python):
    """Whether `python` has torch and FlowBSDF's trainer."""
    if python == sys.executable:
        return all(importlib.util.find_spec(m) is not None for m in ("torch", "trainer"))
    return subprocess.call([python, "-c", "import torch, trainer"], stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL) == 0


# A trainer log line that ends one of its three stages (trainer/train.py).
STAGE_DONE = re.compile(r"^\[(base|flow|reflow)\] (held-out NLL|best held-out NLL|done already)")


def _train(entry, manifest_path, out_dir, python, report, span):
    """Run the trainer for one material, relaying its lines; progress over `span` (lo, hi)."""
    lo, hi = span
    cmd = [python, "-m", "trainer", "train", str(manifest_path), "--material", entry.name,
           "--out", str(out_dir), "--no-progress"]
    report.progress(lo, f"{entry.name}: training (preset {entry.train.get('preset', 'balanced')})")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    done, last = set(), "no output"
    for line in proc.stdout:
        line = line.rstrip()
        last = line or last
        report.log(f"[train] {line}")
        m = STAGE_DONE.match(line)
        if m and m.group(1) not in done:
            done.add(m.group(1))
            report.progress(lo + (hi - lo) * len(done) / 3, f"{entry.name}: training stage {m.group(1)} done")
    code = proc.wait()
    if code != 0:
        raise FlowBSDFError(f"material {entry.name!r}: training failed (exit code {code}): {last}; "
                            "rerun the task to resume from its checkpoints")


def _task(manifest_path, name, out_dir, train, stage, report):
    from ..export.derived import bake_derived
    from .manifest import load_manifest
    from .pipeline import bake_entry, bake_settings, wants_model
    report.progress(0, f"{name}: opening the material")
    manifest = load_manifest(manifest_path)
    entries = manifest.select(name, log=report.log)
    if not entries:
        report.progress(100, f"{name}: skipped (optional source not found)")
        return
    entry = entries[0]
    material = entry.open()
    settings = bake_settings(entry, manifest.path)
    start = 5
    if stage in ("all", "train") and wants_model(entry, material, settings, out_dir):
        python = trainer_python()
        if train != "never" and can_train(python):
            _train(entry, manifest.path, out_dir, python, report, (start, 60 if stage == "all" else 100))
            start = 60
        elif train == "always":
            raise FlowBSDFError(f"material {entry.name!r} needs training (--train always), but {python} has no "
                                "torch/FlowBSDF trainer: set FLOWBSDF_TRAIN_PYTHON or the job's Python")
        else:
            raise FlowBSDFError(f"material {entry.name!r}: bake source 'flow' needs a trained model and "
                                + ("--train never" if train == "never" else f"{python} has no torch/FlowBSDF trainer")
                                + " (train it first, or bake with source = 'auto')")
    if stage in ("all", "bake"):
        report.progress(start, f"{name}: baking tables")
        path, status = bake_entry(entry, out_dir, manifest.path, log=report.log)
        report.progress(start + (100 - start) * 0.8, f"{name}: tables {status}; fit, OSL and SVM textures")
        bake_derived(path, material=material, log=report.log)
        report.log(f"[{'wrote' if status == 'baked' else 'skip'}] {path}"
                   + (" is up to date" if status == "current" else ""))
    report.progress(100, f"{name}: done")


def run_task(manifest_path, name, out_dir, train="auto", stage="all", openjd=False):
    """One material's farm task; FlowBSDFError (after the fail line) on any failure."""
    report = Report(openjd)
    try:
        _task(manifest_path, name, out_dir, train, stage, report)
    except Exception as e:      # noqa: BLE001 - ours, a bug or a system error: the task's own fail line
        message = str(e) if isinstance(e, FlowBSDFError) else f"{type(e).__name__}: {e}"
        message = message if repr(name) in message else f"material {name!r}: {message}"
        report.fail(message)
        raise FlowBSDFError(message) from e


# -- the `flowbsdf farm` command ------------------------------------------------------------------

def cmd_openjd(args):
    common = dict(shared=args.shared, python=args.python, train=args.train, save_as=args.save_as,
                  addon_dir=args.addon_dir)
    if Path(args.input).suffix.lower() == ".blend":
        if not Path(args.input).is_file():
            raise FlowBSDFError("scene not found", args.input)
        openjd_from_blend(args.input, args.out, blender=args.blender, **common)
    else:
        write_openjd(args.input, args.out, scene=args.scene, blender=args.blender or "blender", **common)


def cmd_task(args):
    run_task(args.manifest, args.material, args.out, train=args.train, stage=args.stage, openjd=args.openjd)


def add_parser(sub):
    farm = sub.add_parser("farm", help="farm jobs: an Open Job Description bundle; one material's task")
    fsub = farm.add_subparsers(dest="farm_command", required=True)
    o = fsub.add_parser("openjd", help="write an Open Job Description job bundle (Deadline Cloud, openjd run)")
    o.add_argument("input", help="manifest.toml, or a .blend (scanned by the add-on in Blender)")
    o.add_argument("--out", required=True, help="the job folder (template.json, parameter values)")
    o.add_argument("--shared", help="shared output folder for models/ and tables/ (default: the manifest's "
                                    "folder/out; for a .blend, the scene's FlowBSDF folder)")
    o.add_argument("--train", choices=TRAIN_MODES, default="auto")
    o.add_argument("--python", default=None, help="the workers' Python with FlowBSDF (default: this one)")
    o.add_argument("--blender", default=None, help="Blender for the scan and the Assemble step "
                                                   "(default: FLOWBSDF_BLENDER, else `blender`)")
    o.add_argument("--addon-dir", default="", help="folder holding the `flowbsdf` add-on, here and on the "
                                                   "farm (default: the one installed in Blender)")
    o.add_argument("--save-as", default=None, help="where Assemble saves the .blend (default: "
                                                   "<shot>.flowbsdf.blend beside it)")
    o.add_argument("--scene", default=None, help="(manifest input) the .blend whose scan wrote the "
                                                 "manifest: adds the Assemble step (the add-on's batch passes it)")
    o.set_defaults(func=cmd_openjd)
    t = fsub.add_parser("task", help="one material: train if needed, then bake (what a farm task runs)")
    t.add_argument("manifest")
    t.add_argument("--material", required=True)
    t.add_argument("--out", default="out", help=OUT_HELP)
    t.add_argument("--train", choices=TRAIN_MODES, default="auto")
    t.add_argument("--stage", choices=STAGES, default="all", help="train, bake, or both (default)")
    t.add_argument("--openjd", action="store_true", help="progress and failure as OpenJD protocol lines")
    t.set_defaults(func=cmd_task)
    return farm
