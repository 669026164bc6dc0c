"""What EEVEE shows of the Learned BSDF's fit: a sphere under a constant world and one area
lamp, orthographic camera, rendered by Cycles with the node's fit back end (OSL off) and by
EEVEE, same scene; per material the relative mean absolute difference
mean |EEVEE - Cycles| / mean Cycles over the sphere's pixels (RGB, silhouette excluded).

    .venv/bin/python scripts/eevee_acceptance.py TABLES_DIR NAME [NAME...] [--out DIR]
        [--px 64] [--spp 256] [--taa 64] [--full] [--env EXR] [--variants v7,node,iso,...]

Each NAME is <TABLES_DIR>/<NAME>.exr with its <NAME>.fit.json. The node is bound to a path
that does not exist (with the fit file), so its group holds the fit alone (no SVM graph, no
OSL), unless --full (the tables bound: the group as artists have it, OSL/SVM beside the fit).
Images: <out>/<name>_<engine>_<variant>.png (sRGB, same exposure) and a difference image.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
import cycles_scenes as cs  # noqa: E402

N_DEFAULT, SCALE = 64, 2.2


def scene(px, spp, taa, env=None):
    import bpy
    from blender_addon.render import node as lb
    sc = cs.reset(px, px, spp=spp, osl=False)
    cs.ortho_camera(sc, scale=SCALE)
    if hasattr(bpy.types.Scene, lb.FILM_PROP):
        setattr(sc, lb.FILM_PROP, False)
    cs.set_world(sc, (0.25, 0.25, 0.25), image=env, strength=0.25 if env else 1.0)
    sc.world.cycles.sampling_method = 'AUTOMATIC'
    cs.add_lamp(sc, "AREA", (1.5, 1.0, 4.0), energy=150.0, size=1.0)
    sc.eevee.taa_render_samples = taa
    return sc


def engine_id():
    import bpy
    ids = [e.identifier for e in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items]
    return next(e for e in ("BLENDER_EEVEE_NEXT", "BLENDER_EEVEE") if e in ids)


def render(sc, engine):
    sc.render.engine = engine
    t0 = time.perf_counter()
    img = cs.render(sc)
    return img, time.perf_counter() - t0


def rel_mad(a, ref, mask):
    return float(np.mean(np.abs(a - ref)[mask]) / np.mean(ref[mask]))


def save_png(path, img, white):
    from PIL import Image
    v = np.clip(img / white, 0, 1)
    v = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
    Image.fromarray((v * 255 + 0.5).astype(np.uint8)).resize((img.shape[1] * 4, img.shape[0] * 4), 0).save(path)


def save_diff(path, a, ref, mask):
    from PIL import Image
    ya, yr = a.mean(-1), ref.mean(-1)
    d = np.where(mask, (ya - yr) / max(float(yr[mask].mean()), 1e-9), 0.0)
    d = np.clip(d / 0.5, -1, 1)
    rgb = np.stack([np.maximum(d, 0), np.zeros_like(d), np.maximum(-d, 0)], -1)
    Image.fromarray((rgb * 255 + 0.5).astype(np.uint8)).resize((a.shape[1] * 4, a.shape[0] * 4), 0).save(path)


def variant(fit, kind):
    """A copy of `fit` changed as `kind` says, without its EEVEE fit (EEVEE then renders the fit's
    closures): "v7" as is; "noaniso" every lobe's anisotropy 0 (what EEVEE makes of it, if it
    ignores anisotropy); "notilt" every tilt 0; "plain" both. "node": the fit as is, with its
    EEVEE fit (the node's EEVEE output renders that, Cycles the fit); "iso": the EEVEE fit
    (closure_fit: the fit's "eevee") as the fit, in both engines."""
    import copy
    if kind == "node":
        return copy.deepcopy(fit)
    f = copy.deepcopy(fit)
    eevee = f.pop("eevee", None)
    if kind == "iso":
        f.update({key: eevee[key] for key in ("diffuse", "specular", "roughness", "anisotropy", "tilt",
                                              "diffuse_tilt", "view_aligned")})
    if kind in ("noaniso", "plain"):
        f["anisotropy"] = [[0.0] * len(k) for k in f["anisotropy"]]
    if kind in ("notilt", "plain"):
        f["tilt"] = [[0.0] * len(k) for k in f["tilt"]]
        f["diffuse_tilt"] = [0.0] * len(f["diffuse_tilt"])
    return f


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("tables_dir")
    p.add_argument("names", nargs="+")
    p.add_argument("--out", default=None)
    p.add_argument("--px", type=int, default=N_DEFAULT)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--taa", type=int, default=64)
    p.add_argument("--full", action="store_true")
    p.add_argument("--env", default=None, help="an equirectangular EXR as the world (x 0.25) instead of grey")
    p.add_argument("--variants", default="v7")
    p.add_argument("--fits", default=None, help="where the <name>.fit.json are (default: beside the tables)")
    p.add_argument("--noise", action="store_true", help="a second Cycles seed of the first variant")
    args = p.parse_args(argv)
    import tempfile
    import bpy
    from blender_addon.render import binding, node as lb
    lb.register()
    eevee = engine_id()
    out = Path(args.out) if args.out else None
    if out:
        out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="flowbsdf_eevee_"))
    n, hit = cs.sphere_view(args.px, args.px, SCALE)
    mask = hit & (n[..., 2] > 0.1)
    results = {}
    for name in args.names:
        tables = Path(args.tables_dir) / f"{name}.exr"
        fit = json.loads((Path(args.fits or args.tables_dir) / f"{name}.fit.json").read_text())
        imgs, secs = {}, {}
        for kind in args.variants.split(","):
            fit_path = tmp / f"{name}.{kind}.fit.json"
            fit_path.write_text(json.dumps(variant(fit, kind)))
            sc = scene(args.px, args.spp, args.taa, args.env)
            mat = bpy.data.materials.new(name)
            bound = tables if args.full else tmp / "missing.exr"
            group = lb.assign_learned_bsdf(mat, f"{name}.{kind}", bound, fit_path=fit_path).node_tree
            assert binding.read(group)["has_fit"], binding.read(group)["problems"]
            cs.add_sphere(sc, mat, segments=64, rings=32)
            lb.set_backend(sc, "fit")
            for eng in ("CYCLES", eevee):
                imgs[eng, kind], secs[eng, kind] = render(sc, eng)
            if args.noise and "seed1" not in imgs:
                sc.cycles.seed = 1
                imgs["seed1"], _ = render(sc, "CYCLES")
        ref = imgs["CYCLES", args.variants.split(",")[0]]
        row = {f"{e[:6].lower()}:{k}": rel_mad(img, ref, mask) for (e, k), img in
               ((key, v) for key, v in imgs.items() if key != "seed1")}
        row.update({f"eevee:{k}-vs-cycles:{k}": rel_mad(imgs[eevee, k], imgs["CYCLES", k], mask)
                    for k in args.variants.split(",")})
        if "seed1" in imgs:
            row["cycles_seed_noise"] = rel_mad(imgs["seed1"], ref, mask)
        row["seconds"] = {f"{e[:6].lower()}:{k}": round(s, 1) for (e, k), s in secs.items()}
        results[name] = row
        print(name, json.dumps(row), flush=True)
        if out:
            white = float(np.percentile(ref[hit], 99.5))
            for key, img in imgs.items():
                tag = key if isinstance(key, str) else f"{key[0][:6].lower()}_{key[1]}"
                save_png(out / f"{name}_{tag}.png", img, white)
                np.save(out / f"{name}_{tag}.npy", img)
                if key != ("CYCLES", args.variants.split(",")[0]) and key != "seed1":
                    save_diff(out / f"{name}_{tag}_diff.png", img, ref, mask)
    if out:
        (out / "results.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
