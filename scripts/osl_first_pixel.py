"""Issue 52 item 2, the wait before the first pixel: with Cycles' OSL on, every render first
compiles each material's OSL shader group (OSL's runtime optimizer, then LLVM's optimizer and JIT;
again at every render unless Persistent Data is on). This measures those CPU seconds per material.

Cases, each in a fresh Blender process (one render of 16 x 16 px at 1 spp: its sampling is ~0 s, so
the render's process CPU is the compile plus Cycles' scene sync), a sphere per material:
  principled   one Principled BSDF (the reference: a Cycles node's compile)
  learned1     one Learned BSDF (OSL back end, the default bake of --tables: no carried blend)
  learned2     two Learned BSDFs (two materials bound to one table file: two shader groups)
  carried1     one Learned BSDF with the carried blend (the tables' intervals marked as carrying
               and their carry texture made from --rgl, once, in --work)
each with 0 and 1 point lamps (--lamps; the shader compiles its lamp code only where a lamp renders).
--shader LABEL=CHECKOUT (repeatable) runs the Learned BSDF cases with another checkout's shader
(its blender_addon/render/osl/) beside this one's ("this"): before/after of a cut.

Printed per case and shader, the best (least) of --repeat interleaved rounds (the machine is
shared): the render's process CPU (s), per Learned BSDF material (case - principled at the same
lamps) / materials, and OSL's own statistics (OSL_OPTIONS=statistics:level=1): "Runtime
optimization cost" (its optimizer + LLVM, s; wall clock of OSL's timer, shown for the split) and
the ops left after its optimizer (all groups: the world's and the fit's nodes too).

    .venv/bin/python scripts/osl_first_pixel.py [--shader before=/work/main] [--repeat 2]
"""
import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = ("principled", "learned1", "learned2", "carried1")
TABLES = Path("/work/s44/ref/out/tables/military.exr")
RGL = ROOT.parent / "shared" / "data" / "rgl" / "cm_military_green_rgb.bsdf"


def carried_tables(tables, rgl, work):
    """A copy of `tables` whose intervals all carry, with its carry texture (made once)."""
    from bake.core.table_files import open_tables
    from bake.export.derived import ensure_carry_export
    from bake.materials import open_material
    out = Path(work) / f"{tables.stem}_carried.exr"
    if not out.is_file():
        tab = open_tables(tables)
        tab.meta["carried"] = [True] * (len(tab.meta["theta_bins"]) - 1)
        out.parent.mkdir(parents=True, exist_ok=True)
        tab.save(out)
    ensure_carry_export(out, open_material(rgl))
    return out


def child(case, lamp, shader, tables):
    """One case in this (fresh) process: prints {"cpu": s} as a JSON line."""
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "tests"))
    import bpy
    import cycles_scenes as cs
    from blender_addon.render import node as lb, osl_script
    if shader:
        osl_script.OSL_SOURCE = Path(shader) / "blender_addon" / "render" / "osl" / "learned_bsdf.osl"
    sc = cs.reset(16, 16, spp=1, osl=True, threads=2)
    lb.register()
    count = 2 if case == "learned2" else 1
    for i in range(count):
        mat = bpy.data.materials.new(f"m{i}")
        if case == "principled":
            mat.use_nodes = True
        else:
            node = lb.assign_learned_bsdf(mat, f"m{i}", Path(tables))
        cs.add_sphere(sc, mat, radius=0.3, segments=16, rings=8).location = (i - count / 2, 0, 0)
    cs.set_world(sc, color=(0.3, 0.3, 0.3))
    cs.persp_camera(sc)
    for k in range(lamp):
        cs.add_lamp(sc, 'POINT', (1.0 - 0.3 * k, -1.0, 2.0), energy=100.0)
    lb.set_backend(sc, "osl")
    if case != "principled":
        want = "OSL, carried blend, exact" if case == "carried1" else "OSL, exact"
        assert lb.node_status(node, sc).startswith(want), lb.node_status(node, sc)
    c0 = time.process_time()
    cs.render(sc)
    print(json.dumps({"cpu": time.process_time() - c0}), flush=True)


def run(case, lamp, shader, tables):
    cmd = [sys.executable, __file__, "--child", case, "--lamp", str(int(lamp)), "--tables", str(tables)]
    if shader:
        cmd += ["--child-shader", shader]
    env = dict(os.environ, OSL_OPTIONS="statistics:level=1")
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    text = out.stdout + out.stderr
    line = next((x for x in text.splitlines() if x.startswith('{"cpu"')), None)
    if out.returncode or line is None:
        raise RuntimeError(f"{case} lamp={lamp} shader={shader}: failed\n{text[-3000:]}")
    cost = re.findall(r"Runtime optimization cost: ([\d.]+)s", text)
    ops = re.findall(r"Optimized \d+ ops to (\d+)", text)
    return {"cpu": json.loads(line)["cpu"], "osl": float(cost[-1]) if cost else float("nan"),
            "ops": int(ops[-1]) if ops else -1}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--child", choices=CASES)
    ap.add_argument("--lamp", type=int, default=0)
    ap.add_argument("--child-shader", default="")
    ap.add_argument("--tables", default=str(TABLES))
    ap.add_argument("--rgl", default=str(RGL))
    ap.add_argument("--work", default="/tmp/flowbsdf_first_pixel")
    ap.add_argument("--shader", action="append", default=[], help="LABEL=CHECKOUT")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--lamps", default="0,1", help="numbers of point lamps, one case each")
    ap.add_argument("--repeat", type=int, default=2)
    a = ap.parse_args()
    if a.child:
        return child(a.child, a.lamp, a.child_shader, a.tables)
    sys.path.insert(0, str(ROOT))
    tables = Path(a.tables)
    cases = a.cases.split(",")
    carried = carried_tables(tables, Path(a.rgl), a.work) if "carried1" in cases else None
    shaders = [("this", "")] + [tuple(s.split("=", 1)) for s in a.shader]
    lamps = [int(x) for x in a.lamps.split(",")]
    jobs = [(c, lamp, label, path) for lamp in lamps for c in cases
            for label, path in (shaders if c != "principled" else shaders[:1])]
    best = {}
    for r in range(a.repeat):
        for c, lamp, label, path in jobs:
            res = run(c, lamp, path, carried if c == "carried1" else tables)
            key = (c, lamp, label)
            print(f"round {r}: {c:10s} lamps={lamp} {label:8s} cpu {res['cpu']:6.2f} s, OSL {res['osl']:5.2f} s, "
                  f"ops {res['ops']}", flush=True)
            best[key] = {k: min(best.get(key, res)[k], res[k]) for k in res}
    print("\nbest of rounds: render CPU (s), per Learned BSDF material ((case - principled) / materials), "
          "OSL runtime optimization (s, its timer), ops after OSL's optimizer")
    for c, lamp, label, _ in jobs:
        b = best[(c, lamp, label)]
        n = 2 if c == "learned2" else 1
        per = (b["cpu"] - best[("principled", lamp, "this")]["cpu"]) / n if c != "principled" else float("nan")
        print(f"{c:10s} lamps={lamp} {label:8s} cpu {b['cpu']:6.2f}  per material {per:6.2f}  "
              f"OSL {b['osl']:5.2f}  ops {b['ops']}")


if __name__ == "__main__":
    main()
