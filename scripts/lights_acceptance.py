"""Issues 17 and 18 acceptance: the Learned BSDF's back ends on a sphere in three lighting
scenes, at equal render time, against the reference tracer's converged image of the measured
file's BSDF and/or of the baked tables' BSDF (--reference file|baked|both, default both).

Scenes (64 x 64 by default, box filter, perspective camera as scripts/cycles_acceptance.py;
Cycles' world importance sampling at Blender's default, 'AUTOMATIC', everywhere):
  hdri    the "sunny" environment image of cycles_acceptance (Environment Texture, Closest);
  sky     Blender's default Sky Texture (sun_elevation 0.5) rendered once into an
          equirectangular image by blender_addon/render/world.render_world (--sky-res, --sky-spp), and
          that image is the world of both Cycles (Environment Texture, Closest) and the tracer:
          both renderers see the identical world;
  studio  an area lamp + a point lamp with a radius + a dim constant world.
and "truesky": the real Sky Texture (the same settings), for the fireflies criterion only.

Per (scene, material) — draft tables (32 x 32 cells, 8 theta bins, ideal tabulation) unless
--tables-dir has the material:
  1. CPU time per spp of each back end (--kinds; this process's CPU time: Cycles' threads;
     wall time too, for the record), measured in this run, interleaved: Principled BSDF fit
     (bake.export.closure_fit.principled_params: the clock), "osl" (the OSL back end as the
     node renders it by default: with the carried blend where the tables have a carry
     texture), "osl_fixed" (the OSL back end at the fixed cells: the tables'
     <name>.carry1-<hash>.exr renamed to .<name>... for its renders, carried_cost.without,
     restored in a finally, and put back at start-up if an interrupted run left it aside),
     "svm" (SVM back end), "fit" (closure fit); and Principled under OSL, for the record; each
     at --t-lo and --t-hi spp in --t-rounds rounds (order rotated), time per spp = (min t_hi -
     min t_lo) / (hi - lo): scene sync and shader compilation excluded.
  2. equal time: Principled at --spp, every other back end at the spp that costs the same
     (--spp x its time per spp / Principled's); seeds: OSL (both) --osl-seeds, the others
     --seeds. MSE of one render (mean over the seeds, with its SE over them) against each
     reference, net of the reference's own noise; split into noise (per-pixel variance over
     the seeds) + bias^2 (the seeds' mean vs the reference, net of both noises).
  3. the references: bake/tracer (scene exported by blender_addon/artist/validate.export_scene, lamps
     included), MIS on, tables sampling, the material evaluated as
       file   the manifest material's own eval (the measured RGL file): --file-ref-spp (default
              --ref-spp), tracer seed 2;
       baked  the baked tables (carried where they carry: what the OSL back end renders with
              its carry texture; OSL fixed and SVM render the fixed cells), --ref-spp, seed 1;
     the exported 256 x 128 mesh replaced by the
     analytic unit sphere (the tracer's numpy BVH made the mesh 10x slower); per scene, the
     first material's reference is also traced on the mesh with the same seed (--geom-spp) and
     the sphere means compared (geometry_check).
  4. OSL (and SVM) vs the reference: per-pixel z of the seeds' mean (variance from the seeds'
     spread), sphere mean's relative difference +- SE.
Truesky: OSL, SVM, Principled and Diffuse (the Principled fit's base colour) at --ff-spp,
--ff-seeds seeds each: per-pixel variance over the seeds (mean over the sphere, max), the
largest pixel; OSL's and SVM's sphere means agree (both unbiased for the baked BSDF).

Back ends render as a user gets them: OSL with Open Shading Language on, the SVM graph, the
fit, Principled and Diffuse with it off (Blender's default, SVM). Cycles settings: those of
tests/cycles_scenes.reset (blur_glossy 0, no clamping, 64 bounces...), recorded in the report;
--settings blender: Blender's factory render settings instead (read from a factory scene:
Filter Glossy 1, 12/4/4 bounces, 8 transparent, Clamp Indirect 10, adaptive sampling...) but
denoising off and the box pixel filter kept (the tracer's pixels; the SVM graph and the OSL
shader take hashed u there, as under the default Blackman-Harris filter: implies --film-u off).
With adaptive sampling on, time per spp is not what an equal-time render costs: each back
end's equal-time render's own CPU seconds are in the report.

Report (--out): "Equal time" tables per (scene, material) and back end: time per spp vs
Principled, equal-time spp x seeds, MSE vs file and vs baked (bias^2 + noise) and each MSE's
ratio to the best back end's; the ratios OSL carried / OSL fixed and SVM / fit per reference;
the closure fit's version (at the case's start and end: fits are refit by ensure_fit); each
reference's mean, spp and noise, and baked vs file; the Cycles settings; then the acceptance
details (z statistics, per-sample noise) against the primary reference (baked when traced).

    .venv/bin/python scripts/lights_acceptance.py [names...] [--scenes hdri,sky,studio,truesky]
        [--size 64] [--spp 256] [--ref-spp 4096] [--file-ref-spp N] [--reference file|baked|both]
        [--kinds principled,osl,osl_fixed,svm,fit] [--tables-dir DIR] [--work-dir DIR] [--reuse]
Writes out/lights_acceptance.md (--out) and <work-dir>/<scene>_<name>/*.npy, timing.json,
tracer_{file,baked}.npy, <work-dir>/rows.json (--work-dir, default out/lights_acceptance/).
"""
import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import carried_cost  # noqa: E402
import cycles_acceptance as ca  # noqa: E402
import cycles_scenes as cs  # noqa: E402
from bake.export.closure_fit import load_fit  # noqa: E402
from bake.export.derived import ensure_fit  # noqa: E402
from bake.core.table_files import open_tables  # noqa: E402

NAMES = ["paper_white", "cm_military_green", "chm_mint"]
SCENES = ("hdri", "sky", "studio", "truesky")
OUT = ROOT / "out" / "lights_acceptance"     # (--work-dir)
DRAFT_BINS = np.radians([0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 80.0, 89.5])
SKY = {"sun_elevation": 0.5, "sun_rotation": 0.6, "strength": 0.08}
STUDIO_WORLD = 0.05
KINDS = ("principled", "osl", "osl_fixed", "svm", "fit")   # equal-time comparisons; Principled is the clock
REFS = ("file", "baked")                            # tracer references: the measured file's eval, the baked tables'
REF_SEED = {"baked": 1, "file": 2}                  # independent streams: each reference's noise nets out alone
# Cycles settings recorded in the report (tests/cycles_scenes.reset sets most of them; Blender's defaults differ)
SETTINGS = ("max_bounces", "diffuse_bounces", "glossy_bounces", "transparent_max_bounces", "blur_glossy",
            "caustics_reflective", "caustics_refractive", "sample_clamp_direct", "sample_clamp_indirect",
            "use_light_tree", "light_sampling_threshold", "use_adaptive_sampling", "use_denoising",
            "pixel_filter_type", "filter_width", "sampling_pattern")


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.1f}] {msg}", flush=True)


# ------------------------------------------------------------------------------ inputs

def draft_tables(name, folder, tables_dir=None):
    """The material's tables: <tables_dir>/<name>.exr when given and present, else draft
    tables (32 x 32 cells over DRAFT_BINS, ideal tabulation at 128^2) made once in `folder`."""
    if tables_dir and (Path(tables_dir) / f"{name}.exr").is_file():
        return Path(tables_dir) / f"{name}.exr"
    path = Path(folder) / f"{name}.exr"
    if not path.is_file():
        from bake.core.ideal import IdealSampler
        from bake.materials import open_material
        from bake.plumbing.manifest import load_manifest
        from bake.core.tabulate import build_tables
        entry = {e.name: e for e in load_manifest(ROOT / "manifest.toml").materials}[name]
        mat = open_material(entry.source, base_dir=ROOT)
        t0 = time.perf_counter()
        tab = build_tables(mat, IdealSampler(mat, resolution=128), DRAFT_BINS, rows=32, cols=32, grid=192)
        tab.meta["material"] = name
        Path(folder).mkdir(parents=True, exist_ok=True)
        tab.save(path)
        log(f"draft tables {name}: {time.perf_counter() - t0:.1f} s")
    return path


def write_exr(path, img):
    import OpenEXR
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"RGB": np.ascontiguousarray(img, np.float32)}).write(str(path))


def sky_image(path, width, height, spp):
    """The Sky Texture world (SKY) as an equirectangular image, rendered by world.render_world."""
    if Path(path).is_file():
        return path
    from blender_addon.render import world as bw
    sc = cs.reset(8, 8)
    cs.set_sky_world(sc, SKY["sun_elevation"], SKY["sun_rotation"], SKY["strength"])
    t0 = time.perf_counter()
    img = bw.render_world(sc, width, height, spp)
    write_exr(path, img)
    log(f"sky image {width}x{height}, {spp} spp: {time.perf_counter() - t0:.0f} s, max {img.max():.4g}")
    return path


def setups(hdri_path, sky_path):
    """{scene: setup(scene)} making the world (and lamps)."""
    def env(path):
        def setup(sc):
            world = cs.set_world(sc, image=path)
            world.cycles.sampling_method = 'AUTOMATIC'
        return setup

    def studio(sc):
        world = cs.set_world(sc, color=(STUDIO_WORLD,) * 3)
        world.cycles.sampling_method = 'AUTOMATIC'
        cs.add_lamp(sc, "AREA", (2.5, 2.0, 3.0), energy=150.0, size=1.0)
        cs.add_lamp(sc, "POINT", (-3.0, -1.5, 2.0), energy=100.0, shadow_soft_size=0.25)

    def truesky(sc):
        cs.set_sky_world(sc, SKY["sun_elevation"], SKY["sun_rotation"], SKY["strength"])
    return {"hdri": env(hdri_path), "sky": env(sky_path), "studio": studio, "truesky": truesky}


# Blender's factory render settings --settings blender takes (blender_settings), all but the
# pixel filter, denoising, device, seed and threads (the comparison's own)
FACTORY = ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces", "volume_bounces",
           "transparent_max_bounces", "blur_glossy", "caustics_reflective", "caustics_refractive",
           "sample_clamp_direct", "sample_clamp_indirect", "use_light_tree", "light_sampling_threshold",
           "use_adaptive_sampling", "adaptive_threshold", "adaptive_min_samples", "sampling_pattern")


def blender_settings():
    """{setting: value} of FACTORY in a factory scene (reads the factory settings: call first)."""
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return {k: getattr(bpy.context.scene.cycles, k) for k in FACTORY}


def _with_settings(setup, settings):
    def with_settings(sc):
        for k, v in settings.items():
            setattr(sc.cycles, k, v)
        sc.cycles.use_denoising = False
        setup(sc)
    return with_settings


def _film_off(setup):
    def film_off(sc):
        from blender_addon.render import node as lb
        if hasattr(sc, lb.FILM_PROP):
            setattr(sc, lb.FILM_PROP, False)
        else:
            sc[lb.FILM_PROP] = False
        setup(sc)
    return film_off


# ------------------------------------------------------------------------------ rendering

class Case:
    def __init__(self, scene, name, tables_path, setup, args):
        self.scene, self.name, self.tables_path, self.setup, self.args = scene, name, tables_path, setup, args
        self.fit = load_fit(ensure_fit(tables_path))
        self.fit_version = self.fit.get("version")
        self.folder = Path(args.work_dir) / f"{scene}_{name}"
        self.folder.mkdir(parents=True, exist_ok=True)
        self.carry = carry_texture(tables_path)
        self.settings = None        # the Cycles settings (SETTINGS) of its renders

    def tag(self):
        return f"[{self.scene} {self.name}]"

    def cycles(self, kind, spp, seeds, first_seed=0):
        """(seeds, H, W, 3) renders and the seconds of each render call: (wall, CPU of this
        process, i.e. Cycles' threads: what other jobs on the machine change least)."""
        if kind == "osl_fixed":         # the carry texture moved aside: the node renders the fixed cells
            if self.carry is None:
                raise RuntimeError(f"{self.tag()} osl_fixed: the tables have no carry texture")
            with carried_cost.without(self.carry):
                return self._cycles(kind, spp, seeds, first_seed)
        return self._cycles(kind, spp, seeds, first_seed)

    def _cycles(self, kind, spp, seeds, first_seed):
        native = kind != "principled_osl"
        base = {"principled_osl": "principled", "osl_fixed": "osl"}.get(kind, kind)
        sc, _ = ca.cycles_scene(base, self.name, self.tables_path, None, self.args.size, spp, fit=self.fit,
                                setup=self.setup, native=native)
        if self.settings is None:
            self.settings = {k: getattr(sc.cycles, k) for k in SETTINGS if hasattr(sc.cycles, k)}
        if base in ("osl", "svm", "fit"):
            from blender_addon.render import node as lb
            mat = sc.objects["sphere"].active_material
            group = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeGroup")
            status = lb.node_status(group, sc)
            carried = "carried" in status.lower()
            if (not status.lower().startswith(base) or (kind == "osl_fixed" and carried)
                    or (kind == "osl" and self.carry is not None and not carried)):
                raise RuntimeError(f"{self.tag()} {kind}: the node renders {status!r}")
        imgs, secs = [], []
        for seed in range(first_seed, first_seed + seeds):
            sc.cycles.seed = seed
            t0, c0 = time.perf_counter(), time.process_time()
            imgs.append(cs.render(sc))
            secs.append((time.perf_counter() - t0, time.process_time() - c0))
            log(f"{self.tag()} {kind} {spp} spp seed {seed}: {secs[-1][0]:.1f} s wall, {secs[-1][1]:.1f} s CPU")
        if kind == "osl_fixed" and not self.carry.with_name("." + self.carry.name).is_file():
            raise RuntimeError(f"{self.tag()} osl_fixed: the carry texture was not aside during the renders")
        return np.array(imgs), secs

    def saved(self, key, make):
        """np.load of folder/key.npy, made by make() (an array) unless --reuse finds it."""
        path = self.folder / f"{key}.npy"
        if self.args.reuse and path.is_file():
            return np.load(path)
        arr = make()
        np.save(path, arr)
        return arr

    def timing(self):
        """{kind: seconds per spp} (and the raw times), interleaved, order rotated per round."""
        path = self.folder / "timing.json"
        if self.args.reuse and path.is_file():
            return json.loads(path.read_text())
        a = self.args
        timed = tuple(a.kinds) + ("principled_osl",)
        raw = {k: {"lo": [], "hi": [], "lo_wall": [], "hi_wall": []} for k in timed}
        loads = []
        for rnd in range(a.t_rounds):
            order = timed[rnd % len(timed):] + timed[:rnd % len(timed)]
            for kind in order:
                for which, spp in (("lo", a.t_lo), ("hi", a.t_hi)):
                    _, secs = self.cycles(kind, spp, 1, first_seed=100 + rnd)
                    raw[kind][which].append(secs[0][1])
                    raw[kind][which + "_wall"].append(secs[0][0])
                    loads.append(os.getloadavg()[0])
        per_spp = {k: (min(v["hi"]) - min(v["lo"])) / (a.t_hi - a.t_lo) for k, v in raw.items()}
        wall = {k: (min(v["hi_wall"]) - min(v["lo_wall"])) / (a.t_hi - a.t_lo) for k, v in raw.items()}
        out = {"per_spp": per_spp, "wall_per_spp": wall, "raw": raw, "load": [min(loads), max(loads)], "lo": a.t_lo, "hi": a.t_hi}
        path.write_text(json.dumps(out))
        log(f"{self.tag()} CPU time/spp (ms): " + ", ".join(f"{k} {1e3 * v:.2f}" for k, v in per_spp.items())
            + "; wall: " + ", ".join(f"{k} {1e3 * v:.2f}" for k, v in wall.items())
            + f"; load {min(loads):.1f}-{max(loads):.1f}")
        return out

    def export(self):
        """The scene exported by the validate exporter (lamps included): (mesh scene file, the
        same with the mesh replaced by the analytic unit sphere it approximates)."""
        exp = self.folder / "export"
        sc, mat = ca.cycles_scene("osl", self.name, self.tables_path, None, self.args.size, 1, fit=self.fit,
                                  setup=self.setup, native=True)
        from blender_addon.artist import validate
        mesh_path, notes = validate.export_scene(sc, str(exp), [{"material": mat, "name": self.name}],
                                                 self.args.size, self.args.size, str(ROOT / "manifest.toml"))
        for n in notes:
            log(f"{self.tag()} [export] {n}")
        text = Path(mesh_path).read_text()
        mesh = 'type = "mesh"\nfile = "sphere_0.obj"\n'
        if text.count(mesh) != 1:
            raise RuntimeError(f"{self.tag()}: the export has not exactly one sphere mesh: {mesh_path}")
        sphere_path = exp / "scene_sphere.toml"
        sphere_path.write_text(text.replace(mesh, 'type = "sphere"\ncenter = [0.0, 0.0, 0.0]\nradius = 1.0\n'))
        return mesh_path, sphere_path

    def trace(self, scene_path, spp, seed=1, which="baked"):
        """which: "baked" (the tables' eval, carried where they carry: what OSL renders) or "file"
        (the manifest material's own eval: the measured file); tables sampling either way."""
        t0 = time.perf_counter()
        img, var, var1, _ = ca.trace(scene_path, ROOT / "manifest.toml", open_tables(self.tables_path),
                                     "true" if which == "file" else "baked",
                                     spp, seed=seed, workers=self.args.workers, mis=True)
        return img, var, var1, time.perf_counter() - t0

    def reference(self, which="baked"):
        """Tracer reference (image, variance of the mean, per-sample variance): MIS, the baked
        tables' BSDF (which="baked") or the measured file's (which="file"), the analytic sphere
        (the mesh's BVH in numpy is 10x slower; the mesh's difference is measured by
        geometry_check)."""
        path = self.folder / f"tracer_{which}.npy"
        if self.args.reuse and path.is_file():
            img, var, var1 = np.load(path)
            return img, var, var1
        if getattr(self, "_sphere_path", None) is None:
            self._sphere_path = self.export()[1]
        spp = self.args.ref_spp if which == "baked" else (self.args.file_ref_spp or self.args.ref_spp)
        img, var, var1, secs = self.trace(self._sphere_path, spp, seed=REF_SEED[which], which=which)
        log(f"{self.tag()} tracer reference (MIS, {which} eval, analytic sphere): {spp} spp in {secs:.0f} s")
        np.save(path, np.stack([img, var, var1]))
        return img, var, var1

    def geometry_check(self, spp):
        """The tracer on the exported mesh vs on the analytic sphere, same seed: the sphere
        mean's relative difference and its SE (from the pixels' spread of the difference)."""
        path = self.folder / f"geometry_check_{spp}.json"
        if self.args.reuse and path.is_file():
            return json.loads(path.read_text())
        mesh_path, sphere_path = self.export()
        inner = inner_mask(self.args.size)
        (a, va, _, ta), (b, vb, _, tb) = self.trace(mesh_path, spp, seed=7), self.trace(sphere_path, spp, seed=7)
        d = (a - b)[inner].mean(-1)
        m = float(b[inner].mean())
        out = {"spp": spp, "rel": float(d.mean() / m), "se": float(d.std(ddof=1) / np.sqrt(d.size) / m),
               "mesh_s": ta, "sphere_s": tb}
        path.write_text(json.dumps(out))
        log(f"{self.tag()} tracer mesh vs analytic sphere ({spp} spp, same seed): sphere mean rel "
            f"{out['rel']:+.5f} +- {out['se']:.5f}; {ta:.0f} s vs {tb:.0f} s")
        return out


def carry_texture(tables_path):
    """The tables' carried-blend texture (the node's name for it), or None; one left aside by an
    interrupted run (carried_cost.without's ".<name>") is put back first."""
    from blender_addon.render import derived
    tables_path = Path(tables_path)
    hidden = list(tables_path.parent.glob(f".{tables_path.stem}.carry*.exr"))
    for h in hidden:
        if not h.with_name(h.name[1:]).exists():
            h.rename(h.with_name(h.name[1:]))
            log(f"restored {h.name[1:]} (left aside by an interrupted run)")
    path = derived.carry_texture(tables_path)
    return Path(path) if path else None


def inner_mask(size):
    return cs.sphere_view_persp(size, size, ca.DISTANCE, ca.FOV)[2]


def block_z(img, ref, var_img, var_ref, inner, b=4):
    """rms z of b x b pixel block means (blocks wholly inside `inner`): per-pixel z-scores with
    variances from a few seeds break down where the noise is heavy-tailed (a sun's rare large
    samples: a pixel none of whose seeds drew one looks 30 sigma dark); a block pools b^2
    pixels' samples."""
    H, W = inner.shape
    h, w = H // b, W // b
    blk = lambda a: a[:h * b, :w * b].reshape(h, b, w, b, -1).sum((1, 3))      # noqa: E731
    full = blk(inner[..., None].astype(float))[..., 0] == b * b
    d = (blk(img) - blk(ref))[full]
    v = (blk(var_img) + blk(var_ref))[full]
    return float(np.sqrt(np.mean(d * d / np.where(v > 0, v, np.inf))))


def errors(imgs, ref, ref_var, inner):
    """MSE of one render (mean over the renders, net of the reference's noise), its split into
    noise + bias^2, and the z statistics of the renders' mean against the reference."""
    k = len(imgs)
    ref_noise = float(np.mean(ref_var[inner]))
    per_render = np.mean((imgs - ref)[:, inner] ** 2, axis=(1, 2)) - ref_noise
    mse = float(per_render.mean())
    mse_se = float(per_render.std(ddof=1) / np.sqrt(k)) if k > 1 else float("nan")
    var = imgs.var(0, ddof=1) if k > 1 else np.zeros_like(ref)
    noise = float(np.mean(var[inner]))
    bias2 = float(np.mean((imgs.mean(0) - ref)[inner] ** 2)) - noise / k - ref_noise
    rms_z, frac3, mean_d, se = ca.z_stats(imgs.mean(0), ref, var / k, ref_var, inner)
    m = float(ref[inner].mean())
    return {"mse": mse, "mse_se": mse_se, "noise": noise, "bias2": bias2, "rms_z": rms_z, "frac3": frac3,
            "block_z": block_z(imgs.mean(0), ref, var / k, ref_var, inner),
            "rel": float(mean_d.mean() / m), "rel_se": float(np.sqrt(np.mean(se ** 2)) / m),
            "max_abs_z_mean": float(np.max(np.abs(mean_d / se))), "seeds": k}


def run_case(case):
    """Row of one (scene, material): references, timing, equal-time renders; row[kind] holds the
    errors against the primary reference (baked when traced, else file), row[kind]["vs"][ref]
    those against each reference, row["refs"][ref] each reference's mean, noise and spp."""
    a = case.args
    inner = inner_mask(a.size)
    refs = {w: case.reference(w) for w in a.refs}
    primary = "baked" if "baked" in refs else "file"
    ref, ref_var, var1 = refs[primary]
    t = case.timing()
    per = t["per_spp"]
    spp = {k: max(4, int(round(a.spp * per["principled"] / per[k]))) if k != "principled" else a.spp for k in a.kinds}
    ref_info = {w: {"mean": float(r[0][inner].mean()), "noise": float(np.mean(r[1][inner])),
                    "spp": int(round(float(np.median(r[2][r[1] > 0] / r[1][r[1] > 0])))),
                    "per_sample_var": float(np.mean(r[2][inner]))} for w, r in refs.items()}
    row = {"scene": case.scene, "name": case.name, "primary": primary, "refs": ref_info,
           "mean": ref_info[primary]["mean"], "ref_noise": ref_info[primary]["noise"],
           "ref_spp": ref_info[primary]["spp"], "ref_per_sample_var": ref_info[primary]["per_sample_var"],
           "per_spp": per, "wall_per_spp": t["wall_per_spp"], "spp": spp, "load": t["load"],
           "fit_version": case.fit_version, "carry": case.carry.name if case.carry else None}
    if "file" in refs and "baked" in refs:       # the baked tables' own error against the file
        (b, bv, _), (f_, fv, _) = refs["baked"], refs["file"]
        row["baked_vs_file"] = {"rel": float((b[inner].mean() - f_[inner].mean()) / f_[inner].mean()),
                                "rel_se": float(np.sqrt(np.sum((bv + fv)[inner].mean(-1))) / inner.sum() / f_[inner].mean()),
                                "mse": float(np.mean((b - f_)[inner] ** 2) - np.mean(bv[inner]) - np.mean(fv[inner]))}
    for kind in a.kinds:
        seeds = a.osl_seeds if kind in ("osl", "osl_fixed") else a.seeds
        secs = []

        def make():
            imgs, s = case.cycles(kind, spp[kind], seeds)
            secs.extend(s)
            return imgs
        imgs = case.saved(f"{kind}_{spp[kind]}", make)
        vs = {w: errors(imgs, r[0], r[1], inner) for w, r in refs.items()}
        row[kind] = dict(vs[primary], vs=vs)
        row[kind]["per_sample_var"] = row[kind]["noise"] * spp[kind]
        row[kind]["render_s"] = float(np.mean([w for w, _ in secs])) if secs else None
        row[kind]["render_cpu_s"] = float(np.mean([c for _, c in secs])) if secs else None
        for w, e in vs.items():
            log(f"{case.tag()} {kind} {spp[kind]} spp x {seeds} vs {w}: MSE {e['mse']:.3e} +- {e['mse_se']:.1e} "
                f"(noise {e['noise']:.2e} + bias2 {e['bias2']:.2e}), rms z {e['rms_z']:.2f}, "
                f"mean rel {e['rel']:+.4f} +- {e['rel_se']:.4f}")
    try:                        # (the fit may be refit while the run goes: its version at the end)
        row["fit_version_end"] = json.loads(Path(case.tables_path).with_name(
            Path(case.tables_path).stem + ".fit.json").read_text()).get("version")
    except Exception as e:      # noqa: BLE001
        row["fit_version_end"] = f"unreadable ({e})"
    row["settings"] = case.settings
    return row


def run_truesky(case):
    a = case.args
    inner = inner_mask(a.size)
    row = {"scene": "truesky", "name": case.name, "spp": a.ff_spp, "seeds": a.ff_seeds}
    means = {}
    for kind in ("osl", "svm", "principled", "diffuse"):
        secs = []

        def make():
            imgs, s = case.cycles(kind, a.ff_spp, a.ff_seeds)
            secs.extend(s)
            return imgs
        imgs = case.saved(f"{kind}_{a.ff_spp}", make)
        var = imgs.var(0, ddof=1)
        lum = imgs.mean(-1)
        row[kind] = {"var": float(np.mean(var[inner])), "var_max": float(var[inner].max()),
                     "max_pixel": float(imgs[:, inner].max()), "mean": float(imgs[:, inner].mean()),
                     "se": float(np.sqrt(np.sum(var[inner].mean(-1)) / a.ff_seeds) / inner.sum()),
                     "lum_var_max": float(lum.var(0, ddof=1)[inner].max()),
                     "render_s": float(np.mean([w for w, _ in secs])) if secs else None}
        means[kind] = row[kind]
        log(f"[truesky {case.name}] {kind} {a.ff_spp} spp x {a.ff_seeds}: pixel variance mean "
            f"{row[kind]['var']:.3e} max {row[kind]['var_max']:.3e}, max pixel {row[kind]['max_pixel']:.3g}, "
            f"sphere mean {row[kind]['mean']:.4f} +- {row[kind]['se']:.4f}")
    o, s = means["osl"], means["svm"]
    row["osl_svm_z"] = (o["mean"] - s["mean"]) / np.hypot(o["se"], s["se"])
    return row


# ------------------------------------------------------------------------------ report

LABEL = {"principled": "Principled (clock)", "osl": "OSL carried", "osl_fixed": "OSL fixed cells",
         "svm": "SVM", "fit": "fit"}


def equal_time_tables(rows, args):
    """The equal-time MSEs against each reference, per (scene, material) and back end; the ratio
    of each MSE to the best back end's; the carried-vs-fixed and SVM-vs-fit ratios; the
    references' own noise; the Cycles settings and fit versions."""
    f = lambda x: f"{x:.2e}"  # noqa: E731
    refs = [w for w in REFS if any(w in r.get("refs", {}) for r in rows)]
    settings = next((r["settings"] for r in rows if r.get("settings")), None)
    out = ["## Equal time: MSE against the measured file and the baked tables", "",
           "Per back end: CPU time per spp relative to Principled's (this run's timing); its spp at Principled's "
           f"cost of {args.spp} spp (x seeds); MSE of one render (mean over the seeds +- SE over them; net of the "
           "reference's noise) = bias^2 + noise; '/ best' = MSE / the smallest MSE of the row group's back ends. "
           "'OSL fixed cells': the OSL back end with the carry texture moved aside (what it renders without the "
           "carried blend). Against 'baked' (the CARRIED tables' eval) only OSL carried is unbiased; OSL fixed "
           "and SVM render the fixed cells, the fit its closures.", "",
           ("Cycles settings (Blender's factory render settings but denoising off and the box filter, hashed u): "
            if args.settings == "blender" else
            "Cycles settings (tests/cycles_scenes.reset; Blender's defaults differ, e.g. blur_glossy 1, "
            "light tree on): ") + (", ".join(f"{k} {v}" for k, v in settings.items()) if settings else "?") + ".", ""]
    head = "| scene | material | back end | time/spp vs Pr | spp x seeds | CPU s per render |"
    sep = "|---|---|---|---|---|---|"
    for w in refs:
        head += f" MSE vs {w} +- SE (bias^2 + noise) | / best ({w}) |"
        sep += "---|---|"
    out += [head, sep]
    for r in rows:
        kinds = [k for k in KINDS if k in r]
        best = {w: min(r[k]["vs"][w]["mse"] for k in kinds) for w in refs if w in r["refs"]}
        for k in kinds:
            seeds = r[k]["seeds"]
            line = (f"| {r['scene']} | {r['name']} | {LABEL[k]} | {r['per_spp'][k] / r['per_spp']['principled']:.2f} | "
                    f"{r['spp'][k]} x {seeds} | {r[k].get('render_cpu_s') or float('nan'):.1f} |")
            for w in refs:
                e = r[k]["vs"].get(w)
                if e is None:
                    line += " - | - |"
                    continue
                ratio = e["mse"] / best[w] if best[w] > 0 else float("nan")
                line += (f" {f(e['mse'])} +- {e['mse_se']:.1e} ({f(e['bias2'])} + {f(e['noise'])}) | "
                         f"{'**best**' if e['mse'] == best[w] else f'{ratio:.2f}'} |")
            out.append(line)
    out += ["", "Ratios (< 1: the first wins at equal time; +- from the seeds' SEs, first order):", "",
            "| scene | material |" + "".join(f" OSL carried / fixed vs {w} | SVM / fit vs {w} |" for w in refs)
            + " fit version (start/end) | load |",
            "|---|---|" + "---|---|" * len(refs) + "---|---|"]

    def ratio(r, a, b, w):
        if a not in r or b not in r or w not in r[a]["vs"]:
            return "-"
        x, y = r[a]["vs"][w], r[b]["vs"][w]
        q = x["mse"] / y["mse"]
        se = abs(q) * np.hypot(x["mse_se"] / x["mse"], y["mse_se"] / y["mse"])
        return f"{q:.2f} +- {se:.2f}"
    for r in rows:
        out.append(f"| {r['scene']} | {r['name']} |" + "".join(
            f" {ratio(r, 'osl', 'osl_fixed', w)} | {ratio(r, 'svm', 'fit', w)} |" for w in refs)
            + f" {r.get('fit_version')}/{r.get('fit_version_end')} | {r['load'][0]:.1f}-{r['load'][1]:.1f} |")
    out += ["", "References: sphere mean, spp, noise (per-pixel variance of the reference's mean, mean over the "
            "sphere: to compare with the MSEs above, of which it is netted out); baked vs file: sphere-mean "
            "relative difference and MSE (net of both noises) = the baked tables' own error.", "",
            "| scene | material |" + "".join(f" {w}: mean, spp, noise |" for w in refs) + " baked vs file: rel, MSE |"
            + " smallest back-end MSE / largest ref noise |",
            "|---|---|" + "---|" * len(refs) + "---|---|"]
    for r in rows:
        cells = "".join(f" {r['refs'][w]['mean']:.4f}, {r['refs'][w]['spp']}, {f(r['refs'][w]['noise'])} |"
                        if w in r["refs"] else " - |" for w in refs)
        bf = r.get("baked_vs_file")
        kinds = [k for k in KINDS if k in r]
        m = min(e["mse"] for k in kinds for e in r[k]["vs"].values())
        out.append(f"| {r['scene']} | {r['name']} |{cells} "
                   + (f"{bf['rel']:+.4f} +- {bf.get('rel_se', float('nan')):.4f}, {f(bf['mse'])}" if bf else "-")
                   + f" | {m / max(v['noise'] for v in r['refs'].values()):.0f} |")
    return out


def write(rows, ff_rows, geom, args, started):
    f = lambda x: f"{x:.2e}"  # noqa: E731
    lines = [
        "# Lights acceptance (issues 17 and 18): sphere in three lighting scenes, back ends vs the reference tracer",
        "",
        f"{args.size}x{args.size} px, box filter, perspective camera (scripts/cycles_acceptance.py's sphere, "
        f"256 x 128 UV mesh); bpy 5.0.1 Cycles CPU, 2 threads, world importance sampling 'AUTOMATIC'. "
        f"Tables: {'draft (32 x 32 cells, 8 theta bins, ideal tabulation)' if not args.tables_dir else args.tables_dir}. "
        + (f"Analysis {time.strftime('%Y-%m-%d %H:%M', time.localtime(started))} of the renders, references and "
         "timings saved by an earlier run (--reuse), " if args.reuse else
         f"Run {time.strftime('%Y-%m-%d %H:%M', time.localtime(started))}, {(time.time() - started) / 60:.0f} min, ")
        + "2 shared cores (load per row).", "",
        "- Scenes: **hdri** = cycles_acceptance's 'sunny' image; **sky** = Blender's default Sky Texture "
        f"(sun elevation {SKY['sun_elevation']}, rotation {SKY['sun_rotation']}, strength {SKY['strength']}) "
        f"rendered to a {args.sky_res[0]}x{args.sky_res[1]} image ({args.sky_spp} spp) by world.render_world, "
        "the SAME image as Cycles' world (Environment Texture, Closest) and the tracer's; **studio** = area lamp "
        f"(1 m, 150 W) + point lamp (radius 0.25, 100 W) + constant world {STUDIO_WORLD}.",
        "- References: bake/tracer, MIS on (lamps + world), tables sampling, scene from "
        "blender_addon/artist/validate.export_scene; material = **file**: the measured file's own eval (the manifest's "
        "RGL material), and/or **baked**: the baked tables' eval (carried where they carry: what OSL renders "
        "with its carry texture). MSEs are net of the reference's noise. The tables below the first two use "
        "the primary reference (baked when traced, else file).",
        "- Equal time: Principled at the base spp; each other back end at base spp x t_Pr/t_X, t = CPU time per "
        f"spp measured in this run ({args.t_rounds} interleaved rounds at {args.t_lo} and {args.t_hi} spp; "
        "scene sync excluded). OSL: Open Shading Language on; Principled, fit, SVM: off (SVM, Blender's "
        f"default); 'Pr(OSL)' is Principled with OSL on. Seeds: OSL {args.osl_seeds}, others {args.seeds}; "
        "MSE = mean over the seeds of one render's MSE; noise = per-pixel variance over the seeds; "
        "bias^2 = the seeds' mean vs the reference, net of noise.",
        "- Reference geometry: the analytic unit sphere; the exported mesh (what Cycles renders) differs "
        "from it by (sphere mean, same seed, " + "; ".join(
            f"{k} {g['name']} {g['spp']} spp: {g['rel']:+.5f} +- {g['se']:.5f}" for k, g in geom.items()) + ").",
        "- OSL/SVM vs tracer: per-pixel z of the seeds' mean (var from the seeds' spread: with K seeds "
        "rms z ~ sqrt((K-1)/(K-3)) if within MC error: 1.18 for 8, 1.73 for 4); sphere mean rel. diff +- SE.",
        ""] + equal_time_tables(rows, args) + [
        "", "## Acceptance details (primary reference)", "",
        "| scene | material | mean | ref spp (noise) | spp Pr/OSL/SVM/fit | CPU time per spp vs Pr: OSL / SVM / fit / Pr(OSL) | "
        "OSL rms z (\\|z\\|>3) [4x4 blocks] | OSL mean rel +- SE | SVM rms z [blocks] | SVM mean rel +- SE | "
        "MSE equal time: OSL | SVM | fit (bias^2 + noise) | Principled (bias^2 + noise) | OSL < fit, Pr | SVM < fit | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    old = [r for r in rows if all(k in r for k in ("principled", "osl", "svm", "fit"))]
    if not old:
        lines = lines[:-3]
    for r in old:
        p = r["per_spp"]
        o, s, ft, pr = r["osl"], r["svm"], r["fit"], r["principled"]
        ok = ("yes" if o["mse"] < ft["mse"] else "NO") + " / " + ("yes" if o["mse"] < pr["mse"] else "NO")
        ok_svm = "yes" if s["mse"] < ft["mse"] else "NO"
        lines.append(
            f"| {r['scene']} | {r['name']} | {r['mean']:.3f} | {r['ref_spp']} ({r['ref_noise']:.1e}) | "
            f"{r['spp']['principled']}/{r['spp']['osl']}/{r['spp']['svm']}/{r['spp']['fit']} | "
            f"{p['osl'] / p['principled']:.2f} (wall {r['wall_per_spp']['osl'] / r['wall_per_spp']['principled']:.2f}) / "
            f"{p['svm'] / p['principled']:.2f} / {p['fit'] / p['principled']:.2f} / "
            f"{p['principled_osl'] / p['principled']:.2f} | {o['rms_z']:.2f} ({o['frac3']:.3f}) [{o.get('block_z', float('nan')):.2f}] | "
            f"{o['rel']:+.4f} +- {o['rel_se']:.4f} | {s['rms_z']:.2f} [{s.get('block_z', float('nan')):.2f}] | "
            f"{s['rel']:+.4f} +- {s['rel_se']:.4f} | "
            f"{f(o['mse'])} | {f(s['mse'])} | {f(ft['mse'])} ({f(ft['bias2'])} + {f(ft['noise'])}) | "
            f"{f(pr['mse'])} ({f(pr['bias2'])} + {f(pr['noise'])}) | {ok} | {ok_svm} | "
            f"{r['load'][0]:.1f}-{r['load'][1]:.1f} |")
    lines += ["", "Noise per sample (per-pixel variance over the seeds x spp, mean over the sphere): what the "
              "equal-time MSEs come from. Tracer: plain Monte Carlo, one BSDF + one light sample per vertex "
              "(MIS); OSL/SVM: film-stratified u on camera rays; fit/Principled: Cycles' own QMC, NEE + BSDF.", "",
              "| scene | material | tracer (MIS) | OSL | SVM | fit | Principled | OSL / fit |",
              "|---|---|---|---|---|---|---|---|"] if old else []
    for r in old:
        v = {k: r[k].get("per_sample_var", r[k]["noise"] * r["spp"][k]) for k in ("principled", "osl", "svm", "fit")}
        lines.append(f"| {r['scene']} | {r['name']} | {f(r.get('ref_per_sample_var', float('nan')))} | "
                     f"{f(v['osl'])} | {f(v['svm'])} | {f(v['fit'])} | {f(v['principled'])} | "
                     f"{v['osl'] / v['fit']:.1f} |")
    if ff_rows:
        lines += ["", f"## Sun + sky with the real Sky Texture: fireflies ({args.ff_spp} spp, {args.ff_seeds} seeds, "
                  "equal spp)", "",
                  "Per-pixel variance over the seeds (mean over the sphere's interior, RGB); max pixel variance; "
                  "largest pixel value in any render. Issue 17: OSL within 3x Principled. OSL vs SVM: their "
                  "sphere means (both unbiased for the baked BSDF) in SEs.", "",
                  "| material | OSL var (max) | SVM var (max) | Principled var (max) | Diffuse var (max) | "
                  "OSL / Pr | max pixel OSL / SVM / Pr / Diffuse | OSL - SVM mean (z) | within 3x |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in ff_rows:
            o, s, p, d = r["osl"], r["svm"], r["principled"], r["diffuse"]
            ratio = o["var"] / p["var"]
            lines.append(
                f"| {r['name']} | {f(o['var'])} ({f(o['var_max'])}) | {f(s['var'])} ({f(s['var_max'])}) | "
                f"{f(p['var'])} ({f(p['var_max'])}) | {f(d['var'])} ({f(d['var_max'])}) | {ratio:.2f} | "
                f"{o['max_pixel']:.3g} / {s['max_pixel']:.3g} / {p['max_pixel']:.3g} / {d['max_pixel']:.3g} | "
                f"{o['mean'] - s['mean']:+.4f} ({r['osl_svm_z']:+.1f}) | {'yes' if ratio <= 3 else 'NO'} |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")
    (Path(args.work_dir) / "rows.json").write_text(json.dumps({"rows": rows, "fireflies": ff_rows, "geometry": geom}, indent=1,
                                              default=float))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("names", nargs="*", default=NAMES)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=256, help="Principled's spp (the equal-time clock)")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--osl-seeds", type=int, default=8)
    ap.add_argument("--t-lo", type=int, default=32)
    ap.add_argument("--t-hi", type=int, default=256)
    ap.add_argument("--t-rounds", type=int, default=4,
                    help="timing rounds (best of): with 2, Principled's time per spp varied 6.2-7.3 ms between runs")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--file-ref-spp", type=int, default=0, help="spp of the file's reference (default --ref-spp)")
    ap.add_argument("--reference", choices=("file", "baked", "both"), default="both",
                    help="tracer reference(s): the measured file's eval, the baked tables', or both")
    ap.add_argument("--kinds", default=",".join(KINDS), help="back ends at equal time (principled, the clock, always)")
    ap.add_argument("--geom-spp", type=int, default=128, help="tracer spp of the mesh-vs-sphere check (0: none)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--sky-res", type=int, nargs=2, default=(2048, 1024))
    ap.add_argument("--sky-spp", type=int, default=32)
    ap.add_argument("--ff-spp", type=int, default=64)
    ap.add_argument("--ff-seeds", type=int, default=8)
    ap.add_argument("--film-u", choices=("on", "off"), default="on",
                    help="the scene's 'Stratify camera samples' (off: hashed u, what the SVM graph takes under "
                         "Blender's default Blackman-Harris filter; these scenes use the box filter to match the tracer)")
    ap.add_argument("--settings", choices=("tests", "blender"), default="tests",
                    help="Cycles render settings: the tests' (cycles_scenes.reset) or Blender's factory ones "
                         "(denoising off, box filter kept, hashed u)")
    ap.add_argument("--tables-dir", default=None, help="use <dir>/<name>.exr when present (else draft tables)")
    ap.add_argument("--reuse", action="store_true", help="reuse saved renders, references and timings")
    ap.add_argument("--out", default=str(ROOT / "out" / "lights_acceptance.md"))
    ap.add_argument("--work-dir", default=str(OUT), help="folder of the renders (.npy), references, timings, "
                    "world images, draft tables and rows.json")
    args = ap.parse_args(argv)
    args.refs = REFS if args.reference == "both" else (args.reference,)
    args.kinds = ["principled"] + [k for k in args.kinds.split(",") if k and k != "principled"]
    unknown = set(args.kinds) - set(KINDS)
    if unknown:
        ap.error(f"unknown kinds {sorted(unknown)}: {', '.join(KINDS)}")
    factory = blender_settings() if args.settings == "blender" else None
    started = time.time()
    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    scenes = [s for s in args.scenes.split(",") if s]
    hdri = work / "env_sunny.exr"
    if not hdri.is_file():
        ca.make_env(hdri, "sunny")
    sky = None
    if {"sky", "truesky"} & set(scenes):
        sky = sky_image(work / f"sky_{args.sky_res[0]}x{args.sky_res[1]}.exr", *args.sky_res, args.sky_spp)
    setup = setups(hdri, sky)
    if factory is not None:
        setup = {k: _with_settings(v, factory) for k, v in setup.items()}
    if args.film_u == "off" or factory is not None:
        setup = {k: _film_off(v) for k, v in setup.items()}
    tables = {n: draft_tables(n, work / "tables", args.tables_dir) for n in args.names}
    rows, ff_rows, geom = [], [], {}
    for scene in scenes:
        for name in args.names:
            case = Case(scene, name, tables[name], setup[scene], args)
            try:
                if scene == "truesky":
                    ff_rows.append(run_truesky(case))
                else:
                    if args.geom_spp and scene not in geom:
                        geom[scene] = dict(case.geometry_check(args.geom_spp), name=name)
                    rows.append(run_case(case))
            except Exception as e:      # noqa: BLE001  (one failed case is a finding, not the end of the run)
                import traceback
                traceback.print_exc()
                log(f"{case.tag()} FAILED: {e}")
            write(rows, ff_rows, geom, args, started)
    log(f"done in {(time.time() - started) / 60:.1f} min: {args.out}")


if __name__ == "__main__":
    main()
