"""Commands and jobs: what runs the layers below on a manifest and an output folder (the top layer).

    cli              the `flowbsdf` command (python -m bake.plumbing.cli)
    manifest         the manifest: which materials, how to model them
    job              the main job, `flowbsdf run`: train, bake, report, render, then one page
    pipeline         `flowbsdf bake`: a manifest's tables (and what Blender reads beside them),
                     rebuilt only when their inputs change; an entry's current files as samplers
    reports          `flowbsdf report`: the speed-vs-error report of a manifest's materials
    scene_samplers   a sampler per scene material, from an output folder (render, compare, the job)
    tracer_commands  `flowbsdf render` and `flowbsdf compare` (the reference tracer)
    farm             the same on a render farm (Open Job Description templates, farm tasks)
"""
