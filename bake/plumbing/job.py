"""The main job, `flowbsdf run MANIFEST`: per material train -> bake -> report -> render, then
one page, OUT/index.html, that shows what came out (bake/quality/page.py).

Each stage of each material is skipped when its product is current:
  train   OUT/models/<name>.flow.npz, by the trainer (a subprocess: torch) when missing or
          trained on another version of the material; it resumes from its checkpoints
          (isotropic materials only); the report and render compare it with the tables, which
          are built from it only with bake source "flow" (pipeline.tables_use_model)
  bake    OUT/tables/<name>.exr and the Blender node's files (pipeline.bake_with_derived: kept
          while the hash of their inputs matches)
  report  OUT/report/<name>/: speed vs error of every sampler (report.entry_report, write_report)
  render  OUT/render/<name>/: the shader ball in the reference tracer with the tables, the GGX
          fit and cosine sampling at equal spp and at equal time against a converged reference
          (tracer.compare); the reference (reference.npz) is reused while the material and the
          reference's settings stay the same
report and render write the hash of their inputs to <folder>/job.json last: a folder without
a matching one (changed inputs, or a stage interrupted) is redone.
A stage that fails ends its material, not the job: the message goes to the log and the page,
the other materials go on, and the job exits non-zero at the end (a rerun redoes what failed).

The manifest's optional [run] table sets the job: `max_materials` (the first N selected
materials whose source is present), `report` (REPORT_DEFAULTS) and `render` (RENDER_DEFAULTS).
"""
import hashlib
import json
import os
import subprocess
import sys
import time
import traceback
from pathlib import Path

from ..errors import FlowBSDFError
from ..io.files import atomic_path, file_hash, read_stamp, write_stamp
from ..io.paths import model_path
from ..io.progress import Progress, fmt_seconds

# Bump when a change of the code should redo the reports or renders of earlier runs.
REPORT_VERSION = 1
RENDER_VERSION = 1
# The manifest's [run.report] and [run.render] tables override these.
REPORT_DEFAULTS = {
    "samples": 1 << 14,             # samples per rv cell
    "thetas": [0, 30, 60, 75, 85],  # incident elevations, degrees
    "speed_samples": 1 << 13,       # per timing of sample() / pdf() (the flow's numpy pdf takes ~50 us each)
    "speed_repeat": 2,              # timings per number (the best is kept)
}
RENDER_DEFAULTS = {
    "scene": "shaderball-env",      # a built-in scene of the reference tracer (bake/tracer/scene.py)
    "size": 96,                     # image width and height, pixels
    "samplers": ["tables", "ggx", "cosine"],   # the first one sets the equal-time budget
    "spp": 64,                      # samples per pixel of the equal-spp renders
    "reference_spp": 512,           # the reference: MIS (light and BSDF sampling) whatever `mis` says
    "reference_sampler": "ggx",     # independent of the learned tables
    "mis": False,                   # BSDF sampling only, as the Blender node's portal path (no light
                                    # sampling there): shows the samplers' own quality
    "seed": 1,
    "workers": 2,                   # processes per render (the image does not depend on it; with more
                                    # than one, progress comes once per render instead of per pass)
}
# Seconds per stage before one of its kind has run (then the stages that ran set the estimates):
# the CPU time of the demo's stages (demo.toml), about their wall time on 2 idle cores; training
# from the presets' descriptions (trainer/train.py).
PRIORS = {"bake": 30.0, "report": 35.0, "render": 30.0}
TRAIN_PRIORS = {"fast": 70.0, "balanced": 160.0, "paper": 3600.0}
# The trainer's presets by name (their settings: trainer/train.py PRESETS).
TRAIN_PRESETS = tuple(TRAIN_PRIORS)
# --out of every flowbsdf command that works on a manifest's output folder (train, bake, report, run,
# yardsticks, farm task): the same folder, the same words.
OUT_HELP = "output folder: models/, tables/, report/ inside (default out)"


def add_train_arguments(parser):
    """The arguments of `flowbsdf train` and `python -m trainer train`: one parser for both."""
    parser.add_argument("manifest", help="manifest.toml")
    parser.add_argument("--material", action="append", help="only this material (repeatable)")
    parser.add_argument("--preset", choices=TRAIN_PRESETS, default=None,
                        help="training preset (default: the manifest's, else balanced)")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    parser.add_argument("--out", default="out", help=OUT_HELP)
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (default: 1 for the fast and balanced "
                        "presets, whose small nets train faster on one; all cores for paper)")


def train_models_dir(out, log=print):
    """Where `flowbsdf train --out OUT` writes its models (and their checkpoints): OUT/models, where
    bake, report and run look. Until --out meant the output folder for train too, it named the
    models folder itself, and the Blender add-on and older scripts still pass OUT/models: an OUT
    named models is taken as that folder (with a note), so their models land in OUT/models too."""
    out = Path(out)
    if out.name != "models":
        return out / "models"
    log(f"[train] --out {out} is a models folder: the models go there (--out is the output folder, "
        f"with models/ inside: --out {out.parent} does the same)")
    return out


def run_trainer(args):
    """Training needs torch: `python -m trainer train ARGS` in a subprocess (as the Blender add-on
    does), with $FLOWBSDF_TRAIN_PYTHON or this Python; returns its exit code."""
    python = os.environ.get("FLOWBSDF_TRAIN_PYTHON", sys.executable)
    return subprocess.call([python, "-m", "trainer", "train", *args])


def _digest(obj):
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def run_settings(manifest, key, defaults):
    """The manifest's [run.<key>] over `defaults`: unknown keys, values of another type than the
    default's and unknown sampler or scene names are errors."""
    from ..core.sampler import RENDER_KINDS
    from ..tracer.scene import BUILTINS
    given = manifest.run.get(key, {})
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise FlowBSDFError(f"[run.{key}]: unknown key(s) {', '.join(unknown)} (allowed: {', '.join(defaults)})",
                            manifest.path)
    for k, v in given.items():
        if type(v) is not type(defaults[k]):
            raise FlowBSDFError(f"[run.{key}]: {k} = {v!r} should be like {defaults[k]!r}", manifest.path)
    settings = {**defaults, **given}
    if key == "render":
        bad = sorted(set(settings["samplers"] + [settings["reference_sampler"]]) - set(RENDER_KINDS))
        if bad or settings["scene"] not in BUILTINS:
            raise FlowBSDFError(f"[run.render]: samplers are {', '.join(RENDER_KINDS)}; scenes {', '.join(BUILTINS)}",
                                manifest.path)
    return settings


def selected(manifest, name=None, log=print):
    """The materials the job works on: `name`, or the manifest's (the first max_materials)."""
    entries = manifest.select(name, log=log)
    limit = manifest.run.get("max_materials")
    return entries if name or limit is None else entries[:limit]


class Job:
    """The job on one manifest and output folder. Every stage kind has `<kind>_current(entry,
    material)` (its product is there and matches its inputs) and `<kind>(entry, material)` (do the
    work); `run` plans with the first, for the estimates, and checks again before each stage."""

    def __init__(self, manifest, out_dir, preset="fast", train=True, render=True, samples=None, log=None):
        """samples: per rv cell of the report, over the manifest's."""
        self.manifest, self.out = manifest, Path(out_dir)
        self.preset, self.train_on, self.render_on = preset, train, render
        self.report_settings = run_settings(manifest, "report", REPORT_DEFAULTS)
        if samples:
            self.report_settings["samples"] = samples
        self.render_settings = run_settings(manifest, "render", RENDER_DEFAULTS)
        self.log = log or (lambda line: print(line, flush=True))     # flushed: the lines show when piped too
        self.progress = None
        self.timings = []           # (material, stage, seconds, "done" | "current" | "failed" | "not run")
        self.failures = {}          # {material: (stage, message)}

    def say(self, line):
        (self.progress.say if self.progress else self.log)(line)

    def stages_of(self, material):
        kinds = ["train"] if self.train_on and material.isotropic else []
        return kinds + ["bake", "report"] + (["render"] if self.render_on else [])

    # ---------------------------------------------------------------- train

    def train_current(self, entry, material):
        """A model trained on this very material (any preset: a better one is kept)."""
        from ..core.flow import load_model
        path = model_path(self.out, entry.name)
        try:
            return path.is_file() and \
                load_model(path).meta.get("material", {}).get("fingerprint") == material.fingerprint()
        except FlowBSDFError:
            return False

    def train(self, entry, material):
        if run_trainer([str(self.manifest.path), "--material", entry.name, "--out", str(self.out),
                        "--preset", self.preset, "--no-progress"]) != 0:
            raise FlowBSDFError(f"training {entry.name} failed (see above); rerun to resume from its checkpoints")

    # ---------------------------------------------------------------- bake

    def bake_current(self, entry, material):
        from ..export.derived import TableFile, derived_current
        from ..io.paths import table_path
        from .pipeline import open_current_tables
        try:
            tables = open_current_tables(entry, self.out, self.manifest.path)
            return tables is not None and derived_current(TableFile(table_path(self.out, entry.name), tables))
        except FlowBSDFError:
            return False

    def bake(self, entry, material):
        from .pipeline import bake_with_derived
        bake_with_derived(entry, self.out, self.manifest.path, log=self.say)

    # ---------------------------------------------------------------- report

    def _learned_inputs(self, entry, material):
        """What the learned samplers of a material depend on: its tables' and model's hashes."""
        from .pipeline import open_current_tables
        tables = open_current_tables(entry, self.out, self.manifest.path)
        model = model_path(self.out, entry.name)
        return {"material": material.fingerprint(), "tables": None if tables is None else tables.meta["inputs_hash"],
                "model": file_hash(model) if model.is_file() else None}

    def report_inputs(self, entry, material):
        return _digest({"version": REPORT_VERSION, **self._learned_inputs(entry, material), **self.report_settings})

    def report_current(self, entry, material):
        return _stamp_matches(self.out / "report" / entry.name, self.report_inputs(entry, material))

    def report(self, entry, material):
        from ..quality.report import entry_report, write_report
        from .reports import learned_samplers
        folder = self.out / "report" / entry.name
        digest = self.report_inputs(entry, material)
        t0 = time.perf_counter()
        r = self.report_settings
        material = entry.open()
        flow, tables = learned_samplers(entry, material, self.out, self.manifest.path, log=self.say)
        rows, slice_ = entry_report(entry, material, flow, tables, thetas=r["thetas"], n=r["samples"], steps=(),
                                    log=self.say, speed_n=r["speed_samples"], speed_repeat=r["speed_repeat"])
        written = write_report(rows, folder, slices=[slice_], title=f"{entry.name}: speed vs error")
        pareto = written.get(f"pareto:{entry.name}")
        write_stamp(folder, digest, rows=rows, seconds=time.perf_counter() - t0,
                    files=[Path(p).name for p in written.values()],
                    pdf_slice=Path(written[f"pdf:{entry.name}:{slice_[3]}"]).name,
                    pareto=None if pareto is None else Path(pareto).name)

    # ---------------------------------------------------------------- render

    def reference_inputs(self, entry, material):
        r = self.render_settings
        learned = r["reference_sampler"] in ("tables", "flow")     # a reference drawn by a learned sampler
        return _digest({"version": RENDER_VERSION, "material": material.fingerprint(),
                        "learned": self._learned_inputs(entry, material) if learned else None,
                        **{k: r[k] for k in ("scene", "size", "reference_spp", "reference_sampler", "seed")}})

    def render_inputs(self, entry, material):
        r = self.render_settings
        return _digest({"reference": self.reference_inputs(entry, material),
                        **self._learned_inputs(entry, material), **{k: r[k] for k in ("samplers", "spp", "mis")}})

    def render_current(self, entry, material):
        return _stamp_matches(self.out / "render" / entry.name, self.render_inputs(entry, material))

    def render(self, entry, material):
        import numpy as np
        from ..tracer.compare import compare
        from ..tracer.scene import builtin_scene
        from .scene_samplers import scene_samplers
        r = self.render_settings
        folder = self.out / "render" / entry.name
        ref_digest = self.reference_inputs(entry, material)
        reference, ref_file = None, folder / "reference.npz"
        if ref_file.is_file():
            with np.load(ref_file) as z:
                if str(z["digest"]) == ref_digest:
                    reference = (z["image"], z["variance"])
                    self.say(f"[render {entry.name}] reference: current, reused")
        scene = builtin_scene(r["scene"], material=entry.name, manifest=self.manifest,
                              width=r["size"], height=r["size"])
        t0 = time.perf_counter()
        rows, (ref, ref_var) = compare(scene, r["samplers"], r["spp"], r["reference_spp"], folder,
                                       lambda name: scene_samplers(scene, name, self.out, log=self.say),
                                       reference_sampler=r["reference_sampler"], mis=r["mis"], seed=r["seed"],
                                       log=self.say, reference=reference,
                                       workers=r["workers"], progress=self._render_progress(reference is None))
        if reference is None:
            with atomic_path(ref_file) as tmp:
                with open(tmp, "wb") as f:
                    np.savez(f, image=ref, variance=ref_var, digest=np.array(ref_digest))
        files = ["reference.png", "compare.png", "metrics.md"] + [
            f"{row['sampler']}_{row['mode'].split()[-1]}{suffix}.png" for row in rows if row["mode"] != "unavailable"
            for suffix in ("", "_error")]
        write_stamp(folder, self.render_inputs(entry, material), rows=rows, settings=r, files=files,
                    seconds=time.perf_counter() - t0, load=os.getloadavg()[0])

    def _render_progress(self, with_reference):
        """compare's progress callback, turned into the render stage's share done: each render
        weighs its passes (an equal-time one as much as the equal-spp one it matches)."""
        r = self.render_settings
        order = (["reference"] if with_reference else []) + [
            f"{s} (equal {m})" for s in r["samplers"] for m in ("spp", "time")]
        weight = {w: (r["reference_spp"] if w == "reference" else r["spp"]) for w in order}
        total = sum(weight.values())

        def update(what, passes, fraction, seconds):
            done = sum(weight[w] for w in order[:order.index(what)]) if what in order else 0
            self.progress.update((done + fraction * weight.get(what, 0)) / total, f"{what}: {passes} passes")
        return update

    # ---------------------------------------------------------------- the whole job

    def run(self, name=None):
        """Every stage of every selected material, then the page; returns the page's path. A stage
        that fails ends its material (the rest of its stages are not run), not the job: the other
        materials go on, and the failures, logged and shown on the page, are raised together at the end."""
        from ..quality.page import write_page
        entries = selected(self.manifest, name, log=self.log)
        if not entries:
            raise FlowBSDFError("no material to work on", self.manifest.path)
        plan = []
        for entry in entries:
            try:
                material = entry.open()
                plan += [(entry, material, kind, getattr(self, f"{kind}_current")(entry, material))
                         for kind in self.stages_of(material)]
            except Exception as e:      # noqa: BLE001 (a material that does not open: the others go on)
                self._failed(entry, "open", e)
        priors = {**PRIORS, "train": TRAIN_PRIORS.get(self.preset, TRAIN_PRIORS["fast"])}
        self.progress = Progress([(kind, not current) for _, _, kind, current in plan], priors, out=self.log)
        todo = sum(not current for *_, current in plan)
        self.log(f"[run] {len(entries)} material(s): {', '.join(e.name for e in entries)} -> {self.out}; "
                 f"{len(plan)} stages, {todo} to run, {len(plan) - todo} current")
        try:
            for i, (entry, material, kind, _) in enumerate(plan):
                self.progress.stage(kind, entry.name)
                t0 = time.perf_counter()
                if entry.name in self.failures:
                    status = "not run"
                    self.progress.end(skipped=True, note=f"not run: its {self.failures[entry.name][0]} failed")
                else:
                    try:
                        current = getattr(self, f"{kind}_current")(entry, material)
                        if not current:
                            getattr(self, kind)(entry, material)
                        status = "current" if current else "done"
                        self.progress.end(skipped=current, note="current, skipped" if current else "done")
                    except Exception as e:      # noqa: BLE001 (one material's failure, whatever it is, is its own)
                        status = "failed"
                        self.progress.end(note="FAILED")
                        self._failed(entry, kind, e)
                self.timings.append((entry.name, kind, time.perf_counter() - t0, status))
                if i + 1 < len(plan) and plan[i + 1][0] is not entry:      # a material's last stage
                    write_page(self.out, self.manifest, entries, self.timings, self.failures)
            page = write_page(self.out, self.manifest, entries, self.timings, self.failures)
        finally:
            total = self.progress.close()
            self.progress = None
        count = {s: sum(status == s for *_, status in self.timings) for s in ("done", "current", "failed", "not run")}
        self.log(f"[run] {count['done']} stage(s) ran, {count['current']} current (skipped), "
                 + (f"{count['failed']} failed, {count['not run']} not run after a failure, " if self.failures else "")
                 + f"{fmt_seconds(total)} in all")
        self.log(f"[page] {page.resolve()}")
        if self.failures:
            raise FlowBSDFError(f"{len(self.failures)} of {len(entries)} material(s) failed, the others are done: "
                                + "; ".join(f"{n} ({kind}: {message})" for n, (kind, message) in self.failures.items()),
                                self.manifest.path)
        return page

    def _failed(self, entry, kind, error):
        """Record a material's failed stage: its message in the log (after the traceback when it is
        not a FlowBSDFError: a bug) and, through self.failures, on the page."""
        message = str(error)
        if not isinstance(error, FlowBSDFError):
            self.say(traceback.format_exc().rstrip())
            message = f"{type(error).__name__}: {message}"
        self.failures[entry.name] = (kind, message)
        self.say(f"[fail] {entry.name} {kind}: {message} (its other stages are not run; the job goes on)")


def _stamp_matches(folder, digest):
    """The folder's job.json records these inputs and every file it lists is there."""
    stamp = read_stamp(folder)
    return bool(stamp) and stamp.get("inputs_hash") == digest and \
        all((Path(folder) / f).is_file() for f in stamp.get("files", ()))
