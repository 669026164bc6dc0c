"""Issue 6 acceptance: the Learned BSDF node in Cycles against the reference path tracer.

Scene: a unit sphere (smooth UV mesh, 256 x 128) seen by a perspective camera (distance 6,
fov 22 deg) under an equirectangular environment (closest lookups, world kept out of light
sampling: BSDF-only sampling everywhere), 64 x 64, box pixel filter of width 1 in Cycles
(= the tracer's uniform jitter over the pixel). The Blender scene is exported to the tracer's
format by the add-on's validate exporter (blender_addon/artist/validate.export_scene: the same
triangle mesh and normals, camera and environment file) and rendered by bake/tracer with the
baked tables as sampler, BSDF-only (mis=False).

The tracer always evaluates its scene material's `eval`. Two references are rendered:
  - "baked": the scene material replaced by the baked tables' BSDF (Tables.eval; CarriedTables.eval
    where they carry), i.e. exactly what the OSL back end renders (weight = baked f cos / pdf = the cell's weight);
    OSL must match it within MC error (per-pixel z-scores, and the mean over the sphere with
    its standard error). MSEs of OSL, closure fit and Principled fit are against it.
  - "true": the manifest material's own eval (tables sampling): the baked-vs-true difference
    is reported separately (relative mean, MSE), and the MSEs against it too.

Per material, at equal spp: OSL back end (over OSL_SEEDS Cycles seeds: its noise is
measured, not predicted, since the film-stratified u of camera rays changes it; and once more
with u hashed everywhere, the shader's fallback without film settings), closure fit (and the fit at 4x spp, to split
its error into bias^2 + noise), Principled BSDF fit (closure_fit.principled_params); render
times relative to Principled.

    .venv/bin/python scripts/cycles_acceptance.py [names...] [--spp 256] [--size 64]
        [--ref-spp 4096] [--true-spp N] [--env soft|sunny|both] [--workers 2] [--reuse-refs]
Writes out/cycles_acceptance.md (and out/cycles_acceptance/<env>_<name>_*.exr); logs to stdout.
"""
import argparse
import dataclasses
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import cycles_scenes as cs  # noqa: E402
from bake.export.closure_fit import load_fit, principled_params  # noqa: E402
from bake.plumbing.manifest import load_manifest  # noqa: E402
from bake.core.table_files import open_tables  # noqa: E402

DEFAULT = ["paper_white", "cm_military_green", "chm_mint"]
OSL_SEEDS = 8
DISTANCE, FOV = 6.0, 22.0


def make_env(path, kind="soft", w=256, h=128):
    """Sky gradient + ground, plus a broad soft glow ("soft") or a bright small sun ("sunny");
    rows top first (as written to the EXR)."""
    import OpenEXR
    v = (np.arange(h) + 0.5) / h                    # 0 at the top row
    u = (np.arange(w) + 0.5) / w
    U, V = np.meshgrid(u, v)
    elev = (0.5 - V) * np.pi                        # +pi/2 at the top
    az = (0.5 - U) * 2 * np.pi                      # Blender: u = 0.5 - atan2(y, x) / 2 pi
    d = np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], -1)
    sky = np.where(elev[..., None] > 0, [0.3, 0.5, 0.9] * (0.4 + 0.6 * np.sin(np.maximum(elev, 0)))[..., None],
                   [0.25, 0.2, 0.15])
    sun_dir = np.array([0.5, -0.4, 0.77])
    sun_dir /= np.linalg.norm(sun_dir)
    if kind == "sunny":
        blob = np.exp((d @ sun_dir - 1.0) / 0.02)[..., None] * [20.0, 18.0, 14.0]
    else:
        blob = np.exp((d @ sun_dir - 1.0) / 0.35)[..., None] * [2.0, 1.8, 1.4]
    img = (sky + blob).astype(np.float32)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"RGB": img}).write(str(path))
    return img


class BakedBSDF:
    """The baked tables' BSDF as a tracer material (eval = Tables.eval, or CarriedTables.eval where
    the tables carry: bake/core/carried.as_rendered)."""

    def __init__(self, tables, true_material):
        self.tables = tables
        self.isotropic = getattr(true_material, "isotropic", True)
        self.name = "baked:" + str(getattr(true_material, "name", "?"))

    def eval(self, wi, wo):
        return self.tables.eval(wi, wo)


def cycles_scene(kind, name, tables_path, env_path, size, spp, fit=None, seed=0,
                 segments=256, rings=128, distance=DISTANCE, fov=FOV, world_mis=False, setup=None, native=False):
    """The Blender scene (current scene reset) with the sphere's material for `kind`:
    osl | fit | svm (the Learned BSDF node's back ends) | oslhash (OSL, u hashed on camera rays
    too) | principled | diffuse (a Diffuse BSDF of the Principled fit's base colour).
    `setup(scene)`, when given, makes the world and lamps instead of the environment image
    `env_path` (and decides the world's sampling itself). Open Shading Language is on for
    every kind, or with `native` only for the OSL kinds (the others render as Blender's
    default, SVM). Returns (scene, material)."""
    import bpy
    from blender_addon.render import node as lb
    sc = cs.reset(size, size, spp=spp, seed=seed, osl=not native or kind in ("osl", "oslhash"))
    sc.cycles.pixel_filter_type = 'BOX'
    sc.cycles.filter_width = 1.0
    cs.persp_camera(sc, distance=distance, fov_deg=fov)
    if setup is not None:
        setup(sc)
    else:
        world = cs.set_world(sc, image=env_path)
        if world_mis:           # Blender's default: the world importance-sampled (Cycles' closures only)
            world.cycles.sampling_method = 'AUTOMATIC'
    if kind in ("principled", "diffuse"):
        params = principled_params(fit)

        def nodes(tree):
            if kind == "diffuse":
                d = tree.nodes.new("ShaderNodeBsdfDiffuse")
                d.inputs["Color"].default_value = (*params["Base Color"], 1.0)
                return d.outputs[0]
            p = tree.nodes.new("ShaderNodeBsdfPrincipled")
            for k, v in params.items():
                p.inputs[k].default_value = (*v, 1.0) if isinstance(v, list) else v
            return p.outputs[0]
        mat = cs.material_with(nodes)
    else:
        lb.register()
        mat = bpy.data.materials.new(name)
        node = lb.assign_learned_bsdf(mat, name, tables_path)
        lb.set_backend(sc, "osl" if kind == "oslhash" else kind)
        if kind == "oslhash":
            cs.hashed_u(node)
    cs.add_sphere(sc, mat, segments=segments, rings=rings)
    return sc, mat


def render_case(*args, seeds=1, **kw):
    """(image, or (seeds, H, W, 3) images for Cycles seeds 0..seeds-1; seconds per render)."""
    sc, _ = cycles_scene(*args, **kw)
    t0 = time.perf_counter()
    imgs = cs.render_seeds(sc, seeds)
    return (imgs[0] if seeds == 1 else imgs), (time.perf_counter() - t0) / seeds


def export_for_tracer(name, tables_path, env_path, size, folder, manifest_path, **kw):
    """The OSL scene exported by the add-on's validate exporter; returns the scene file."""
    from blender_addon.artist import validate
    sc, mat = cycles_scene("osl", name, tables_path, env_path, size, 1, **kw)
    path, notes = validate.export_scene(sc, str(folder), [{"material": mat, "name": name}], size, size,
                                        str(manifest_path))
    for n in notes:
        print(f"[export] {n}", flush=True)
    return path


def trace(scene_path, manifest, tables, which, spp, seed=1, workers=1, mis=False, seconds=None):
    """Tracer render (BSDF-only, or with `mis` next-event estimation of the lamps and the
    world; tables sampling) with the scene's learned material evaluated as the baked tables
    (which="baked") or the true material (which="true"); `seconds`: as many passes as fit.
    Returns (image, per-pixel variance of the mean, per-sample variance, seconds)."""
    from bake.tracer import load_scene, render
    from bake.core.carried import as_rendered
    scene = load_scene(scene_path, manifest=load_manifest(manifest))
    tables = as_rendered(tables, next(m.material for m in scene.materials if m.learned))     # what OSL renders
    if which == "baked":
        scene.materials = [dataclasses.replace(m, material=BakedBSDF(tables, m.material)) if m.learned else m
                           for m in scene.materials]
    samplers = [tables if m.learned else None for m in scene.materials]
    t0 = time.perf_counter()
    img, var, st = render(scene, samplers, spp=spp, seconds=seconds, mis=mis, seed=seed, workers=workers)
    return img, var, var * st.extra["spp"], time.perf_counter() - t0


def z_stats(img, ref, var_img, var_ref, mask):
    """Per-pixel z-scores (all channels) and the sphere mean's relative deviation with its
    standard error (pixels independent)."""
    s = np.sqrt(var_img + var_ref)[mask]
    z = ((img - ref)[mask] / np.where(s > 0, s, np.inf))
    n = mask.sum()
    mean_d = (img - ref)[mask].mean(0)
    se = np.sqrt((var_img + var_ref)[mask].sum(0)) / n
    return float(np.sqrt(np.mean(z ** 2))), float(np.mean(np.abs(z) > 3)), mean_d, se


CASES = lambda spp: (("osl", spp), ("oslhash", spp), ("fit", spp), ("fit", 4 * spp), ("principled", spp))  # noqa: E731


def run_material(name, env_kind, env_path, args, manifest_path):
    """Render everything for one material (tracer references, Cycles cases) into
    out/cycles_acceptance/<env>_<name>/ (*.npy, times.json); then analyse()."""
    tables_path = ROOT / "out" / "tables" / f"{name}.exr"
    tables = open_tables(tables_path)
    folder = ROOT / "out" / "cycles_acceptance" / f"{env_kind}_{name}"
    folder.mkdir(parents=True, exist_ok=True)
    scene_path = export_for_tracer(name, tables_path, env_path, args.size, folder, manifest_path)
    times = {}
    for which, spp in (("baked", args.ref_spp), ("true", args.true_spp or args.ref_spp)):
        if args.reuse_refs and (folder / f"tracer_{which}.npy").is_file():
            print(f"[{env_kind} {name}] tracer {which}: reused", flush=True)
            continue
        img, var, var1, secs = trace(scene_path, manifest_path, tables, which, spp, workers=args.workers)
        print(f"[{env_kind} {name}] tracer {which} {spp} spp: {secs:.0f} s", flush=True)
        np.save(folder / f"tracer_{which}.npy", np.stack([img, var, var1]))
    from bake.export.derived import ensure_fit
    fit = load_fit(ensure_fit(tables_path))
    for kind, spp in CASES(args.spp):
        img, secs = render_case(kind, name, tables_path, env_path, args.size, spp, fit=fit,
                                seeds=OSL_SEEDS if kind.startswith("osl") else 1, world_mis=args.world_mis)
        np.save(folder / f"{kind}_{spp}{_tag(args)}.npy", img)
        times[f"{kind}_{spp}"] = secs
        print(f"[{env_kind} {name}] {kind} {spp} spp: {secs:.1f} s", flush=True)
    (folder / f"times{_tag(args)}.json").write_text(json.dumps(times))
    return analyse(name, env_kind, args)


def _tag(args):
    """File-name tag of the Cycles renders: with the world importance-sampled, their own files."""
    return "_worldmis" if getattr(args, "world_mis", False) else ""


def times_from_log(log):
    """{(env, name): {kind_spp: seconds}} from a run's log (runs before times.json existed)."""
    out = {}
    for m in re.finditer(r"^\[(\w+) (\w+)\] (oslhash|osl|fit|principled) (\d+) spp: .*?([\d.]+) s$", Path(log).read_text(), re.M):
        out.setdefault((m[1], m[2]), {})[f"{m[3]}_{m[4]}"] = float(m[5])
    return out


def analyse(name, env_kind, args, times=None):
    folder = ROOT / "out" / "cycles_acceptance" / f"{env_kind}_{name}"
    if times is None:
        times = json.loads((folder / f"times{_tag(args)}.json").read_text())
    ref, ref_var, var1 = np.load(folder / "tracer_baked.npy")
    true, true_var, true_var1 = np.load(folder / "tracer_true.npy")
    spp_of = lambda v, v1: int(round(float(np.median(v1[v > 0] / v[v > 0]))))  # noqa: E731
    _, cos, inner = cs.sphere_view_persp(args.size, args.size, DISTANCE, FOV)
    out = {}
    for kind, spp in CASES(args.spp):
        img = np.load(folder / f"{kind}_{spp}{_tag(args)}.npy")
        imgs = img if img.ndim == 4 else img[None]          # OSL: one render per seed
        d = (imgs - ref)[:, inner]
        out[(kind, spp)] = (float(np.mean(d ** 2)), times[f"{kind}_{spp}"], imgs,
                            float(np.mean((imgs - true)[:, inner] ** 2)))
        print(f"[{env_kind} {name}] {kind} {spp} spp: MSE {np.mean(d ** 2):.3e} (mean of {len(imgs)} "
              f"render(s)), mean rel {np.mean(d) / np.mean(ref[inner]):+.4f}", flush=True)
    imgs = out[("osl", args.spp)][2]
    # The OSL noise, measured over the seeds (the film-stratified u makes it differ from the
    # tables' own, which the tracer's per-sample variance would predict): the test
    # image is the seeds' mean, its per-pixel variance var / seeds (t-distributed z, K - 1 dof).
    var_osl = imgs.var(0, ddof=1) / len(imgs)
    rms_z, frac3, mean_d, se = z_stats(imgs.mean(0), ref, var_osl, ref_var, inner)
    m = ref[inner].mean(0)
    mse_fit, mse_fit4 = out[("fit", args.spp)][0], out[("fit", 4 * args.spp)][0]
    ref_mse = float(np.mean(ref_var[inner]))
    true_noise = float(np.mean(true_var[inner]))
    # fit noise at spp ~ 4/3 (mse(spp) - mse(4 spp)); bias^2 = mse(spp) - noise - reference noise.
    noise = max(4.0 / 3.0 * (mse_fit - mse_fit4), 0.0)
    row = {"env": env_kind, "name": name, "mean": float(m.mean()), "ref_mse": ref_mse,
           "ref_spp": spp_of(ref_var, var1), "true_spp": spp_of(true_var, true_var1),
           "osl": out[("osl", args.spp)][0], "oslhash": out[("oslhash", args.spp)][0],
           "oslhash_expected": float(np.mean(var1[inner])) / args.spp + ref_mse,
           "rms_z": rms_z, "frac3": frac3, "osl_rel": float(mean_d.mean() / m.mean()),
           "osl_rel_se": float(np.sqrt(np.mean(se ** 2)) / m.mean()),
           "osl_rel_z": float(np.max(np.abs(mean_d / se))),
           "fit": mse_fit, "fit_bias2": max(mse_fit - noise - ref_mse, 0.0), "fit_noise": noise,
           "principled": out[("principled", args.spp)][0],
           "baked_vs_true_rel": float((m.mean() - true[inner].mean()) / true[inner].mean()),
           "baked_vs_true_se": float(np.sqrt(np.mean((ref_var + true_var)[inner].sum(0))) / inner.sum()
                                     / true[inner].mean()),
           "baked_vs_true_mse": max(float(np.mean((ref - true)[inner] ** 2)) - ref_mse - true_noise, 0.0),
           "true_noise": true_noise,
           "osl_true": out[("osl", args.spp)][3] - true_noise, "fit_true": out[("fit", args.spp)][3] - true_noise,
           "principled_true": out[("principled", args.spp)][3] - true_noise,
           "t_osl": out[("osl", args.spp)][1], "t_fit": out[("fit", args.spp)][1],
           "t_pr": out[("principled", args.spp)][1]}
    print(f"[{env_kind} {name}] OSL vs tracer(baked): rms z {rms_z:.3f}, |z|>3 {frac3:.4f}, sphere mean "
          f"rel {row['osl_rel']:+.5f} +- {row['osl_rel_se']:.5f}; baked vs true {row['baked_vs_true_rel']:+.4f}",
          flush=True)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("names", nargs="*", default=DEFAULT)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--true-spp", type=int, default=0, help="spp of the true-material render (default ref-spp)")
    ap.add_argument("--env", choices=("soft", "sunny", "both"), default="soft")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--reuse-refs", action="store_true", help="keep the tracer references already saved")
    ap.add_argument("--world-mis", action="store_true", help="Cycles importance-samples the world (Blender's "
                    "default; the references stay BSDF-only: the same converged image)")
    ap.add_argument("--from-saved", action="store_true",
                    help="no rendering: analyse the saved renders in out/cycles_acceptance/")
    ap.add_argument("--times-log", help="with --from-saved: take render times from this run log")
    ap.add_argument("--out", default=str(ROOT / "out" / "cycles_acceptance.md"))
    args = ap.parse_args(argv)
    manifest_path = ROOT / "manifest.toml"
    entries = {e.name: e for e in load_manifest(manifest_path).materials}
    rows = []
    for env_kind in (("soft", "sunny") if args.env == "both" else (args.env,)):
        env_path = ROOT / "out" / f"acceptance_env_{env_kind}.exr"
        if not args.from_saved:
            make_env(env_path, env_kind)
        for name in args.names:
            if name not in entries or not (ROOT / "out" / "tables" / f"{name}.exr").is_file():
                print(f"[skip] {name}: not in the manifest or no tables", flush=True)
                continue
            if args.from_saved:
                times = times_from_log(args.times_log).get((env_kind, name)) if args.times_log else None
                rows.append(analyse(name, env_kind, args, times))
            else:
                rows.append(run_material(name, env_kind, env_path, args, manifest_path))
            write(rows, args)
    write(rows, args)


def write(rows, args):
    lines = ["# Cycles acceptance (issue 6): sphere under an environment map vs the reference tracer",
             "",
             f"{args.size}x{args.size} px, perspective camera, box filter; Cycles (bpy 5.0.1, CPU, 2 threads"
             f"{', world importance-sampled' if args.world_mis else ', world not light-sampled'}) "
             f"at {args.spp} spp; reference: bake/tracer, BSDF-only, tables sampling (ref spp: baked / true "
             "reference, per row), "
             "scene exported by blender_addon/artist/validate.export_scene. Pixels: the sphere's interior (no "
             "silhouette pixels, cos view > 0.05). MSE: mean over those pixels and RGB.", "",
             "- **baked ref**: tracer with the scene material's eval = the tables' (carried where they carry: what the OSL back end "
             f"renders). OSL: {OSL_SEEDS} renders (Cycles seeds); MSE = their mean MSE (one render at the spp). "
             f"OSL z: per-pixel (mean of the renders - ref) / sqrt(var_OSL + var_ref), var_OSL from the seeds' "
             f"spread ({OSL_SEEDS - 1} dof: rms z ~ {np.sqrt((OSL_SEEDS - 1) / (OSL_SEEDS - 3)):.2f} and a few "
             "% beyond 3 if within MC error). Sphere mean: relative difference +- its standard error.",
             "- OSL hashed u: the same shader with u hashed on camera rays too (its fallback without the "
             "scene's film settings: plain Monte Carlo); 'expected' is its MSE predicted from the tracer's "
             "per-sample variance.",
             "- Fit MSE = bias^2 + noise (noise from the fit at 4x spp; bias^2 net of the reference's noise).",
             "- **true ref**: the same tracer render with the true material's eval; baked-vs-true is the "
             "tables' own error (sphere-mean relative difference; MSE net of both references' noise). "
             "MSE vs true ref: net of the true reference's noise^2.",
             "- Noise: Cycles gives OSL no sampler state; on camera rays the OSL shader takes u from the "
             "sample's position in its pixel (Cycles' stratified film sample, rotated per pixel), deeper it "
             "hashes u (plain Monte Carlo). Cycles' own closures (fit, Principled) get its QMC samples everywhere.",
             f"- Times: whole render call incl. scene sync (OSL: mean over its renders), 2 cores, load "
             f"{os.getloadavg()[0]:.1f} when written.", "",
             "| env | material | ref spp | mean radiance | ref noise^2 | OSL rms z (\\|z\\|>3) | OSL sphere-mean rel. diff | "
             "OSL MSE | OSL hashed-u MSE (expected) | fit MSE (bias^2 + noise) | Principled MSE | baked-vs-true mean rel. +- SE (MSE) | "
             "MSE vs true ref: OSL / fit / Principled | time OSL/Pr | time fit/Pr |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        mse_bt = f"{r['baked_vs_true_mse']:.1e}" if r["baked_vs_true_mse"] > 0 else "below noise"
        lines.append(
            f"| {r['env']} | {r['name']} | {r['ref_spp']} / {r['true_spp']} | {r['mean']:.4f} | {r['ref_mse']:.1e} | {r['rms_z']:.3f} ({r['frac3']:.4f}) | "
            f"{r['osl_rel']:+.5f} +- {r['osl_rel_se']:.5f} | {r['osl']:.2e} | {r['oslhash']:.2e} ({r['oslhash_expected']:.2e}) | "
            f"{r['fit']:.2e} ({r['fit_bias2']:.2e} + {r['fit_noise']:.2e}) | {r['principled']:.2e} | "
            f"{r['baked_vs_true_rel']:+.4f} +- {r['baked_vs_true_se']:.4f} ({mse_bt}) | "
            f"{r['osl_true']:.2e} / {r['fit_true']:.2e} / {r['principled_true']:.2e} | "
            f"{r['t_osl'] / r['t_pr']:.2f} | {r['t_fit'] / r['t_pr']:.2f} |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
