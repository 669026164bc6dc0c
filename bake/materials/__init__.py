"""Materials: anything that evaluates a BSDF f(wi, wo) (RGB, without the cosine).

`open_material(spec)` accepts
  - a path to an RGL `.bsdf` file or a MERL `.binary` file,
  - a table: {kind = "rgl" | "merl", path = ...},
             {kind = "analytic", model = ..., ...} (see `analytic.from_spec`),
             {kind = "python", callable = "module:function", isotropic = true},
  - a Material (returned as is).
Relative paths resolve against `base_dir` (the manifest's folder).
"""
import hashlib
import importlib
from pathlib import Path

import numpy as np

from ..errors import FlowBSDFError
from .base import Material, as_dirs


def open_material(spec, base_dir=None, name=None):
    if isinstance(spec, Material):
        return spec
    if isinstance(spec, (str, Path)):
        path = _resolve(spec, base_dir)
        suffix = path.suffix.lower()
        if suffix == ".bsdf":
            spec = {"kind": "rgl", "path": path}
        elif suffix in (".binary", ".merl"):
            spec = {"kind": "merl", "path": path}
        else:
            raise FlowBSDFError("unknown material file type (expected .bsdf or .binary)", path)
    if not isinstance(spec, dict):
        raise FlowBSDFError(f"a material source must be a path or a table, not {type(spec).__name__}")
    kind = spec.get("kind")
    if kind == "rgl":
        from .rgl import RGLMaterial
        return RGLMaterial(_resolve(_require(spec, "path"), base_dir))
    if kind == "merl":
        from .merl import MERLMaterial
        return MERLMaterial(_resolve(_require(spec, "path"), base_dir))
    if kind == "analytic":
        from .analytic import from_spec
        return from_spec(spec)
    if kind == "python":
        return PythonMaterial(_require(spec, "callable"), bool(spec.get("isotropic", False)))
    raise FlowBSDFError(f"unknown material kind {kind!r}; expected rgl, merl, analytic or python")


def _require(spec, key):
    if key not in spec:
        raise FlowBSDFError(f"material source of kind {spec.get('kind')!r} needs a {key!r} entry")
    return spec[key]


def _resolve(path, base_dir):
    path = Path(path).expanduser()
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    if not path.is_file():
        raise FlowBSDFError("material file not found", path)
    return path


class PythonMaterial(Material):
    """A user's BSDF: `module:function` with f(wi, wo) -> (N, 3)."""

    def __init__(self, target, isotropic):
        module_name, _, func_name = str(target).partition(":")
        if not module_name or not func_name:
            raise FlowBSDFError(f"callable {target!r} must look like 'module:function'")
        try:
            func = getattr(importlib.import_module(module_name), func_name)
        except (ImportError, AttributeError) as e:
            raise FlowBSDFError(f"cannot load callable {target!r}: {e}") from None
        if not callable(func):
            raise FlowBSDFError(f"{target!r} is not callable")
        self.func, self.target, self.isotropic = func, target, isotropic
        self.name = func_name

    def eval(self, wi, wo):
        wi, wo = as_dirs(wi, wo)
        value = np.asarray(self.func(wi, wo), dtype=np.float64)
        if value.shape != (len(wo), 3):
            raise FlowBSDFError(f"callable {self.target!r} returned shape {value.shape}, expected ({len(wo)}, 3)")
        above = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        return np.where(above[:, None], value, 0.0)

    def fingerprint(self):
        return hashlib.sha256(f"python:{self.target}:{self.isotropic}".encode()).hexdigest()


__all__ = ["Material", "open_material", "as_dirs", "PythonMaterial"]
