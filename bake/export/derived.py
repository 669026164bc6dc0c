"""What the Blender node needs beside a table file (`bake_derived`), and the exporter contract every
file made from a table file keeps. Written like the sampler contract (bake/core/sampler.py).

An exporter is a module (osl_export, svm_export, carry_export, closure_fit) with

    KIND                          its name in file names and log lines ("osl", "svm", "carry", "fit")
    path(tables_path, digest)     where its file for a table file of content hash `digest` lives
                                  (beside the tables; the textures carry the hash in their names)
    is_current(path, digest)      whether that file is there, readable, of the exporter's current
                                  layout and made from tables of that hash
    read(path)                    the file's contents (a texture: (image, meta); the fit: its dict);
                                  FlowBSDFError if it is not one
    write(path, tables_path, tables, digest, material=None) -> note or None
                                  write it (atomically) from the opened tables (`material`: the file
                                  they were baked from, where the exporter needs it); the note goes
                                  into the log line

Exporters import none of each other (what two of them share sits below them: guides.py) and
nothing of this module: `ensure` keeps any of them current, and `bake_derived` makes all of them.
The world map (world_map.py) is made from a rendered world, not from tables: the add-on names its
file, and it offers write_world_texture and read_world_meta.
"""
from pathlib import Path

from ..core.tables import open_tables
from ..errors import FlowBSDFError
from ..io.files import file_hash
from . import carry_export, closure_fit, osl_export, svm_export


def ensure(exporter, tables_path, material=None, log=None):
    """The exporter's file of a table file, written when missing, stale or broken; files of the
    same tables named after another hash (older contents) are removed. Returns its path."""
    tables_path = Path(tables_path)
    if not tables_path.is_file():
        raise FlowBSDFError("table file not found", tables_path)
    digest = file_hash(tables_path)
    path = exporter.path(tables_path, digest)
    if not exporter.is_current(path, digest):
        note = exporter.write(path, tables_path, open_tables(tables_path), digest, material=material)
        if log:
            log(f"[{exporter.KIND}] wrote {path}" + (f" {note}" if note else ""))
    if digest[:12] in path.name:
        for old in tables_path.parent.glob(f"{tables_path.stem}.{exporter.KIND}*-*.exr"):
            if old.name != path.name:
                old.unlink(missing_ok=True)
    return path


def ensure_osl_export(tables_path, log=None):
    """The OSL texture of a table file (osl_export), (re)built when missing, stale or broken; returns its path."""
    return ensure(osl_export, tables_path, log=log)


def ensure_svm_export(tables_path, log=None):
    """The SVM texture of a table file (svm_export), (re)built when missing, stale or broken; returns its path."""
    return ensure(svm_export, tables_path, log=log)


def ensure_fit(tables_path, material=None, log=None):
    """The closure fit of a table file (<stem>.fit.json beside it, closure_fit), rebuilt when missing,
    of an older version or made from other table contents. Returns its path. `material` (the
    measured file the tables were baked from): the fit's error is measured against it (else
    against the tables)."""
    return ensure(closure_fit, tables_path, material=material, log=log)


def ensure_carry_export(tables_path, material, log=None):
    """The carry texture of a table file whose meta says which intervals carry (carry_export, made
    from `material`, the file the tables were baked from), rebuilt when missing or stale; None
    (and no carry texture left beside them) for tables that do not carry."""
    tables_path = Path(tables_path)
    if open_tables(tables_path).meta.get("carried") is None:
        for old in tables_path.parent.glob(f"{tables_path.stem}.{carry_export.KIND}*-*.exr"):
            old.unlink(missing_ok=True)
        return None
    return ensure(carry_export, tables_path, material=material, log=log)


def derived_current(tables_path):
    """Whether every file bake_derived makes beside a table file is there and current (the main
    job's bake stage is current only then: a bake whose exports failed, or were made by an older
    layout, is redone)."""
    tables_path = Path(tables_path)
    digest = file_hash(tables_path)
    exporters = [svm_export, osl_export, closure_fit]
    if open_tables(tables_path).meta.get("carried") is not None:
        exporters.append(carry_export)
    return all(e.is_current(e.path(tables_path, digest), digest) for e in exporters)


def bake_derived(tables_path, material=None, log=None):
    """What the Blender node needs beside a table file: its SVM texture, the carried blend's texture
    (given the material it was baked from, where the tables' meta says which intervals carry),
    its OSL texture and its closure fit, each rebuilt only when missing or stale. Called by the
    bake pipeline; returns (OSL texture, fit)."""
    ensure_svm_export(tables_path, log=log)
    if material is not None:
        ensure_carry_export(tables_path, material, log=log)
    return ensure_osl_export(tables_path, log=log), ensure_fit(tables_path, material=material, log=log)
