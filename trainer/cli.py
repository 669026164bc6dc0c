"""python -m trainer train MANIFEST [--material NAME]... [--preset fast|balanced|paper] [--device cpu|cuda]
[--out DIR] [--threads N] [--no-progress]; `flowbsdf train` takes the same arguments (the parser is
bake.plumbing.job.add_train_arguments) and runs this in a subprocess.

Trains one flow per material of the manifest (or only the --material ones) and writes
OUT/models/<name>.flow.npz, where `flowbsdf bake/report/run --out OUT` look for it (--out is the
output folder, default out; torch-free: load with bake.core.flow.load_model). Checkpoints go to
OUT/models/<name>.train/ckpt/: rerunning the same command resumes an interrupted run. An --out
named models is that folder itself (what --out meant before: job.train_models_dir).

A material's `train` table in the manifest may set: preset, steps (Euler steps N),
seed, the training data's SOURCE_KEYS (theta_i: incident elevations in degrees to train on;
resolution and supersample of the ideal sampler's tables; pool: training samples pre-drawn;
phi_i_count: incident azimuths, anisotropic materials), and any trainer setting (see
trainer.train.PRESETS / COMMON).
"""
import argparse
import contextlib
import sys
from pathlib import Path

from bake.errors import FlowBSDFError, exit_code
from bake.plumbing.job import add_train_arguments, train_models_dir

SOURCE_KEYS = {"theta_i", "resolution", "pool", "supersample", "phi_i_count"}


def build_parser():
    p = argparse.ArgumentParser(prog="python -m trainer", description="FlowBSDF trainer (torch)")
    sub = p.add_subparsers(dest="command", required=True)
    add_train_arguments(sub.add_parser("train", help="train flow samplers for a manifest's materials"))
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)      # its one command: train
    return exit_code(lambda: cmd_train(args), "flowbsdf train", "interrupted (checkpoints kept; rerun to resume)")


def cmd_train(args):
    import numpy as np
    import torch

    from bake.plumbing.manifest import load_manifest

    from .sources import SLOPE_SHARE, SPECULAR_CONE_DEG, MaterialSource, choose_domain
    from .train import train

    if args.device == "cuda" and not torch.cuda.is_available():
        raise FlowBSDFError("--device cuda: torch sees no CUDA device")
    manifest_path = Path(args.manifest)
    manifest = load_manifest(manifest_path)
    if args.material:
        names = {m.name for m in manifest.materials}
        missing = [n for n in args.material if n not in names]
        if missing:
            raise FlowBSDFError(f"no material named {', '.join(map(repr, missing))} "
                                f"(have: {', '.join(sorted(names))})", manifest_path)
    log = lambda m: print(m, file=sys.stderr)  # noqa: E731
    materials = [m for m in manifest.select(None, log=log) if not args.material or m.name in args.material]
    out = train_models_dir(args.out, log)
    written = []
    for entry in materials:
        settings = dict(getattr(entry, "train", None) or {})
        preset = args.preset or settings.pop("preset", None) or "balanced"
        settings.pop("preset", None)
        source_kw = {k: settings.pop(k) for k in list(settings) if k in SOURCE_KEYS}
        if "theta_i" in source_kw:
            source_kw["theta_i"] = np.radians(np.asarray(source_kw["theta_i"], float))
        domain = getattr(entry, "domain", None) or "auto"
        material = entry.open()
        seed = settings.get("seed", 0)
        source = MaterialSource(material, "disk" if domain == "auto" else domain, seed=seed, **source_kw)
        extra = {}
        if domain == "auto":
            domain, share = choose_domain(source.sampler)
            extra["domain_choice"] = {"rule": f"slope if >= {SLOPE_SHARE} of f·cos within "
                                              f"{SPECULAR_CONE_DEG} deg of the specular half vector",
                                      "specular_share": round(share, 4)}
            print(f"[{entry.name}] domain auto -> {domain} ({share:.1%} of f·cos within "
                  f"{SPECULAR_CONE_DEG:g} deg of the specular direction)", file=sys.stderr)
        fingerprint = material.fingerprint()
        print(f"[{entry.name}] training ({domain}, preset {preset}) -> {out}", file=sys.stderr)
        with _torch_threads(torch, args.threads or (1 if preset in ("fast", "balanced") else None)):
            path = train(source, out / f"{entry.name}.train", preset=preset, domain=domain,
                         isotropic=material.isotropic, name=entry.name, device=args.device,
                         progress=not args.no_progress, log=log,
                         meta={"material": {"fingerprint": fingerprint, "kind": type(material).__name__},
                               "source": source.describe(), **extra},
                         **settings)
        final = out / path.name
        out.mkdir(parents=True, exist_ok=True)
        path.replace(final)
        written.append(final)
        print(f"[{entry.name}] model: {final}", file=sys.stderr)
    for p in written:
        print(p)
    return 0


@contextlib.contextmanager
def _torch_threads(torch, n):
    """torch's CPU threads set to n (None: unchanged) for the block, restored after it. fast and
    balanced train on one unless asked: their nets are small and their steps overhead-bound
    (chm_mint balanced alone on 2 cores: 135 s on one thread, 186 s on two)."""
    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
