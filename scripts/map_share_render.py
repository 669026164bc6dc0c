"""The world map's share of portal directions, measured in renders (blender_addon/render/world.py
SHARE_GLOSSY, SHARE_MATTE): per share, a back end's per-sample variance and CPU time per spp on
the lights acceptance's sphere, and their product (what an equal-time MSE follows).

Per share (world.SHARE patched, the per-material share off: the share is the one given), the
material's tables in a folder of their own (the world maps beside them are made per share),
--spp x --seeds renders against scripts/lights_acceptance.py's tracer reference of the scene
(run that first), and the CPU time per spp from --lo and --hi spp (best of two, persistent data).

    .venv/bin/python scripts/map_share_render.py paper_white --scene hdri --shares 0.35,0.5,0.65
        [--backend osl|svm] [--spp 96] [--seeds 8]
"""
import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import cycles_acceptance as ca  # noqa: E402
import cycles_scenes as cs  # noqa: E402
import lights_acceptance as la  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name")
    ap.add_argument("--scene", default="hdri", choices=("hdri", "sky", "studio"))
    ap.add_argument("--shares", default="0.35,0.5,0.65")
    ap.add_argument("--backend", default="osl", choices=("osl", "svm"))
    ap.add_argument("--spp", type=int, default=96)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--lo", type=int, default=16)
    ap.add_argument("--hi", type=int, default=144)
    args = ap.parse_args(argv)
    from blender_addon.render import world as bw
    ref_path = la.OUT / f"{args.scene}_{args.name}" / "tracer_baked.npy"
    if not ref_path.is_file():
        sys.exit(f"no reference: run scripts/lights_acceptance.py {args.name} --scenes {args.scene} first")
    ref, ref_var, _ = np.load(ref_path)
    tables = la.draft_tables(args.name, la.OUT / "tables")
    setup = la.setups(la.OUT / "env_sunny.exr", la.OUT / f"sky_{2048}x{1024}.exr")[args.scene]
    inner = la.inner_mask(64)
    bw.material_share = lambda inputs, matte: inputs          # the share as given, for every material
    print(f"{args.scene} {args.name} {args.backend}, {args.spp} spp x {args.seeds}:")
    print("| share | per-sample variance | CPU ms/spp | product | mean rel +- SE |")
    print("|---|---|---|---|---|")
    for share in (float(s) for s in args.shares.split(",")):
        folder = la.OUT / "share_sweep" / f"{share:.3f}"
        folder.mkdir(parents=True, exist_ok=True)
        mine = folder / tables.name
        for f in tables.parent.glob(f"{tables.stem}.*"):         # fit and exports: not rebuilt
            if not (folder / f.name).exists():
                shutil.copy(f, folder / f.name)
        shutil.copy(tables, mine)
        bw.SHARE = share
        sc, _ = ca.cycles_scene(args.backend, args.name, mine, None, 64, args.spp, setup=setup, native=True)
        sc.render.use_persistent_data = True
        cs.render(sc)
        t = min(cs.seconds_per_spp(sc, args.lo, args.hi, clock=time.process_time) for _ in range(2))
        sc.cycles.samples = args.spp
        imgs = []
        for seed in range(args.seeds):
            sc.cycles.seed = seed
            imgs.append(cs.render(sc))
        e = la.errors(np.array(imgs), ref, ref_var, inner)
        var = e["noise"] * args.spp
        print(f"| {share:.2f} | {var:.4f} | {1e3 * t:.2f} | {var * 1e3 * t:.4f} | {e['rel']:+.4f} +- {e['rel_se']:.4f} |",
              flush=True)


if __name__ == "__main__":
    main()
