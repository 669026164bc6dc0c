"""Where the add-on finds FlowBSDF's numpy runtime (`bake`).

The extension zip vendors it as `vendor/bake` (scripts/build_extension.py); in a development
checkout the repository's `bake` package is importable directly.
"""
try:
    from .vendor import bake  # noqa: F401  (extension zip)
except ImportError:
    import bake  # noqa: F401  (development checkout / venv)
