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
A table file is hashed once and opened at most once for all of them (`TableFile`: its `digest`
and its `tables`, opened on first use), whichever of them are stale.
The world map (world_map.py) is made from a rendered world, not from tables: the add-on names its
file, and it offers write_world_texture and read_world_meta.
"""
from functools import cached_property
from pathlib import Path

from ..core.table_files import open_tables
from ..errors import FlowBSDFError
from ..io.files import file_hash
from . import carry_export, closure_fit, osl_export, svm_export


class TableFile:
    """A table file as the exporters take it: its path, its content hash (`digest`, read once) and
    its Tables (`tables`, opened on first use, then kept; or the ones the caller already opened)."""

    def __init__(self, path, tables=None):
        self.path = Path(path)
        if not self.path.is_file():
            raise FlowBSDFError("table file not found", self.path)
        self.digest = file_hash(self.path)
        if tables is not None:
            self.tables = tables

    @cached_property
    def tables(self):
        return open_tables(self.path)

    @property
    def carried(self):
        """Whether the tables' meta says some intervals carry (they need carry_export's texture)."""
        return self.tables.meta.get("carried") is not None


def table_file(tables):
    """A TableFile of a path, or the TableFile given."""
    return tables if isinstance(tables, TableFile) else TableFile(tables)


def ensure(exporter, tables, material=None, log=None):
    """The exporter's file of a table file (a path or a TableFile), written when missing, stale or
    broken; files of the same tables named after another hash (older contents) are removed.
    Returns its path."""
    source = table_file(tables)
    tables_path, digest = source.path, source.digest
    path = exporter.path(tables_path, digest)
    if not exporter.is_current(path, digest):
        note = exporter.write(path, tables_path, source.tables, digest, material=material)
        if log:
            log(f"[{exporter.KIND}] wrote {path}" + (f" {note}" if note else ""))
    if digest[:12] in path.name:
        for old in tables_path.parent.glob(f"{tables_path.stem}.{exporter.KIND}*-*.exr"):
            if old.name != path.name:
                old.unlink(missing_ok=True)
    return path


def ensure_osl_export(tables, log=None):
    """The OSL texture of a table file (osl_export), (re)built when missing, stale or broken; returns its path."""
    return ensure(osl_export, tables, log=log)


def ensure_svm_export(tables, log=None):
    """The SVM texture of a table file (svm_export), (re)built when missing, stale or broken; returns its path."""
    return ensure(svm_export, tables, log=log)


def ensure_fit(tables, material=None, log=None):
    """The closure fit of a table file (<stem>.fit.json beside it, closure_fit), rebuilt when missing,
    of an older version or made from other table contents. Returns its path. `material` (the
    measured file the tables were baked from): the fit's error is measured against it (else
    against the tables)."""
    return ensure(closure_fit, tables, material=material, log=log)


def ensure_carry_export(tables, material, log=None):
    """The carry texture of a table file whose meta says which intervals carry (carry_export, made
    from `material`, the file the tables were baked from), rebuilt when missing or stale; None
    (and no carry texture left beside them) for tables that do not carry."""
    source = table_file(tables)
    if not source.carried:
        for old in source.path.parent.glob(f"{source.path.stem}.{carry_export.KIND}*-*.exr"):
            old.unlink(missing_ok=True)
        return None
    return ensure(carry_export, source, material=material, log=log)


def derived_current(tables):
    """Whether every file bake_derived makes beside a table file (a path or a TableFile) is there
    and current (the main job's bake stage is current only then: a bake whose exports failed, or
    were made by an older layout, is redone)."""
    source = table_file(tables)
    exporters = [svm_export, osl_export, closure_fit] + ([carry_export] if source.carried else [])
    return all(e.is_current(e.path(source.path, source.digest), source.digest) for e in exporters)


def bake_derived(tables_path, material=None, log=None):
    """What the Blender node needs beside a table file: its SVM texture, the carried blend's texture
    (given the material it was baked from, where the tables' meta says which intervals carry),
    its OSL texture and its closure fit, each rebuilt only when missing or stale. Called by the
    bake pipeline; returns (OSL texture, fit)."""
    from concurrent.futures import ThreadPoolExecutor
    source = TableFile(tables_path)
    source.tables       # (opened once, before the threads share it)
    # The fit, most of the time, in a thread beside the textures; its line after theirs.
    lines = []
    with ThreadPoolExecutor(1, thread_name_prefix="flowbsdf-fit") as fitting:
        fit = fitting.submit(ensure_fit, source, material=material, log=lines.append if log else None)
        ensure_svm_export(source, log=log)
        if material is not None:
            ensure_carry_export(source, material, log=log)
        osl = ensure_osl_export(source, log=log)
        fit = fit.result()
    for line in lines:
        log(line)
    return osl, fit
