"""FlowBSDF's torch-free core: materials, domains, samplers, yardsticks, tables.

    open_material(spec)     a material (bake/materials/)
    open_sampler(kind, ..)  a sampler by name; the contract every sampler keeps (bake/sampler.py)
    open_tables(path)       baked tables (.exr) as a sampler (bake/tables.py)
    load_model(path)        a trained flow (.flow.npz) as a sampler (bake/flow.py)
"""
from .errors import FlowBSDFError
from .flow import load_model
from .materials import Material, open_material
from .sampler import Sampler, open_sampler
from .tables import open_tables

__all__ = ["FlowBSDFError", "Material", "Sampler", "load_model", "open_material", "open_sampler", "open_tables"]
