"""Issue 24 item 5: `flowbsdf train --device cuda` trains as good a flow as the CPU does.

Trains one material of the manifest with the CPU and with each --devices entry (same preset,
same seed, its own output folder), then measures each model's relative variance
Var[f cos / pdf] / E[f cos / pdf]^2 against the material at a few incident elevations
(bake.core.metrics.relative_variance, one fixed sample set for all models) and prints them
side by side. A device whose rv is more than --tolerance times the CPU's (plus 0.01) at some
elevation fails (exit 1): a GPU run is not bit-identical to the CPU's, but must be as good.
A device torch cannot use is skipped with the reason (exit 0: nothing to compare); `--devices
cpu` runs the whole check on this machine (two CPU runs of the same seed: equal rv).

    .venv/bin/python scripts/train_device_check.py [--manifest manifest.toml] [--material red_plastic]
        [--preset fast] [--devices cuda] [--thetas 0,30,60,75,85] [--samples 65536] [--out DIR]
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import trainer  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)


def unavailable(device):
    """Why torch cannot train on `device` here (None when it can)."""
    import torch
    if device == "cpu":
        return None
    if device == "cuda":
        return None if torch.cuda.is_available() else "torch sees no CUDA device (torch.cuda.is_available() is False)"
    return f"unknown device {device!r} (flowbsdf train takes cpu or cuda)"


def train_on(device, manifest, material, preset, out):
    from trainer.cli import main as train_main
    t0 = time.perf_counter()
    code = train_main(["train", str(manifest), "--material", material, "--preset", preset,
                       "--device", device, "--out", str(out), "--no-progress"])
    if code != 0:
        raise SystemExit(f"train_device_check: training on {device} failed (exit {code})")
    return out / "models" / f"{material}.flow.npz", time.perf_counter() - t0     # --out: the output folder


def rv_table(model_path, material, thetas, samples):
    from bake.core.flow import load_model
    from bake.maths.geometry import incident
    from bake.core.metrics import relative_variance
    model = load_model(model_path)
    return [relative_variance(material, model, incident(t), n=samples, seed=1)[0] for t in thetas]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--manifest", default=str(ROOT / "manifest.toml"))
    ap.add_argument("--material", default="red_plastic")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--devices", default="cuda", help="comma-separated: cuda, cpu")
    ap.add_argument("--thetas", default="0,30,60,75,85")
    ap.add_argument("--samples", type=int, default=1 << 16)
    ap.add_argument("--tolerance", type=float, default=1.5)
    ap.add_argument("--out", default=None, help="folder for the models (default: a temporary one)")
    args = ap.parse_args(argv)
    devices = [d.strip() for d in args.devices.split(",") if d.strip()]
    usable = []
    for d in devices:
        reason = unavailable(d)
        if reason:
            print(f"train_device_check: {d}: skipped: {reason}")
        else:
            usable.append(d)
    if not usable:
        print("train_device_check: no device to compare with the CPU on this machine: nothing checked")
        return 0
    from bake.plumbing.manifest import load_manifest
    entry = next((m for m in load_manifest(Path(args.manifest)).materials if m.name == args.material), None)
    if entry is None:
        raise SystemExit(f"train_device_check: no material {args.material!r} in {args.manifest}")
    material = entry.open()
    thetas = [float(t) for t in args.thetas.split(",")]
    out = Path(args.out or tempfile.mkdtemp(prefix="flowbsdf_train_device_"))
    rows = {}
    for label, device in [("cpu (reference)", "cpu")] + [(d, d) for d in usable]:
        model, secs = train_on(device, args.manifest, args.material, args.preset, out / label.replace(" ", "_"))
        rows[label] = (rv_table(model, material, thetas, args.samples), secs)
    ref = rows["cpu (reference)"][0]
    print(f"{args.material}, preset {args.preset}: rv of each model ({args.samples} samples per elevation)")
    print("| device | train s | " + " | ".join(f"rv {t:g} deg" for t in thetas) + " | worst rv / cpu |")
    print("|---" * (len(thetas) + 3) + "|")
    failed = False
    for label, (rv, secs) in rows.items():
        worst = max(r / max(c, 1e-12) for r, c in zip(rv, ref))
        bad = any(r > args.tolerance * c + 0.01 for r, c in zip(rv, ref))
        failed |= bad
        print(f"| {label} | {secs:.0f} | " + " | ".join(f"{r:.4f}" for r in rv) + f" | {worst:.2f}"
              + (" WORSE |" if bad else " |"))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
