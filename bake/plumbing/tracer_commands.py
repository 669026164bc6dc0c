"""`flowbsdf render` and `flowbsdf compare`: the reference tracer (bake/tracer/) on a scene, its
manifest materials sampled from an output folder (registered by bake/plumbing/cli.py)."""
from pathlib import Path

from ..core.sampler import RENDER_KINDS, canonical_kind
from ..errors import FlowBSDFError


def _scene(args):
    from ..tracer.scene import builtin_scene, load_scene
    from .manifest import load_manifest

    def manifest():         # read when the scene names a manifest material
        return load_manifest(args.manifest)
    if args.scene.startswith("builtin:"):
        scene = builtin_scene(args.scene[len("builtin:"):], material=args.material, manifest=manifest,
                              width=args.width or 128, height=args.height or 128)
    else:
        if args.material:
            raise FlowBSDFError("--material applies to built-in scenes only (scene files name their materials)")
        scene = load_scene(args.scene, manifest=manifest)
        if args.width:
            scene.camera.width = args.width
        if args.height:
            scene.camera.height = args.height
    return scene


def cmd_render(args):
    import time
    from ..tracer.compare import _prepare
    from ..tracer.images import write_exr
    from ..tracer.integrator import render
    from .scene_samplers import scene_samplers
    scene = _scene(args)
    cam = scene.camera
    print(f"[render] {args.scene}: {cam.width}x{cam.height}, sampler {args.sampler}, "
          f"{'MIS' if args.mis else 'BSDF sampling only'}")
    t0 = time.perf_counter()
    samplers = scene_samplers(scene, args.sampler, args.tables_dir)
    _prepare(samplers)
    print(f"[render] samplers ready in {time.perf_counter() - t0:.1f}s")
    last = [0.0]

    def progress(k, elapsed, st):
        if elapsed - last[0] >= 2.0 or (args.time is None and k == args.spp):
            last[0] = elapsed
            goal = f"/{args.spp}" if args.time is None else f" ({elapsed:.0f}/{args.time:.0f}s)"
            print(f"[render] {k}{goal} spp, {elapsed:.1f}s, {st.paths / st.seconds:,.0f} paths/s, "
                  f"BSDF sampling {st.sampling_share:.0%} of the time", flush=True)

    img, var, st = render(scene, samplers, spp=args.spp, seconds=args.time, mis=args.mis, seed=args.seed,
                          progress=progress, workers=args.workers)
    write_exr(args.out, img, {"flowbsdf_sampler": args.sampler, "flowbsdf_spp": st.extra["spp"],
                              "flowbsdf_mis": args.mis})
    print(f"[wrote] {args.out}: {st.extra['spp']} spp, {st.paths:,} paths, {st.rays:,} rays in "
          f"{st.seconds:.1f}s; lost BSDF samples {st.lost}")


def cmd_compare(args):
    from ..tracer.compare import compare
    from .scene_samplers import scene_samplers
    scene = _scene(args)
    names = [canonical_kind(s.strip()) for s in args.samplers.split(",") if s.strip()]
    bad = [s for s in names if s not in RENDER_KINDS]
    if bad:
        raise FlowBSDFError(f"unknown sampler(s) {', '.join(bad)} (choose from {', '.join(RENDER_KINDS)})")
    compare(scene, names, args.spp, args.reference_spp, args.out, lambda name: scene_samplers(scene, name, args.tables_dir),
            reference_sampler=args.reference_sampler, mis=args.mis, equal_time=not args.no_equal_time, seed=args.seed,
            workers=args.workers)
    print((Path(args.out) / "metrics.md").read_text())
    print(f"[wrote] {args.out}/: reference.exr, <sampler>_spp.exr, <sampler>_time.exr, compare.png, "
          "metrics.md, metrics.csv")


def add_commands(sub):
    def common(c):
        c.add_argument("scene", help="a scene file (.toml/.json) or builtin:shaderball-env | builtin:shaderball-point")
        c.add_argument("--material", help="built-in scenes: the manifest material on the ball")
        c.add_argument("--manifest", default="manifest.toml", help="where manifest materials come from")
        c.add_argument("--tables-dir", default="out", help="folder with tables/ and models/ (default out)")
        c.add_argument("--spp", type=int, default=16, help="samples per pixel")
        mode = c.add_mutually_exclusive_group()
        mode.add_argument("--mis", dest="mis", action="store_true", default=True,
                          help="light + BSDF sampling, power heuristic (default)")
        mode.add_argument("--bsdf-only", dest="mis", action="store_false", help="BSDF sampling only")
        c.add_argument("--width", type=int, help="override the image width")
        c.add_argument("--height", type=int, help="override the image height")
        c.add_argument("--seed", type=int, default=0)
        c.add_argument("--workers", type=int, default=1, help="processes (forked; the image does not change)")

    r = sub.add_parser("render", help="render a scene with the reference path tracer")
    common(r)
    r.add_argument("--sampler", default="tables", type=canonical_kind, choices=RENDER_KINDS)
    r.add_argument("--time", type=float, help="render whole passes for this many seconds instead of --spp")
    r.add_argument("--out", required=True, help="output image (.exr)")
    r.set_defaults(func=cmd_render)
    c = sub.add_parser("compare", help="samplers against a converged reference (equal spp and equal time)")
    common(c)
    c.add_argument("--samplers", default="tables,ggx,ideal,cosine", help="comma-separated")
    c.add_argument("--reference-spp", type=int, default=1024)
    c.add_argument("--reference-sampler", default="ideal", type=canonical_kind, choices=RENDER_KINDS)
    c.add_argument("--no-equal-time", action="store_true", help="skip the equal-time renders")
    c.add_argument("--out", default="out/compare", help="output folder")
    c.set_defaults(func=cmd_compare)
