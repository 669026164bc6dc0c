"""FlowBSDF's torch-free core: materials, domains, samplers, yardsticks, tables."""
from .errors import FlowBSDFError
from .materials import Material, open_material
from .flow import load_model

__all__ = ["FlowBSDFError", "Material", "open_material"]
