"""The steps the panel and the batch command share: scan -> manifest -> worker -> bind nodes."""
import os
import subprocess
from pathlib import Path

import bpy

from .. import deps
from . import prefs, scan, worker

MANIFEST_NAME = "manifest.toml"


class BindError(RuntimeError):
    """Tables are baked but a node could not be bound; the message names the material."""


def prepare(scene, only=None):
    """Scan the scene and write its manifest. Returns (rows, manifest path, output folder);
    `only`: a Blender material name to restrict the job to (its manifest row)."""
    rows = scan.scan(scene)
    if only is not None:
        rows = [r for r in rows if r["material"].name == only]
        if not rows:
            raise scan.ScanError(f"material {only!r} is not a learned material used by a rendered object "
                                 "(enable Learned BSDF on it and assign it to an object that renders)")
    if not rows:
        raise scan.ScanError("no learned materials in use: enable Learned BSDF on a material that a "
                             "rendered object uses")
    out = scan.out_dir(scene)
    # The manifest always lists everything the scene needs; `only` restricts the job, not the file.
    path = scan.write_manifest(scan.scan(scene), os.path.join(out, MANIFEST_NAME),
                               source=bpy.path.basename(bpy.data.filepath) or "an unsaved file")
    return rows, path, out


def unsaved_problem(scene):
    """Why a job started from the UI would write where the artist does not expect, or None:
    the file is not saved and the output folder is relative to it (//...)."""
    raw = scene.flowbsdf.out_dir.strip() or "//flowbsdf"
    if bpy.data.filepath or not raw.startswith("//"):
        return None
    return f"save the .blend first: FlowBSDF writes the tables beside it, in {raw}"


def status_args(manifest, out):
    return ["status", manifest, "--out", out]


def bake_args(manifest, out, train="never", names=()):
    args = ["bake", manifest, "--out", out, "--train", train.lower()]
    for name in names:
        args += ["--material", name]
    return args


def start_status(scene, context=None):
    rows, manifest, out = prepare(scene)
    python = worker.python_for(prefs.get(context))
    return rows, manifest, out, worker.Job(python, status_args(manifest, out),
                                           worker.extra_paths(prefs.get(context)), label="Scan")


def start_bake(scene, context=None, only=None, train="never"):
    """Start the bake job: `train` "never" (tables from the material, or from its trained model
    where its From (under Tables) says so and the model exists), "always" (train the materials whose tables
    come from a model and have none first; fails without torch) or "auto"."""
    rows, manifest, out = prepare(scene, only)
    p = prefs.get(context)
    python = worker.python_for(p, need_train=(train == "always"))
    names = sorted({r["name"] for r in rows}) if only else ()
    return rows, manifest, out, worker.Job(python, bake_args(manifest, out, train, names),
                                           worker.extra_paths(p), label="Train + Bake" if train == "always" else "Bake")


def start_library(folder, out, quality="final", context=None):
    """The asset library's first step (blender_addon/artist/library.py): DIR/manifest.toml of the folder's
    measured files, and their bake in the worker (tables, textures, fit, preview; current ones
    skipped). Returns (items, manifest path, the Job); library.LibraryError when the folder has
    no measured files."""
    from . import library
    items, manifest = library.prepare(folder, out, quality)
    p = prefs.get(context)
    return items, manifest, worker.Job(worker.python_for(p), bake_args(str(manifest), str(Path(out).resolve())),
                                       worker.extra_paths(p), label="Asset Library: Bake")


def blender_program():
    return bpy.app.binary_path          # ('' in the bpy module)


def library_blend_job(folder, out, quality="final", context=None):
    """Its second step: DIR/library.blend written by a background Blender (this one's program;
    writing it here would replace the open file) from the tables baked already."""
    from . import library
    if not blender_program():
        raise worker.JobError("this Blender cannot start itself in the background (its program is unknown): "
                              f"write library.blend with `flowbsdf library {folder} --out {out}`")
    p = prefs.get(context)
    args = library.blender_args(folder, out, quality, python=worker.python_for(p), blender=blender_program(),
                                blend_only=True)
    return worker.Job(args[0], args[1:], worker.extra_paths(p), label="Asset Library: library.blend", script=None)


def after_status(scene, rows, manifest, lines):
    """Record a finished status/bake job: scan rows in the panel, notes in the manifest."""
    statuses = scan.parse_status(lines)
    scan.fill_scan_items(scene, rows, statuses)
    all_rows = scan.scan(scene)
    scan.write_manifest(all_rows, manifest, notes=scan.notes_of(all_rows, statuses),
                        source=bpy.path.basename(bpy.data.filepath) or "an unsaved file")
    scene.flowbsdf.last_manifest = manifest
    return statuses


def _blend_path(path):
    """Relative to the .blend (//...) when it is saved, so the file can move with its folder."""
    if bpy.data.filepath:
        try:
            return bpy.path.relpath(path)
        except ValueError:          # another drive (Windows)
            pass
    return path


# Writes what the node reads beside each table file (its OSL texture and closure fit), in the
# worker Python, for a Blender whose own Python cannot (no numpy: Debian's 3.4).
DERIVE_CODE = """
import sys
from bake.export.derived import bake_derived
for k, path in enumerate(sys.argv[1:], 1):
    print(f"[progress {k}/{len(sys.argv) - 1}] fit + OSL texture {path}", flush=True)
    bake_derived(path, log=lambda line: print(line, flush=True))
"""


def ensure_derived(tables_paths, python=None, extra_paths=None):
    """Make the OSL texture and closure fit of each table file current, in the worker Python,
    when this Blender cannot (no numpy); elsewhere the node makes them itself when binding.
    Returns the paths it derived; worker.JobError when the worker fails."""
    from ..render import derived
    if deps.bake_module("export.osl_export") is not None:
        return []
    todo = [str(p) for p in tables_paths if os.path.isfile(p) and not derived.is_current(p)]
    if not todo:
        return []
    p = prefs.get()
    python = python or worker.python_for(p)
    extra = worker.extra_paths(p) if extra_paths is None else extra_paths
    try:
        proc = subprocess.Popen([str(python), "-c", DERIVE_CODE, *todo], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True, bufsize=1,
                                env=deps.worker_env(python, extra))
    except OSError as e:
        raise worker.JobError(f"cannot start {python}: {e}") from None
    lines = []
    for line in proc.stdout:
        lines.append(line.rstrip("\n"))
        print(lines[-1], flush=True)
    if proc.wait() != 0:
        tail = [ln for ln in lines if ln.strip()][-1:] or ["no output"]
        raise worker.JobError(f"the worker failed making the fit/OSL texture (exit code {proc.returncode}): "
                              f"{tail[0]}")
    return todo


def bind(rows, statuses):
    """Bind every row with current tables to a Learned BSDF node. Returns the bound material
    names; raises BindError listing the ones that could not be bound."""
    try:
        from ..render import node
    except ImportError as e:
        raise BindError(f"the Learned BSDF node cannot be built in this Blender ({e}); the tables "
                        "are baked: bind them in another Blender (or run with --no-bind)") from None
    bound, problems = [], []
    try:
        ensure_derived([info["tables_path"] for info in statuses.values()
                        if info.get("tables_path") and scan.state_of(info) == "current"])
    except worker.JobError as e:
        raise BindError(f"not bound: {e}") from None
    for row in rows:
        info = statuses.get(row["name"])
        if info is None or scan.state_of(info) != "current":
            state = "not scanned" if info is None else scan.state_of(info)
            problems.append(f"{row['material'].name}: tables {state}"
                            + (f" ({info['error']})" if info and info.get("error") else ""))
            continue
        fit = info.get("fit_path")
        try:
            node.assign_learned_bsdf(row["material"], row["name"], _blend_path(info["tables_path"]),
                                     fit_path=_blend_path(fit) if fit else None)
        except Exception as e:      # noqa: BLE001 - the node's own error, reported per material
            problems.append(f"{row['material'].name}: {e}")
            continue
        bound.append(row["material"].name)
    if problems:
        raise BindError("not bound: " + "; ".join(problems))
    return bound
