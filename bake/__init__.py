"""FlowBSDF's torch-free runtime (numpy only; Blender loads it): materials, samplers, tables,
yardsticks, the commands. One folder per kind:

    core/        the samplers and what they stand on: flow, tables, ideal, baselines, warps
    export/      what Blender's Cycles back ends read: OSL and SVM textures, closure fit, world map
    quality/     yardsticks, reports, benchmarks, the stress suite
    plumbing/    the `flowbsdf` command, manifests, jobs, farm tasks, files
    materials/   measured and analytic BSDFs
    tracer/      the reference path tracer
    errors.py    FlowBSDFError, the one error type of every folder
    formats.py   the version numbers of the files and graphs (numpy, the OSL shader and the add-on read them)

The public API:

    open_material(spec)     a material (bake/materials/)
    open_sampler(kind, ..)  a sampler by name; the contract every sampler keeps (bake/core/sampler.py)
    open_tables(path)       baked tables (.exr) as a sampler (bake/core/tables.py)
    load_model(path)        a trained flow (.flow.npz) as a sampler (bake/core/flow.py)
"""
from .core.flow import load_model
from .core.sampler import Sampler, open_sampler
from .core.tables import open_tables
from .errors import FlowBSDFError
from .materials import Material, open_material

__all__ = ["FlowBSDFError", "Material", "Sampler", "load_model", "open_material", "open_sampler", "open_tables"]
