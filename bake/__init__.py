"""FlowBSDF's torch-free core: materials, domains, samplers, yardsticks, tables."""
from .errors import FlowBSDFError
from .materials import Material, open_material

__all__ = ["FlowBSDFError", "Material", "open_material"]
