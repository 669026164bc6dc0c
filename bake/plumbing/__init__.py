"""Commands, jobs and files: what runs the core on a manifest and writes the results.

    cli            the `flowbsdf` command (python -m bake.plumbing.cli)
    manifest       the manifest: which materials, how to model them
    job            the main job, `flowbsdf run`: train, bake, report, render, then one page
    pipeline       `flowbsdf bake`: a manifest's tables (and what Blender reads beside them),
                   rebuilt only when their inputs change
    farm           the same on a render farm (Open Job Description templates, farm tasks)
    progress       progress lines with time-left estimates
    files          atomic writes, file hashes
    exrio          OpenEXR reading and writing
"""
