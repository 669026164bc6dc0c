"""The reference path tracer (numpy only): renders scenes with any BSDF sampler -- baked
tables, the flow, the ideal tabulation, a fitted GGX lobe, cosine -- and compares them. It renders
the samplers it is handed: bake/plumbing/scene_samplers.py opens them from an output folder, and
bake/plumbing/tracer_commands.py is `flowbsdf render` and `flowbsdf compare`.

    scene.py       scene files (TOML/JSON; format in its docstring), built-in scenes
    meshes.py      OBJ and PLY loaders, the shader ball (analytic pieces and as a mesh)
    accel.py       ray intersection: triangle BVH, analytic spheres, planes, lathe pieces
    lights.py      environment (image, procedural sky, constant; importance sampled) and
                   Blender's lamps (point, spot, sun, area) with Cycles' radiometry
    integrator.py  wavefront path tracer: MIS (power heuristic) or BSDF-only, Russian roulette
    compare.py     reference vs samplers at equal spp and equal time: EXR, PNG, MSE/MAE/SSIM
    images.py      EXR/PNG files, tone mapping, false colour, metrics
    label.py       text in images without a font library (labelled panels)
"""
from .integrator import render
from .scene import builtin_scene, load_scene

__all__ = ["render", "builtin_scene", "load_scene"]
