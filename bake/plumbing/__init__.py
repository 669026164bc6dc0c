"""Commands, jobs and files: what runs the core on a manifest and writes the results.

    cli            the `flowbsdf` command (python -m bake.plumbing.cli)
    manifest       the manifest: which materials, how to model them
    job            the main job (train, bake, report, render, page) and its stamps
    pipeline       baking a manifest's tables (and their Cycles exports) from models
    farm           the same on a render farm (Open Job Description templates, farm tasks)
    progress       progress lines with time-left estimates
    files          atomic writes, file hashes
    exrio          OpenEXR reading and writing
"""
