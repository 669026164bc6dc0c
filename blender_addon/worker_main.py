"""The FlowBSDF worker: runs outside Blender, in a Python with numpy + OpenEXR (+ torch to train).

    python worker_main.py probe
    python worker_main.py status MANIFEST --out DIR
    python worker_main.py bake MANIFEST --out DIR [--material NAME]... [--train auto|always|never]
    python worker_main.py validate SCENE.toml --manifest M --out DIR --cycles CYCLES.exr [--spp N]

A standalone script (no bpy, no add-on imports): the add-on starts it as a subprocess with
its own `bake` first on PYTHONPATH, reads its stdout line by line, and kills its process
group to cancel. Every output line ends with a newline, so a farm log can follow it:
    [progress K/N] what          a step starts (K counts from 1)
    [status] {json}              one material's state (status; bake, at its end)
    [error] message              why the job failed (exit code 2)
    anything else                log text (the baker's and the trainer's lines)
"""
import argparse
import importlib.util
import json
import os
import subprocess
import sys
import traceback
from pathlib import Path


def emit(line):
    print(line, flush=True)


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
    from bake.pipeline import model_path, open_current_tables, table_path
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
                info["theta_bins_deg"] = [round(float(np.degrees(t)), 3) for t in tables.theta_bins]
                info["tables_source"] = tables.meta.get("source")      # "flow" or "ideal"
    except FlowBSDFError as e:
        info["error"] = str(e)
    return info


def cmd_status(args):
    from bake.manifest import load_manifest
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
    for line in proc.stdout:
        emit(f"[train] {entry.name}: {line.rstrip()}")
    return proc.wait()


def cmd_bake(args):
    from bake.errors import FlowBSDFError
    from bake.manifest import load_manifest
    from bake.pipeline import bake_entry, bake_settings, model_path
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
            isotropic = entry.open().isotropic
        except FlowBSDFError as e:          # reported at the end; the others still bake
            failures.append(f"{entry.name}: {e}")
            emit(f"[fail] {failures[-1]}")
            continue
        wants_model = (isotropic and bake_settings(entry, manifest.path)["source"] != "ideal"
                       and not model_path(args.out, entry.name).is_file())
        if wants_model and args.train == "always" and not trainer_here:
            raise FlowBSDFError(f"material {entry.name!r} needs training, but this Python ({sys.executable}) "
                                "has no torch/trainer: use one that has (the FlowBSDF checkout's "
                                ".venv/bin/python), or bake without training")
        if wants_model and args.train != "never" and trainer_here:
            plan.append(("train", entry))
        elif wants_model:
            emit(f"[note] {entry.name}: no trained model; baking from the ideal tabulation")
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
            path, status = bake_entry(entry, args.out, manifest.path, log=emit)
            if path is not None:        # the node's OSL texture and closure fit, beside the tables
                from bake.osl_export import bake_derived
                bake_derived(path, log=emit)
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


def cmd_validate(args):
    """Reference render of an exported scene (tables sampler; lamps and environment sampled with
    MIS, as the OSL back end does) vs Cycles' image."""
    import numpy as np
    from bake.errors import FlowBSDFError
    from bake.manifest import load_manifest
    from bake.tracer.compare import metrics, write_side_by_side
    from bake.tracer.images import read_exr, write_exr
    from bake.tracer.integrator import render
    from bake.tracer.samplers import scene_samplers
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
            emit(f"[reference] {k}/{spp} spp, {elapsed:.1f}s")
    ref, var, _ = render(scene, samplers, spp=spp, mis=True, seed=0, progress=progress)
    emit("[progress 2/2] compare")
    folder = Path(args.cycles).parent
    write_exr(folder / "reference.exr", ref)
    image = folder / "compare.png"
    write_side_by_side(image, ref, {("cycles", "spp"): cycles})
    result = {k: float(v) for k, v in metrics(cycles, ref).items()}
    mean_ref, mean_cyc = float(ref.mean()), float(cycles.mean())
    result.update(reference_noise=float(np.mean(var)), reference_spp=spp, cycles_spp=args.spp,
                  mean_reference=mean_ref, mean_cycles=mean_cyc, image=str(image),
                  reference=str(folder / "reference.exr"), cycles=str(args.cycles))
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
