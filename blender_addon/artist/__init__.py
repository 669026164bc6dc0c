"""The artist side: the panel, its operators and the jobs they start; the batch command and the
asset library drive the same steps. Imports the render side, never the other way round.
    props      FlowBSDF data on materials/scenes     scan      what the scene needs -> manifest
    prefs      the Python that bakes and trains      worker    subprocess jobs, progress, cancel
    operators  the panel's operators                 jobs      scan -> worker -> bind nodes
    panels     Shader Editor sidebar + Material tab  uitext    long texts wrapped to the region
    validate   reference tracer vs Cycles            library   a folder of files -> asset library
    worker_main  the worker (outside Blender, run as a script: no add-on imports)
    farm/      the Flamenco job type (the farm's side of `batch farm`)
"""
