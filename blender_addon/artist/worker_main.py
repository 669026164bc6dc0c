"""The FlowBSDF worker: runs outside Blender, in a Python with numpy + OpenEXR (+ torch to train).

    python worker_main.py probe
    python worker_main.py status MANIFEST --out DIR
    python worker_main.py bake MANIFEST --out DIR [--material NAME]... [--train never|always|auto]
        (tables, the node's textures and fit, and a preview beside them: <name>.preview.png)
    python worker_main.py validate SCENE.toml --manifest M --out DIR --cycles CYCLES.exr [--spp N]

A standalone script (no bpy, no add-on imports): the add-on starts it as a subprocess with
its own `bake` first on PYTHONPATH, reads its stdout line by line, and kills its process
group to cancel. Every output line ends with a newline, so a farm log can follow it:
    [progress K/N] what          a step starts (K counts from 1)
    [step F] words               how far the current step is (F in [0, 1]) in an artist's words,
                                 with the time left ("Baking X: 7 of about 17 angles, about 1 min left")
    [status] {json}              one material's state (status; bake, at its end)
    [error] message              why the job failed (exit code 2)
    anything else                log text (the baker's and the trainer's lines)
"""
import argparse
import importlib.util
import json
import math
import os
import re
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path

_out = threading.Lock()


def emit(line):
    with _out:                  # whole lines, also from the heartbeat thread
        sys.stdout.write(f"{line}\n")
        sys.stdout.flush()


# -- progress in an artist's words -------------------------------------------------------------

def time_left(seconds):
    """'about 2 min left' and the like; '' when unknown."""
    if seconds is None:
        return ""
    if seconds < 15:
        return "a few seconds left"
    if seconds < 55:
        return f"about {10 * round(seconds / 10)} s left"
    if seconds < 90:
        return "about 1 min left"
    if seconds < 3600:
        return f"about {round(seconds / 60)} min left"
    return f"about {seconds / 3600:.1f} h left"


class Step:
    """One step of a job (a material's bake or training) as `[step F] words` lines: on every
    event and, from a heartbeat thread, every HEARTBEAT seconds (so the time left counts down
    and the bar moves while the step is busy). F never goes back."""
    HEARTBEAT = 5.0

    def __init__(self, clock=time.monotonic):
        self.clock, self.t0, self.done = clock, clock(), 0.0
        self._stop = threading.Event()
        self._thread = None

    def estimate(self, now):          # -> (fraction of the step or None, words)
        raise NotImplementedError

    def report(self):
        now = self.clock()
        fraction, words = self.estimate(now)
        if fraction is not None:
            self.done = min(max(self.done, fraction), 0.99)
        emit(f"[step {self.done:.3f}] {words}")

    def __enter__(self):
        self.report()

        def beat():
            while not self._stop.wait(self.HEARTBEAT):
                self.report()
        self._thread = threading.Thread(target=beat, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


class _Plan:
    """One plan's progress: the material's only plan, or one cell layout's of an isotropic material."""

    def __init__(self, resolution, first):
        self.resolution, self.stage, self.probed, self.bins = resolution, "prepare", 0, first
        self.scores = []        # the worst midpoint's loss over its target, per split
        self.turns = []         # seconds of its turns (a split's new intervals scored), measured
        self.opened = None      # when its turn under way began (its split or resolution line)
        self.ended = False      # done, stopped or dropped

    def seconds_per_angle(self):
        recent = self.turns[-4:]
        return sum(recent) / len(recent)


class BakeProgress(Step):
    """A material's bake, estimated from the baker's log (bake/core/planner.plan_tables): the
    resolution probe ("resolution R: single-bin rv Xx the target"), then one line per incident
    angle the planner adds ("bins N: split ... (midpoint loss Sx its target)") until the worst
    midpoint reaches its target (S <= 1) or the memory budget caps the angles, then the tables'
    build ("tables: building N angles", "tables: built K of N", about ten of them), after a
    comparison of cell placements between bins where the planner makes one ("between bins:
    comparing N", "placement K of N"; planner._between_bins: by default only plans of fewer than
    6 angles over wo, a few cheap builds), then the node's textures and fit, and the preview
    ("tables in", "[svm]/[osl]/[fit] wrote", "[preview]": AFTER_TABLES, each at its measured
    cost, counted in the bar from the start). The comparison's time: its placements at their
    measured pace (the reference draws before the first count as one more), until the first is
    done PLACEMENT_COST split turns per angle each. The build: BUILD_COST split turns per angle
    until its first "built" line, then its own pace. Angles left: from how far the worst midpoint went down on a log scale, and how far
    the angle count went towards its cap; the time a split takes, measured. An isotropic material is planned over each cell
    layout (planner.ISO_PLANNED; its lines start "<coords>: ") in turns, a round of splits each
    (planner._plan_in_turns): each plan is followed on its own (its angles left from its own
    midpoints), and the time a split takes is each plan's own turn (from its split line to the
    next plan's line), measured; the time left is every running plan's angles left at its own
    pace, the words say the plan that spoke last ("layout 2 of 2, 7 of about 12 angles, ...").
    Until every running plan has three splits and a measured turn: "estimating the time left".
    Lines pass through to the log."""
    RESOLUTION = re.compile(r"resolution (\d+): single-bin rv ([0-9.eE+-]+)x the target")
    SPLIT = re.compile(r"bins (\d+): split .*\(midpoint loss ([0-9.eE+-]+)x its target\)")
    ENDED = re.compile(r"bins (\d+): (done|stopped|dropped)\b")
    COORDINATES = re.compile(r"coordinates: (\w+) \(")
    PLACEMENTS = re.compile(r"between bins: comparing (\d+) cell placements(?: on (\d+) angles)?")
    PLACED = re.compile(r"between bins: placement (\d+) of (\d+)")
    BUILDING = re.compile(r"tables: building (\d+) angles")
    BUILT = re.compile(r"tables: built (\d+) of (\d+)")
    TABLES_DONE = re.compile(r"tables in [0-9.]+ s$")
    # A placement's cost (its tables built from the ideal's cached points, their rv at ~4 angles
    # per bin) and the build's (the kept placement's tables from the same points, when not
    # compared), in the kept plan's split turns per angle, each the ratio within one Final bake (a
    # busy 2-core machine, load 7-24): placements 0.12-0.15 (cm_military_green, 45 angles, three
    # bakes) and ~0.19 (paper_white, 21), the reference draws before them 0.15-0.3; the build
    # 0.06-0.12. The placements an isotropic material compares by default (planner._between_bins,
    # placement "compare", the full comparison): 5-6 on the shared files (2-3 with placement "rule");
    # counted as 3 until the stage's first line says how many (then its own count: an estimate
    # that is low by 2-3 placements before that line; the rule's count, which the tests' numbers use).
    PLACEMENT_COST = 0.15
    ISO_PLACEMENTS = 3
    BUILD_COST = 0.1
    # After the tables: the node's SVM and OSL textures, the closure fit (FIT_VERSION 7), the
    # preview (write_preview), in seconds, in the order they run; a line ends each (the preview's
    # first line: the fit is done). Measured as CPU seconds of each alone (single-threaded: about
    # their wall time on an idle core) on paper_white and cm_military_green: SVM 0.2-0.5, OSL
    # 0.2-0.4, the fit 10.9-15.3, the preview (96², 32 spp) 1.4. Their wall time on a loaded
    # machine is many times that (load 23-25: the fit 126-366 s): once the textures are written,
    # the steps left are scaled by their pace against these costs.
    AFTER_TABLES = (("svm", 0.5), ("osl", 0.5), ("fit", 13.0), ("preview", 1.5))
    AFTER_WORDS = {"svm": "writing the node's textures and closure fit", "osl": "writing the node's textures and closure fit",
                   "fit": "fitting the node's closures", "preview": "rendering a preview"}

    def __init__(self, name, settings, clock=time.monotonic):
        from bake.core.planner import ISO_PLANNED, RESOLUTIONS, bins_within
        super().__init__(clock)
        self.name, self.resolutions, self.bins_within = name, RESOLUTIONS, bins_within
        self.planned_resolution, self.first = settings.resolution, settings.first_bins     # (BakeSettings)
        self.target, self.budget = 1.0, settings.memory_budget     # the planner's scores are x its targets
        self.layout_names = ISO_PLANNED
        self.layout_of = re.compile("(" + "|".join(ISO_PLANNED) + "): (.*)$")
        self.layouts, self.layout = 1, 0          # plans of this material (one until a line says more), the one in words
        self.plans = {0: _Plan(self.planned_resolution, self.first)}
        self.speaker = None                        # the plan whose turn is under way
        self.last_turn = self.t0                   # when the last planner line came
        self.angles = self.first                   # the kept plan's angles (placements, build)
        self.stage = None                          # after the plans: "placements", "build", "derive", "preview"
        self.build = None                          # [start time, parts built, parts, time of the last]
        self.placed = None                         # [start time, placements done, placements, time of the last]
        self.after = None                          # [AFTER_TABLES index under way, when it began]

    @property
    def plan(self):
        return self.plans[self.layout]

    @property
    def resolution(self):
        return self.plan.resolution

    @property
    def bins(self):
        return self.plan.bins

    def _plan_of(self, layout):
        return self.plans.setdefault(layout, _Plan(self.planned_resolution, self.first))

    def _turn(self, layout, text, now):
        """A planner line of `layout` (None: no plan's, e.g. "coordinates: ..."): it ends the turn
        under way when another plan speaks, or this plan's next split or resolution line comes."""
        boundary = bool(self.RESOLUTION.match(text) or text.startswith("bins "))
        if self.speaker is not None and (layout != self.speaker or boundary):
            p = self.plans[self.speaker]
            p.turns.append(now - p.opened)
            p.opened, self.speaker = None, None
            self.last_turn = now
        if boundary:
            self.last_turn = now

    def _open(self, layout, now):
        self.plans[layout].opened, self.speaker = now, layout

    def log(self, line):
        emit(line)
        text = line.split(": ", 1)[1] if line.startswith("[bake] ") and ": " in line else ""
        now = self.clock()
        speaker = 0
        m = self.layout_of.match(text)
        if m:
            self.layouts = len(self.layout_names)
            speaker = self.layout_names.index(m.group(1))
            text = m.group(2)
        elif self.layouts > 1:
            speaker = None
        if text:
            self._turn(speaker, text, now)
        p = self._plan_of(speaker) if speaker is not None else None
        m = self.RESOLUTION.match(text)
        if m and p:
            p.stage, p.probed = "probe", self.resolutions.index(int(m.group(1))) + 1
            if float(m.group(2)) <= self.target or p.probed == len(self.resolutions):
                p.resolution, p.stage = int(m.group(1)), "plan"
                self._open(speaker, now)
            self.layout = speaker
        elif self.SPLIT.match(text) and p:
            m = self.SPLIT.match(text)
            if p.stage != "plan":       # the resolution given: the plan began with the bake
                p.stage = "plan"
                if self.layouts == 1:   # (planned alone: its first turn is the time so far)
                    p.turns.append(now - self.t0)
            p.bins = int(m.group(1))
            p.scores.append(float(m.group(2)))
            self._open(speaker, now)
            self.layout = speaker
        elif self.ENDED.match(text) and p:
            p.ended = True
            return
        elif self.COORDINATES.match(text):
            kept = self.COORDINATES.match(text).group(1)
            if kept in self.layout_names:
                self.layout = self.layout_names.index(kept)
            return
        elif self.PLACEMENTS.match(text):
            m = self.PLACEMENTS.match(text)
            self.stage, self.placed = "placements", [now, 0, int(m.group(1)), now]
            self.angles = int(m.group(2)) if m.group(2) else self.bins
        elif self.PLACED.match(text) and self.placed:
            self.placed[1:] = [int(n) for n in self.PLACED.match(text).groups()] + [now]
        elif self.BUILDING.match(text):
            self.angles = int(self.BUILDING.match(text).group(1))
            self.stage, self.build = "build", [now, 0, None, None]
        elif self.BUILT.match(text) and self.build:
            m = self.BUILT.match(text)
            self.build[1:] = [int(m.group(1)), int(m.group(2)), now]
        elif self.TABLES_DONE.match(text):
            self.stage, self.after = "after", [0, now, now]
        elif line.startswith(("[svm] wrote", "[osl] wrote", "[fit] wrote", "[preview] ")):
            kind = line[1:line.index("]")]
            names = [k for k, _ in self.AFTER_TABLES]
            step = names.index(kind) + (0 if kind == "preview" else 1)
            if self.after is None or step > self.after[0]:
                self.stage, self.after = "after", [min(step, len(names) - 1), now, self.after[2] if self.after else now]
        else:
            return
        self.report()

    def max_bins(self, plan=None):
        plan = plan or self.plan
        return self.bins_within(self.budget, plan.resolution) if plan.resolution else None

    def angles_left(self, plan=None):
        """(angles the plan will still add, True when that is the memory cap)."""
        plan = plan or self.plan
        cap = self.max_bins(plan) - plan.bins
        progress = (plan.bins - self.first) / max(self.max_bins(plan) - self.first, 1)
        if plan.scores[0] > self.target:
            span = math.log(plan.scores[0] / self.target)
            progress = max(progress, math.log(plan.scores[0] / max(plan.scores[-1], 1e-30)) / span)
        if progress <= 0:
            return cap, True
        left = math.ceil((plan.bins - self.first) * (1 - min(progress, 1.0)) / progress)
        return (cap, True) if left >= cap else (left, False)

    def estimate(self, now):
        who = f"Baking {self.name}"
        elapsed = now - self.t0
        if self.stage == "after":
            step, began, start = self.after
            # the steps done so far against their costs: how much slower this machine is now (a
            # busy one: the fit at the textures' pace)
            pace = max((began - start) / sum(c for _, c in self.AFTER_TABLES[:step]), 1.0) if step else 1.0
            remaining = pace * self.after_left(step, (now - began) / pace)
            words = f"{who}: {self.AFTER_WORDS[self.AFTER_TABLES[step][0]]}"
            if remaining <= 0:
                return None, words
            return elapsed / (elapsed + remaining), f"{words}, {time_left(remaining)}"
        if self.stage == "build":
            return self._build_estimate(now, who)
        if self.stage == "placements":
            return self._placements_estimate(now, who)
        shown = self.layout
        running = [k for k, q in self.plans.items() if not q.ended]
        if self.plan.ended and running:         # the words follow a plan still running
            shown = running[0]
        running = [self.plans[k] for k in running]
        p = self.plans[shown]
        layout = f"layout {shown + 1} of {self.layouts}, " if self.layouts > 1 else ""
        if p.stage == "prepare" and self.layouts == 1:
            return 0.02, f"{who}: tabulating the material"
        if p.stage in ("prepare", "probe"):
            return 0.05, f"{who}: {layout}choosing the table resolution ({p.probed} of {len(self.resolutions)})"
        running = running or [p]
        if any(q.stage != "plan" or len(q.scores) < 3 or not q.turns for q in running + [p]):
            return 0.1, f"{who}: {layout}{p.bins} angles placed, estimating the time left"
        lefts = [self.angles_left(q)[0] for q in running]
        left, capped = self.angles_left(p)
        total = p.bins + left
        # every running plan's angles left at its own measured pace, less the turn under way so far
        plan_left = sum(n * q.seconds_per_angle() for n, q in zip(lefts, running)) - (now - self.last_turn)
        # then the kept plan's placements (+1: the reference draws) or build, and what follows the
        # tables; which plan is kept is not known yet: the costliest running plan's angles at its pace
        per_angle = max((q.bins + n) * q.seconds_per_angle() for n, q in zip(lefts, running))
        placements = self.ISO_PLACEMENTS + 1 if self.layouts > 1 else 0
        remaining = plan_left + per_angle * (placements * self.PLACEMENT_COST + self.BUILD_COST) + self.after_left()
        if remaining <= 0:
            return None, f"{who}: finishing the tables ({total} angles)"
        if not any(lefts):
            words = (f"{who}: {total} angles placed, comparing cell placements next" if placements else
                     f"{who}: building the tables for {total} angles") + f", {time_left(remaining)}"
        else:
            words = (f"{who}: {layout}{p.bins} of {'at most' if capped else 'about'} {total} angles, "
                     f"{time_left(remaining)}")
        return elapsed / (elapsed + remaining), words

    def after_left(self, step=0, spent=0.0):
        """Seconds of AFTER_TABLES left from its step `step`, `spent` seconds into it."""
        costs = [c for _, c in self.AFTER_TABLES]
        return max(costs[step] - spent, 0.0) + sum(costs[step + 1:])

    def _placements_estimate(self, now, who):
        start, done, total, last = self.placed
        split = self.plan.seconds_per_angle() if self.plan.turns else 1.0
        if done:
            pace, left = (last - start) / (done + 1), total - done
        else:
            pace, left = self.PLACEMENT_COST * self.angles * split, total + 1
        remaining = left * pace - (now - last) + self.angles * split * self.BUILD_COST + self.after_left()
        words = f"{who}: comparing cell placements across {self.angles} angles ({done} of {total} done"
        if remaining <= 0:
            return None, words + ")"
        elapsed = now - self.t0
        return elapsed / (elapsed + remaining), words + f", {time_left(remaining)})"

    def _build_estimate(self, now, who):
        start, done, parts, last = self.build
        if done:
            remaining = (last - start) / done * (parts - done) - (now - last)
        else:
            split = self.plan.seconds_per_angle() if self.plan.turns else 1.0
            remaining = self.angles * split * self.BUILD_COST - (now - start)
        remaining = max(remaining, 0.0) + self.after_left()
        words = f"{who}: building the tables ({done} of {parts or self.angles} angles done"
        elapsed = now - self.t0
        return elapsed / (elapsed + remaining), words + f", {time_left(remaining)})"


TRAIN_TIME = {"fast": "about 1 min", "balanced": "2-3 min", "paper": "hours without a GPU"}


class TrainProgress(Step):
    """A material's training: its stage (the trainer's "[stage]" lines) and the time so far."""
    STAGE = re.compile(r"^\[(\w+)\]")

    def __init__(self, name, preset, clock=time.monotonic):
        super().__init__(clock)
        self.name, self.preset, self.stage = name, preset, "starting"

    def log(self, line):
        emit(f"[train] {self.name}: {line}")
        m = self.STAGE.match(line)
        if m and m.group(1) != self.stage:
            self.stage = m.group(1)
            self.report()

    def estimate(self, now):
        minutes = (now - self.t0) / 60
        so_far = "under a minute so far" if minutes < 1 else f"{minutes:.0f} min so far"
        usual = TRAIN_TIME.get(self.preset, "minutes")
        return None, f"Training {self.name} ({self.preset}, usually {usual}): {self.stage}, {so_far}"


def cmd_probe(args):
    has = {m: importlib.util.find_spec(m) is not None for m in ("numpy", "OpenEXR", "torch", "trainer")}
    spec = importlib.util.find_spec("bake")
    emit("[probe] " + json.dumps({
        "numpy": has["numpy"], "openexr": has["OpenEXR"], "torch": has["torch"], "trainer": has["trainer"],
        "bake": None if spec is None else str(Path(spec.origin).parent),
        "python": sys.executable, "executable": os.path.realpath(sys.executable), "base_prefix": sys.base_prefix,
        "version": list(sys.version_info[:3])}))
    return 0


def material_status(entry, out_dir, manifest_path):
    """A material's state: can it be opened, is it isotropic, model and tables present/current."""
    from bake.errors import FlowBSDFError
    from bake.io.paths import model_path, table_path
    from bake.plumbing.pipeline import open_current_tables
    info = {"name": entry.name, "domain": entry.domain, "isotropic": None, "error": None,
            "model": model_path(out_dir, entry.name).is_file(), "tables": "missing",
            "tables_path": str(table_path(out_dir, entry.name)), "theta_bins_deg": None}
    try:
        material = entry.open()
        info["isotropic"] = bool(material.isotropic)
        if table_path(out_dir, entry.name).is_file():
            try:
                tables = open_current_tables(entry, out_dir, manifest_path)
            except FlowBSDFError:
                tables = None
            info["tables"] = "stale" if tables is None else "current"
            if tables is not None:
                import numpy as np
                if preview_path(table_path(out_dir, entry.name)).is_file():
                    info["preview"] = str(preview_path(table_path(out_dir, entry.name)))
                info["theta_bins_deg"] = [round(float(np.degrees(t)), 3) for t in tables.theta_bins]
                info["tables_source"] = tables.meta.get("source")      # "flow" or "ideal"
    except FlowBSDFError as e:
        info["error"] = str(e)
    return info


def cmd_status(args):
    from bake.plumbing.manifest import load_manifest
    manifest = load_manifest(args.manifest)
    for entry in manifest.select(args.material and args.material[0], log=emit):
        emit("[status] " + json.dumps(material_status(entry, args.out, manifest.path)))
    return 0


def can_train():
    return all(importlib.util.find_spec(m) is not None for m in ("torch", "trainer"))


def train(entry, manifest_path, out_dir):
    """Train one material with the trainer as a child process (same Python), relaying its lines."""
    cmd = [sys.executable, "-m", "trainer", "train", str(manifest_path), "--material", entry.name,
           "--out", str(Path(out_dir) / "models"), "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    with TrainProgress(entry.name, str(entry.train.get("preset", "balanced"))) as progress:
        for line in proc.stdout:
            progress.log(line.rstrip())
        return proc.wait()


PREVIEW_SIZE, PREVIEW_SPP = 96, 32         # about 2 s with the tables sampler on one core


def preview_path(tables_path):
    return Path(tables_path).with_name(Path(tables_path).stem + ".preview.png")


def write_preview(entry, manifest, out_dir, tables_path, log=emit):
    """<name>.preview.png beside the tables: the material on the reference tracer's shader ball
    under its soft sky (builtin:shaderball-env), sampled from the baked tables; remade when
    older than the tables. Returns its path."""
    path = preview_path(tables_path)
    if path.is_file() and path.stat().st_mtime >= Path(tables_path).stat().st_mtime:
        return path
    from bake.tracer.images import tonemap, write_png
    from bake.tracer.integrator import render
    from bake.plumbing.scene_samplers import scene_samplers
    from bake.tracer.scene import builtin_scene
    log(f"[preview] {entry.name}: {PREVIEW_SIZE}x{PREVIEW_SIZE}, {PREVIEW_SPP} spp, shader ball under a soft sky")
    scene = builtin_scene("shaderball-env", material=entry.name, manifest=manifest, width=PREVIEW_SIZE,
                          height=PREVIEW_SIZE)
    image, _, _ = render(scene, scene_samplers(scene, "tables", out_dir, log=log), spp=PREVIEW_SPP, mis=True,
                         seed=0)
    write_png(path, tonemap(image))
    log(f"[preview] wrote {path}")
    return path


def cmd_bake(args):
    from bake.errors import FlowBSDFError
    from bake.plumbing.manifest import load_manifest
    from bake.plumbing.pipeline import bake_entry, bake_settings, wants_model
    manifest = load_manifest(args.manifest)
    wanted = set(args.material or [])
    entries = [e for e in manifest.select(log=emit) if not wanted or e.name in wanted]
    unknown = wanted - {e.name for e in entries}
    if unknown:
        raise FlowBSDFError(f"no material(s) {', '.join(sorted(unknown))} in the manifest", manifest.path)
    trainer_here = can_train()
    plan, failures = [], []
    for entry in entries:
        try:
            needs_model = wants_model(entry, entry.open(), bake_settings(entry, manifest.path), args.out)
        except FlowBSDFError as e:          # reported at the end; the others still bake
            failures.append(f"{entry.name}: {e}")
            emit(f"[fail] {failures[-1]}")
            continue
        if needs_model and args.train == "always" and not trainer_here:
            raise FlowBSDFError(f"material {entry.name!r} needs training, but this Python ({sys.executable}) "
                                "has no torch/trainer: use one that has (the FlowBSDF checkout's "
                                ".venv/bin/python), or bake without training")
        if needs_model and args.train != "never" and trainer_here:
            plan.append(("train", entry))
        elif needs_model:
            failures.append(f"{entry.name}: its tables come from a trained model and it has none: Train + Bake, "
                            "Load Model, or set From (under Tables): Material")
            emit(f"[fail] {failures[-1]}")
            continue
        plan.append(("bake", entry))
    for k, (step, entry) in enumerate(plan, 1):
        emit(f"[progress {k}/{len(plan)}] {step} {entry.name}")
        if step == "train":
            code = train(entry, manifest.path, args.out)
            if code != 0:
                failures.append(f"{entry.name}: training failed (exit code {code}); rerun to resume")
                emit(f"[fail] {failures[-1]}")
            else:
                emit(f"[trained] {entry.name}")
            continue
        try:
            with BakeProgress(entry.name, bake_settings(entry, manifest.path)) as progress:
                path, status = bake_entry(entry, args.out, manifest.path, log=progress.log)
                if path is not None:        # the node's OSL texture and closure fit, beside the tables
                    from bake.export.derived import bake_derived
                    bake_derived(path, material=entry.open(), log=progress.log)
                    write_preview(entry, manifest, args.out, path, log=progress.log)
        except FlowBSDFError as e:
            failures.append(f"{entry.name}: {e}")
            emit(f"[fail] {failures[-1]}")
            continue
        emit({"current": f"[skip] {entry.name}: {path} is up to date", "baked": f"[wrote] {path}",
              "unsupported": f"[skip] {entry.name}: not baked (unsupported)"}[status])
    for entry in entries:
        emit("[status] " + json.dumps(material_status(entry, args.out, manifest.path)))
    emit(f"[progress {len(plan)}/{len(plan)}] done")
    if failures:
        raise FlowBSDFError(f"{len(failures)} material(s) failed: " + "; ".join(failures))
    return 0


def compare_text(result, vmax):
    """The captions (Cycles | reference | difference) and the footer of compare.png."""
    ratio = result["mean_cycles"] / result["mean_reference"] - 1 if result["mean_reference"] else 0.0
    captions = [["Cycles", f"{result['cycles_spp']} spp"],
                ["Reference tracer", f"{result['reference_spp']} spp, MIS"],
                ["|Cycles - reference|", f"0 to {vmax:.3g}"]]
    footer = [f"MSE {result['mse']:.3g}   SSIM {result['ssim']:.3f}",
              f"mean: Cycles {result['mean_cycles']:.4f}, reference {result['mean_reference']:.4f} "
              f"({100 * ratio:+.1f} %)"]
    return captions, footer


def write_compare(path, cycles, ref, result):
    """compare.png (Cycles, the reference and their luminance difference, labelled, with the
    numbers) and compare.md beside it saying the same in words."""
    import numpy as np
    from bake.maths.geometry import LUMINANCE
    from bake.tracer.images import false_colour, tonemap, write_png
    from bake.tracer.label import labelled_panels
    err = np.abs((cycles - ref) @ LUMINANCE)
    vmax = float(np.percentile(err, 99)) or 1.0
    captions, footer = compare_text(result, vmax)
    write_png(path, labelled_panels([tonemap(cycles), tonemap(ref), false_colour(err, vmax)], captions, footer))
    Path(path).with_suffix(".md").write_text(
        f"# FlowBSDF validate\n\n![compare]({Path(path).name})\n\n"
        f"Left: Cycles ({result['cycles_spp']} spp). Middle: the reference tracer ({result['reference_spp']} spp, "
        f"the baked tables, lamps and world sampled with MIS). Right: |Cycles - reference| in luminance, "
        f"colour scale 0 to {vmax:.3g}.\n\n" + "\n\n".join(footer) +
        f"\n\nReference noise (mean variance of its pixel means): {result['reference_noise']:.3g}\n")


def cmd_validate(args):
    """Reference render of an exported scene (tables sampler; lamps and environment sampled with
    MIS, as the OSL back end does) vs Cycles' image."""
    import numpy as np
    from bake.errors import FlowBSDFError
    from bake.plumbing.manifest import load_manifest
    from bake.tracer.compare import metrics
    from bake.tracer.images import read_exr, write_exr
    from bake.tracer.integrator import render
    from bake.plumbing.scene_samplers import scene_samplers
    from bake.tracer.scene import load_scene
    scene = load_scene(args.scene, manifest=load_manifest(args.manifest))
    cycles = np.asarray(read_exr(args.cycles), np.float32)[..., :3]
    cam = scene.camera
    if cycles.shape[:2] != (cam.height, cam.width):
        raise FlowBSDFError(f"Cycles image is {cycles.shape[1]}x{cycles.shape[0]}, the scene "
                            f"{cam.width}x{cam.height}", args.cycles)
    spp = args.reference_spp or 4 * args.spp
    emit(f"[progress 1/2] reference render {cam.width}x{cam.height}, {spp} spp (tables, MIS)")
    samplers = scene_samplers(scene, "tables", args.out, log=emit)
    last = [0.0]

    def progress(k, elapsed, st):
        if elapsed - last[0] >= 2.0 or k == spp:
            last[0] = elapsed
            emit(f"[step {k / spp:.3f}] Reference render: {k} of {spp} samples, "
                 f"{time_left(elapsed * (spp - k) / k) if k < spp else 'done'}")
    ref, var, _ = render(scene, samplers, spp=spp, mis=True, seed=0, progress=progress)
    emit("[progress 2/2] compare")
    folder = Path(args.cycles).parent
    write_exr(folder / "reference.exr", ref)
    image = folder / "compare.png"
    result = {k: float(v) for k, v in metrics(cycles, ref).items()}
    mean_ref, mean_cyc = float(ref.mean()), float(cycles.mean())
    result.update(reference_noise=float(np.mean(var)), reference_spp=spp, cycles_spp=args.spp,
                  mean_reference=mean_ref, mean_cycles=mean_cyc, image=str(image),
                  reference=str(folder / "reference.exr"), cycles=str(args.cycles))
    write_compare(image, cycles, ref, result)
    (folder / "metrics.json").write_text(json.dumps(result, indent=1) + "\n")
    emit(f"[validate] {json.dumps(result)}")
    emit(f"MSE {result['mse']:.4g}, SSIM {result['ssim']:.4f}, mean {mean_cyc:.4f} (Cycles) vs "
         f"{mean_ref:.4f} (reference); wrote {image}")
    emit("[progress 2/2] done")
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(prog="flowbsdf-worker")
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("probe").set_defaults(func=cmd_probe)
    for name, func in (("status", cmd_status), ("bake", cmd_bake)):
        c = sub.add_parser(name)
        c.add_argument("manifest")
        c.add_argument("--out", required=True)
        c.add_argument("--material", action="append")
        c.set_defaults(func=func)
        if name == "bake":
            c.add_argument("--train", choices=["auto", "always", "never"], default="never")
    v = sub.add_parser("validate")
    v.add_argument("scene")
    v.add_argument("--manifest", required=True)
    v.add_argument("--out", required=True, help="the folder with tables/")
    v.add_argument("--cycles", required=True, help="Cycles' render of the same scene (.exr)")
    v.add_argument("--spp", type=int, default=16, help="Cycles' samples per pixel")
    v.add_argument("--reference-spp", type=int, default=None, help="default: 4 x --spp")
    v.set_defaults(func=cmd_validate)
    args = p.parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        emit("[error] interrupted")
        return 130
    except Exception as e:       # noqa: BLE001 - one clear line for the user, the traceback for the log
        if type(e).__name__ != "FlowBSDFError":
            traceback.print_exc(file=sys.stdout)
        emit(f"[error] {e}")
        return 2


if __name__ == "__main__":
    if sys.path and Path(sys.path[0]).resolve() == Path(__file__).resolve().parent:
        del sys.path[0]          # the add-on's own modules are not importable outside Blender
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    sys.exit(main())
