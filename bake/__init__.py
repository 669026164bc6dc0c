"""FlowBSDF's torch-free runtime (numpy only; Blender loads it): materials, samplers, tables,
yardsticks, the commands. One folder per kind, in layers: a module imports its own layer and
those below it, never one above (tests/test_layers.py), bottom first:

    errors.py    FlowBSDFError, the one error type of every folder
    io/          files: OpenEXR, atomic writes and hashes, output paths, progress, threads
    maths/       what materials and samplers share: directions, warps, special functions, the C path
    formats.py   the version numbers of the files and graphs (numpy, the OSL shader and the add-on read them)
    materials/   measured and analytic BSDFs
    core/        the samplers and what they stand on: flow, tables, ideal, baselines, metrics
    export/      what Blender's Cycles back ends read: OSL and SVM textures, closure fit, world map
    quality/     reports, benchmarks, the stress suite
    tracer/      the reference path tracer
    plumbing/    the `flowbsdf` command, manifests, jobs, the bake pipeline, farm tasks
    __init__.py  this face: the public API below

The public API:

    open_material(spec)     a material (bake/materials/)
    open_sampler(kind, ..)  a sampler by name; the contract every sampler keeps (bake/core/sampler.py)
    open_tables(path)       baked tables (.exr) as a sampler (bake/core/table_files.py)
    load_model(path)        a trained flow (.flow.npz) as a sampler (bake/core/flow.py)
"""
from .core.flow import load_model
from .core.sampler import Sampler, open_sampler
from .core.table_files import open_tables
from .errors import FlowBSDFError
from .materials import Material, open_material

__all__ = ["FlowBSDFError", "Material", "Sampler", "load_model", "open_material", "open_sampler", "open_tables"]
