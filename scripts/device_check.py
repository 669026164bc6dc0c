"""Issue 18's device check: the SVM back end renders the same image on every Cycles device.

Renders a learned plastic sphere under a soft environment with the SVM graph (OSL off) on
the CPU and on each GPU Cycles finds (CUDA, OptiX, HIP, Metal, oneAPI), over several seeds,
and compares the GPU images with the CPU's within Monte Carlo error (per-pixel z-scores and
the sphere's mean). Without a GPU it says so and exits 0 (nothing to compare).

    .venv/bin/python scripts/device_check.py [--spp 64] [--seeds 4] [--size 32]
Exit code 1 when a device disagrees.
"""
import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import cycles_scenes as cs  # noqa: E402

GPU_TYPES = ("OPTIX", "CUDA", "HIP", "METAL", "ONEAPI")


def gpu_devices():
    """{device type: [device names]} of the GPUs Cycles can use here."""
    import bpy
    prefs = bpy.context.preferences.addons["cycles"].preferences
    found = {}
    for kind in GPU_TYPES:
        try:
            prefs.compute_device_type = kind
        except TypeError:           # not a device type of this build (e.g. Metal off macOS)
            continue
        prefs.get_devices()
        names = [d.name for d in prefs.devices if d.type == kind]
        if names:
            found[kind] = names
    return found


def render_on(kind, tables, spp, seeds, size):
    import bpy
    from blender_addon.render import node as lb
    sc = cs.reset(size, size, spp=spp, osl=False)
    sc.cycles.pixel_filter_type = 'BOX'
    cs.ortho_camera(sc, scale=2.2)
    cs.set_world(sc, (0.9, 0.95, 1.0))
    mat = bpy.data.materials.new("m")
    lb.assign_learned_bsdf(mat, tables.stem, tables)
    lb.set_backend(sc, "svm")
    cs.add_sphere(sc, mat, segments=64, rings=32)
    prefs = bpy.context.preferences.addons["cycles"].preferences
    if kind == "CPU":
        sc.cycles.device = 'CPU'
    else:
        prefs.compute_device_type = kind
        prefs.get_devices()
        for d in prefs.devices:
            d.use = d.type == kind
        sc.cycles.device = 'GPU'
    return cs.render_seeds(sc, seeds)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--size", type=int, default=32)
    args = ap.parse_args(argv)
    gpus = gpu_devices()
    if not gpus:
        print("device_check: no GPU that Cycles can use on this machine (looked for "
              f"{', '.join(GPU_TYPES)}): nothing to compare; skipped")
        return 0
    from blender_addon.render import node as lb
    lb.register()
    tables = Path(tempfile.mkdtemp(prefix="flowbsdf_device_")) / "plastic.exr"
    cs.small_tables({"kind": "analytic", "model": "plastic", "albedo": [0.7, 0.1, 0.08], "alpha": 0.12},
                    "plastic", tables.parent)
    cpu = render_on("CPU", tables, args.spp, args.seeds, args.size)
    failed = False
    for kind, names in gpus.items():
        gpu = render_on(kind, tables, args.spp, args.seeds, args.size)
        var = cpu.var(0, ddof=1) / args.seeds + gpu.var(0, ddof=1) / args.seeds + 1e-12
        z = (gpu.mean(0) - cpu.mean(0)) / np.sqrt(var)
        rms = float(np.sqrt(np.mean(z ** 2)))
        rel = float(gpu.mean() / cpu.mean() - 1)
        ok = rms < 2.0 and abs(rel) < 0.01
        failed |= not ok
        print(f"{kind} ({', '.join(names)}) vs CPU: rms z {rms:.2f}, mean {rel:+.4%} -> {'same' if ok else 'DIFFERENT'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
