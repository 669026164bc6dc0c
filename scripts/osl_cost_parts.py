"""Issue 52 item 2: where the OSL back end's time per sample goes. The node's OSL shader
(blender_addon/render/osl/) compiled with parts replaced, side by side with Principled (OSL off and on),
per scene, on a default bake (cm_military_green's by default).

Variants (the shader's text patched while the node compiles it; some render a different image:
they measure cost, not a look):
  principled   Principled BSDF, OSL off (the reference of every ratio)
  pr_osl       Principled BSDF with OSL on (OSL's own cost on a Cycles closure)
  const        the node's Script node returning a constant Ray Portal toward the mirror direction
               (OSL's shader overhead + a portal bounce)
  floor1       the tables' header read + N texture() calls of one texel (N: --fetches, default the
               full shader's mean count per shading point in the scene, counted) + the constant
               portal: the texture system's per-call floor, cache hot
  floorR       the same with the N texels spread at random over the texture (cache misses)
  nonee        the full shader without lamp and image-world next-event estimation (the mixture stays)
  osl          the full shader as it is
  before       the full shader of another checkout (--before): a cut's saving
               (with --before-texture its OSL texture, when the layouts differ); --at LABEL=CHECKOUT[=TEXTURE]
               (repeatable) adds such a variant named LABEL
One or two Cycles threads (--threads). Per scene (constant world, the acceptance's HDRI, studio
lamps) and variant: CPU time of this process (and the wall clock) per spp while Cycles samples (its
"Sample k/N" statuses: OSL's JIT at every render, seconds that vary by seconds, is left out), the
best of --repeat interleaved rounds (the machine is shared). --count: texture() calls per shading
point of the full shader (every call printed by OSL's printf, one render at 1 spp).

    .venv/bin/python scripts/osl_cost_parts.py [--tables T.exr] [--variants osl,before] [--threads 1]
"""
import argparse
import contextlib
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import backend_cost  # noqa: E402
import cycles_acceptance as ca  # noqa: E402
import cycles_scenes as cs  # noqa: E402
from bake.export.closure_fit import load_fit  # noqa: E402
from bake.export.derived import ensure_fit  # noqa: E402

VARIANTS = ("principled", "pr_osl", "const", "floor1", "floorR", "nonee", "osl")
BODY = "#else\n    if (!read_header(Tables"        # the shader body (not the probe's)
PORTAL = """
    vector wi = normalize(I);
    normal n = normalize(N);
    float c = dot(wi, n);
    if (c > 0.0)
        BSDF = color(0.5 * (1.0 + ACC)) * ray_portal_bsdf(P, 2.0 * c * n - wi);
"""


def _body(src, body):
    i = src.index(BODY) + len("#else\n")
    j = src.rindex("#endif")
    return src[:i] + body + src[j:]


def _floor(src, n, spread):
    at = ("int hk = hash(h, k); int x = abs(hk) % int(tab.W); int y = abs(hash(hk, 7)) % int(tab.H);" if spread
          else "int x = 3; int y = 5;")
    return _body(src, f"""
    if (!read_header(Tables, tab)) {{
        BSDF = Fallback;
        return;
    }}
    int h = hash(P);
    float acc = 0.0;
    for (int k = 0; k < {n}; k++) {{
        {at}
        acc += fetch1(Tables, tab.W, tab.H, x, y);
    }}
""" + PORTAL.replace("ACC", "1e-30 * acc"))


def _nonee(src):
    lamps = "        LAMP_AT(4); LAMP_AT(5); LAMP_AT(6); LAMP_AT(7);\n"
    env = 'int env_nee = EnvImage != "" && has_bright;'
    assert src.count(lamps) == 1 and src.count(env) == 1
    src = src.replace(lamps, lamps + "        for (int k = 0; k < LAMP_SLOTS; k++) lamps[k].kind = 0;\n")
    return src.replace(env, "int env_nee = 0;")


def _counted(src):
    """Every texture() call prints T (a line before each statement that calls it), each shading point S."""
    lines = src.split("\n")
    out = []
    for ln in lines:
        if re.search(r"(?<![\w.])texture\(", ln) and not ln.lstrip().startswith("//"):
            out.append('    printf("T\\n");')
        out.append(ln)
    src = "\n".join(out)
    return src.replace(BODY, '#else\n    printf("S\\n");\n' + BODY[len("#else\n"):], 1)


def source(variant, fetches=0, before=None, at=None):
    from blender_addon.render import osl_script
    src = osl_script.shader_source()
    if variant == "const":
        return _body(src, PORTAL.replace("ACC", "0.0"))
    if variant in ("floor1", "floorR"):
        return _floor(src, fetches, variant == "floorR")
    if variant == "nonee":
        return _nonee(src)
    if variant == "count":
        return _counted(src)
    if variant == "before":
        return _before_source(before)
    if at and variant in at:
        return _before_source(at[variant][0])
    return src


def _before_source(path):
    """The shader of another checkout's blender_addon/render/osl (blender_addon/osl before issue 53's
    split; headers inlined as osl_script.shader_source does)."""
    folder = next((f for f in (Path(path) / "blender_addon" / "render" / "osl", Path(path) / "blender_addon" / "osl")
                   if f.is_dir()), Path(path) / "blender_addon" / "render" / "osl")
    return re.sub(r'^#include "([^"]+)"$',
                  lambda m: (folder / m.group(1)).read_text() if (folder / m.group(1)).is_file() else m.group(0),
                  (folder / "learned_bsdf.osl").read_text(), flags=re.M)


@contextlib.contextmanager
def patched(text, texture=None):
    """The node compiling `text` as its shader (and binding the OSL texture `texture`, when given)
    while the scene is built and rendered (the node refreshes its texture at every render)."""
    from blender_addon.render import derived, osl_script
    saved, saved_texture = osl_script.shader_source, derived.osl_texture
    osl_script.shader_source = lambda probe=False: text if not probe else saved(probe)
    if texture:
        derived.osl_texture = lambda tables_path: str(texture)
    try:
        yield
    finally:
        osl_script.shader_source, derived.osl_texture = saved, saved_texture


def scene_for(variant, tables, fit, setup, size, spp, threads):
    kind = "principled" if variant in ("principled", "pr_osl") else "osl"
    sc, _ = ca.cycles_scene(kind, tables.stem, tables, None, size, spp, fit=fit, setup=setup,
                            native=variant != "pr_osl")
    sc.render.threads = threads
    return sc


_STATS = []


def _stats(*args):
    """render_stats handler: (CPU time of this process, wall clock, k) at each "Sample k/N" status."""
    m = re.search(r"Sample (\d+)/(\d+)", str(args[0]) if args else "")
    if m:
        _STATS.append((time.process_time(), time.perf_counter(), int(m.group(1))))


def per_spp(sc, spp, inner):
    """(CPU, wall) seconds per spp of the fastest of `inner` renders at `spp`: from Cycles' first
    sample status past sample 0 to its last, so neither the shaders' compilation (OSL's JIT runs
    at every render: seconds, varying by seconds) nor the first sample's texture loading counts."""
    import bpy
    if _stats not in bpy.app.handlers.render_stats:        # (scene builds load factory settings)
        bpy.app.handlers.render_stats.append(_stats)
    sc.cycles.samples = spp
    best = (float("inf"), float("inf"))
    for _ in range(inner):
        _STATS.clear()
        cs.render(sc)
        first = next((s for s in _STATS if s[2] >= 1), None)
        last = max(_STATS, key=lambda s: s[2], default=None)
        if first is None or last[2] <= first[2]:
            raise RuntimeError(f"no sample statuses from the render: {_STATS}")
        n = last[2] - first[2]
        best = tuple(min(b, (x1 - x0) / n) for b, x0, x1 in zip(best, first[:2], last[:2]))
    return best


def count_calls(tables, fit, scenes, size):
    """{scene: (shading points, texture() calls, gettextureinfo() calls)} of the full shader, one
    render at 1 spp on one thread in a child process (OSL's printf writes to its stdout)."""
    out = {}
    for scene in scenes:
        with tempfile.TemporaryFile("w+") as log:
            subprocess.run([sys.executable, __file__, "--tables", str(tables), "--size", str(size),
                            "--count-child", scene], stdout=log, stderr=subprocess.DEVNULL, check=True)
            log.seek(0)
            lines = [ln.strip() for ln in log]
        out[scene] = tuple(lines.count(c) for c in "ST")
    return out


def count_child(tables, scene, size):
    fit = load_fit(ensure_fit(tables))
    setup = backend_cost.setups()[scene]
    with patched(source("count")):
        sc = scene_for("count", tables, fit, setup, size, 1, 1)
        sys.stdout.flush()
        cs.render(sc)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tables", type=Path, required=True,
                    help="a default bake's table file (its carry texture beside it renders the carried blend: "
                         "pass a copy without it for the fixed cells)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--scenes", default="constant,hdri,studio")
    ap.add_argument("--threads", default="1", help="comma-separated Cycles thread counts")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--inner", type=int, default=1, help="renders per round (the fastest counts)")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--fetches", type=int, default=0, help="floor variants' texture() calls (0: counted)")
    ap.add_argument("--before", help="another checkout, for the variant `before`")
    ap.add_argument("--before-texture", help="the OSL texture the before variant binds (when its layout differs)")
    ap.add_argument("--at", action="append", default=[], help="LABEL=CHECKOUT[=TEXTURE]: a variant of that checkout")
    ap.add_argument("--count", action="store_true", help="count the calls only")
    ap.add_argument("--count-child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if "before" in args.variants.split(",") and not args.before:
        ap.error("the variant `before` needs --before CHECKOUT")
    if args.count_child:
        return count_child(args.tables, args.count_child, args.size)
    scenes = {k: v for k, v in backend_cost.setups().items() if k in args.scenes.split(",")}
    variants = args.variants.split(",")
    counts = count_calls(args.tables, None, scenes, 16) if args.count or (
        not args.fetches and any(v.startswith("floor") for v in variants)) else {}
    for scene, (s, t) in counts.items():
        print(f"count {scene}: {s} shading points, {t / max(s, 1):.2f} texture() calls per shading point",
              flush=True)
    if args.count:
        return
    fit = load_fit(ensure_fit(args.tables))
    threads = [int(t) for t in args.threads.split(",")]
    at = {}
    for spec in args.at:
        label, checkout, *texture = spec.split("=")
        at[label] = (checkout, texture[0] if texture else None)
    best = {}
    for r in range(args.repeat):
        for scene, setup in scenes.items():
            n = args.fetches or round(counts[scene][1] / max(counts[scene][0], 1)) if counts or args.fetches else 0
            for th in threads:
                for v in variants:
                    texture = args.before_texture if v == "before" else at[v][1] if v in at else None
                    with patched(source(v, n, args.before, at), texture):
                        sc = scene_for(v, args.tables, fit, setup, args.size, args.spp, th)
                        t = per_spp(sc, args.spp, args.inner)
                    key = (scene, th, v)
                    best[key] = tuple(min(a, b) for a, b in zip(best.get(key, (1e9, 1e9)), t))
                    print(f"round {r} {scene} {th}t {v}: cpu {1e3 * t[0]:.3f} wall {1e3 * t[1]:.3f} ms/spp "
                          f"(load {os.getloadavg()[0]:.1f})", flush=True)
    print(f"\n{args.tables.stem}, {args.size} px sphere, ms per spp of {args.spp} spp renders (Cycles' "
          f"sampling alone), best of {args.repeat} interleaved rounds; ratio to Principled "
          f"(OSL off) of the same scene and threads; CPU of this process (wall in brackets)")
    print("| variant | " + " | ".join(f"{s} {th}t" for s in scenes for th in threads) + " |")
    print("|---" * (len(scenes) * len(threads) + 1) + "|")
    for v in variants:
        cells = []
        for s in scenes:
            for th in threads:
                t, p = best[s, th, v], best.get((s, th, "principled"), (float("nan"),) * 2)
                cells.append(f"{1e3 * t[0]:.2f} ({t[0] / p[0]:.2f}x) [{t[1] / p[1]:.2f}x]")
        print(f"| {v} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
