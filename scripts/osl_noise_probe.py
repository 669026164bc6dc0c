"""Where the OSL back end's noise comes from, in the scenes of scripts/lights_acceptance.py
(run that first: it makes the draft tables, the environment images and the world maps).

  roulette   A copy of the shader (in memory; the add-on's file is untouched) that returns, per
             camera sample, (drawn by the world/sun technique, that portal weight under 2x
             Cycles' closure cutoff so Russian-rouletted, its keep probability) as emission:
             how often the world's light arrives through a rouletted closure (each kept one
             amplified 1/keep times).
  lamps      Per-sample variance (per-pixel variance over seeds x spp, mean over the sphere) of
             OSL, a Diffuse BSDF (the Principled fit's base colour) and the fit in the studio with
             the area lamp alone, the point lamp alone, both, and the dim world alone.

    .venv/bin/python scripts/osl_noise_probe.py roulette [material] [scenes...]
    .venv/bin/python scripts/osl_noise_probe.py lamps [material]
"""
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import cycles_acceptance as ca  # noqa: E402
import cycles_scenes as cs  # noqa: E402
import lights_acceptance as la  # noqa: E402
from bake.export.closure_fit import load_fit  # noqa: E402
from bake.export.derived import ensure_fit  # noqa: E402

N = 32


def _case(name):
    tp = la.OUT / "tables" / f"{name}.exr"
    return tp, load_fit(ensure_fit(tp))


def roulette(name="cm_military_green", scenes=("sky", "truesky", "hdri")):
    import bpy
    import cycles.osl
    from blender_addon.render import node as lb, osl_script
    setups = la.setups(la.OUT / "env_sunny.exr", sorted(la.OUT.glob("sky_*.exr"))[-1])
    src = osl_script.shader_source()
    marker = "        w_portal = fcos / q;\n"
    if src.count(marker) != 1:
        raise RuntimeError("the shader changed: no single 'w_portal = fcos / q;' to probe after")
    src = src.replace(marker, marker + """    {
        int from_world = u1 < c_sun + c_world;
        float swp = abs(mean(w_portal));
        int live = nonzero(w_portal);
        int rl = live && swp < 2.0 * CUTOFF;
        BSDF = emission() * color(from_world && live, from_world && rl, from_world && rl ? swp / (2.0 * CUTOFF) : 0.0);
        return;
    }
""")
    tp, fit = _case(name)
    _, _, inner = cs.sphere_view_persp(N, N, ca.DISTANCE, ca.FOV)
    for scene in scenes:
        lb.register()
        sc, mat = ca.cycles_scene("osl", name, tp, None, N, 64, fit=fit, setup=setups[scene], native=True)
        lb.sync(sc, refresh=True)
        script = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeGroup").node_tree.nodes[osl_script.SCRIPT]
        lb.unregister()         # nothing may rebuild the node before the render
        text = bpy.data.texts.new("flowbsdf_probe.osl")
        text.from_string(src)
        with osl_script._own_tempdir():
            script.script = text
            if not cycles.osl.update_script_node(script, osl_script._report):
                raise RuntimeError("probe shader did not compile")
        r, g, b = cs.render(sc).astype(float)[inner].T
        print(f"[roulette] {scene} {name}: world/sun-technique samples {r.mean():.3f} of the camera samples; "
              f"rouletted {g.sum() / max(r.sum(), 1e-12):.1%} of them, mean keep probability "
              f"{b.sum() / max(g.sum(), 1e-12):.3f}; pixels with over half of them rouletted "
              f"{np.mean(g > 0.5 * r):.1%}", flush=True)


def lamps(name="paper_white", spp=64, seeds=4):
    tp, fit = _case(name)
    _, _, inner = cs.sphere_view_persp(N, N, ca.DISTANCE, ca.FOV)

    def setup_of(area, point, world):
        def setup(sc):
            w = cs.set_world(sc, color=(world,) * 3)
            w.cycles.sampling_method = 'AUTOMATIC'
            if area:
                cs.add_lamp(sc, "AREA", (2.5, 2.0, 3.0), energy=150.0, size=1.0)
            if point:
                cs.add_lamp(sc, "POINT", (-3.0, -1.5, 2.0), energy=100.0, shadow_soft_size=0.25)
        return setup
    for label, args in (("area", (1, 0, 0.0)), ("point r=0.25", (0, 1, 0.0)), ("area + point", (1, 1, 0.0)),
                        (f"world {la.STUDIO_WORLD}", (0, 0, la.STUDIO_WORLD))):
        out = {}
        for kind in ("osl", "diffuse", "fit"):
            sc, _ = ca.cycles_scene(kind, name, tp, None, N, spp, fit=fit, setup=setup_of(*args), native=True)
            imgs = cs.render_seeds(sc, seeds).astype(float)
            out[kind] = (imgs.var(0, ddof=1)[inner].mean() * spp, imgs[:, inner].mean())
        print(f"[lamps] {label}: per-sample variance " + ", ".join(f"{k} {v:.2e} (mean {m:.3f})" for k, (v, m) in
                                                                   out.items())
              + f"; OSL / Diffuse {out['osl'][0] / out['diffuse'][0]:.0f}x", flush=True)


if __name__ == "__main__":
    what, rest = sys.argv[1], sys.argv[2:]
    if what == "roulette":
        roulette(*(rest[:1] or ["cm_military_green"]), **({"scenes": rest[1:]} if rest[1:] else {}))
    elif what == "lamps":
        lamps(*(rest[:1] or ["paper_white"]))
    else:
        raise SystemExit(__doc__)
