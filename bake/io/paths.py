"""Where an output folder keeps a manifest entry's products (the layout: bake/plumbing/pipeline.py)."""
import os
import sys
from pathlib import Path


def model_path(out_dir, name):
    """OUT/models/<name>.flow.npz. A model that an older `flowbsdf train --out OUT` left in OUT itself
    (its --out was the models folder then) is moved there first, with its checkpoints, saying so
    on stderr: every reader of a model finds it, and the folder has one layout from then on."""
    path = Path(out_dir) / "models" / f"{name}.flow.npz"
    old = Path(out_dir) / path.name
    if old.is_file() and not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(old, path)
        except FileNotFoundError:       # another process moved it first
            return path
        checkpoints = old.with_name(f"{name}.train")
        if checkpoints.is_dir() and not (path.parent / checkpoints.name).exists():
            os.replace(checkpoints, path.parent / checkpoints.name)
        print(f"[models] moved {old} to {path} (and its checkpoints): an older `flowbsdf train --out "
              f"{out_dir}` put it there; models are in {path.parent} now", file=sys.stderr, flush=True)
    return path


def table_path(out_dir, name):
    return Path(out_dir) / "tables" / f"{name}.exr"
