"""Issue 24 item 4: what each Cycles back end of the Learned BSDF costs per sample, and where
the OSL back end's time goes, against a Principled BSDF at equal spp.

One material (the lights acceptance's draft tables of --material), the acceptance's sphere
(64 x 64, box filter), in three scenes that switch the OSL shader's parts on one by one:
  constant   a constant world: the tables' sample and the portal only (no map, no lamps);
  hdri       the acceptance's "sunny" image world: + the world's next-event estimation (map
             sample, shadow ray, the tables' pdf for MIS) and its control variate;
  studio     two lamps (area + sphere) and a dim constant world: + lamp next-event estimation;
  sky        (where scripts/lights_acceptance.py has rendered it) its Sky Texture image: a small
             sun's next-event estimation.
Per scene and back end (Principled, fit, SVM, OSL): CPU time of this process (Cycles'
threads) per spp, from two sample counts (each render's fixed cost, scene sync and shader
compilation, cancels), the best of --repeat interleaved rounds (the machine is shared).

    .venv/bin/python scripts/backend_cost.py [--material paper_white] [--repeat 2]
"""
import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import cycles_acceptance as ca  # noqa: E402
import cycles_scenes as cs  # noqa: E402
import lights_acceptance as la  # noqa: E402
from bake.export.closure_fit import load_fit  # noqa: E402
from bake.export.derived import ensure_fit  # noqa: E402

KINDS = ("principled", "fit", "svm", "osl")


def setups():
    hdri = la.OUT / "env_sunny.exr"
    if not hdri.is_file():
        ca.make_env(hdri, "sunny")
    sky = la.OUT / "sky_2048x1024.exr"
    scenes = la.setups(hdri, sky)

    def constant(sc):
        cs.set_world(sc, color=(0.5, 0.5, 0.5))
    out = {"constant": constant, "hdri": scenes["hdri"], "studio": scenes["studio"]}
    if sky.is_file():       # made by scripts/lights_acceptance.py
        out["sky"] = scenes["sky"]
    return out


def per_spp(kind, name, tables, fit, setup, lo, hi):
    sc, _ = ca.cycles_scene(kind, name, tables, None, 64, lo, fit=fit, setup=setup, native=True)
    cs.render(sc)                               # warm: compilation, world map, textures
    return cs.seconds_per_spp(sc, lo, hi, clock=time.process_time)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", default="paper_white")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--lo", type=int, default=16)
    ap.add_argument("--hi", type=int, default=96)
    args = ap.parse_args(argv)
    tables = la.draft_tables(args.material, la.OUT / "tables")
    fit = load_fit(ensure_fit(tables))
    scenes = setups()
    best = {}
    for _ in range(args.repeat):
        for scene, setup in scenes.items():
            for kind in KINDS:
                t = per_spp(kind, args.material, tables, fit, setup, args.lo, args.hi)
                best[scene, kind] = min(best.get((scene, kind), float("inf")), t)
    print(f"{args.material}, 64 x 64, CPU ms per spp (all threads) from {args.lo} and {args.hi} spp, "
          f"best of {args.repeat}")
    print("| scene | " + " | ".join(KINDS) + " | fit / Pr | SVM / Pr | OSL / Pr |")
    print("|---" * (len(KINDS) + 4) + "|")
    for scene in scenes:
        p = best[scene, "principled"]
        print(f"| {scene} | " + " | ".join(f"{1e3 * best[scene, k]:.2f}" for k in KINDS)
              + " | " + " | ".join(f"{best[scene, k] / p:.2f}" for k in ("fit", "svm", "osl")) + " |")
    base = best["constant", "osl"]
    print(f"OSL: the world's next-event estimation adds {1e3 * (best['hdri', 'osl'] - base):.2f} ms/spp "
          f"({best['hdri', 'osl'] / base:.2f}x the portal-only shader), two lamps "
          f"{1e3 * (best['studio', 'osl'] - base):.2f} ms/spp ({best['studio', 'osl'] / base:.2f}x)")


if __name__ == "__main__":
    main()
