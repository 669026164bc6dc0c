"""`flowbsdf bake`: tables for the materials a manifest lists, rebuilt only when their inputs change.

Layout of an output folder:
    <out>/models/<name>.flow.npz     trained flows (flowbsdf train --out <out>; an older train's
                                     <out>/<name>.flow.npz is moved here: io/paths.model_path)
    <out>/tables/<name>.exr          baked tables (flowbsdf bake)
    <out>/tables/<name>.osl<layout>-<hash>.exr, <name>.svm<layout>-<hash>.exr, <name>.fit.json,
      <name>.match.exr (isotropic)   what the Blender node reads beside them (bake/export/osl_export.py,
                                     bake/export/svm_export.py, bake/export/closure_fit.py)
A table file records the hash of its inputs (material content, model file, bake settings,
table format); a bake whose inputs hash matches the file on disk is skipped, any change
rebuilds it, and a stale file is never used (`open_current_tables`).
"""
import hashlib
import json
import time
from dataclasses import replace

from ..core.sampler import open_sampler
from ..core.settings import BakeSettings
from ..core.table_files import open_tables
from ..errors import FlowBSDFError
from ..formats import BUILDER, FORMAT
from ..io.files import file_hash, remove_stale_temps
from ..io.paths import model_path, table_path

BUILDER_VERSION = BUILDER     # bake/formats.py (a module global: tests bump it)


def bake_settings(entry, manifest_path):
    """The entry's `[bake]` table as BakeSettings (checked: bake/core/settings.py)."""
    return BakeSettings.from_table(entry.bake, f"material {entry.name!r}", manifest_path)


def inputs_of(material, settings, model_file):
    """What a table depends on, and its hash."""
    inputs = {"material": material.fingerprint(), "settings": settings.inputs(),
              "model": file_hash(model_file) if model_file else None,
              "format": FORMAT, "builder": BUILDER_VERSION}
    return inputs, hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()


def _changed(old, new):
    """What differs between a table file's recorded inputs and today's (inputs_of), in words."""
    if not isinstance(old, dict):
        return "its inputs are not recorded"
    words = {"material": "the material", "settings": "the bake settings", "model": "the trained model",
             "format": f"the table format {old.get('format')} -> {new['format']}",
             "builder": f"the table builder {old.get('builder')} -> {new['builder']}"}
    return ", ".join(words.get(k, k) for k in new if old.get(k) != new[k]) + " changed"


def tables_use_model(settings):
    """Whether the tables are built from the material's trained model: only with source "flow".
    "auto" and "ideal" build them from the ideal tabulation (f·cos tabulated per incident angle):
    the source only places the cells (their masses are integrated from the true f·cos either
    way), and the ideal placed them as well or better (cc_nothern_aurora at theta_i 60-85: rv
    1.5-4x lower) in a third to a fifth of the time (29-59 s vs 101-212 s; session 20)."""
    return settings.source == "flow"


def _tables_model(entry, settings, out_dir):
    """The model file the entry's tables are built from (source "flow"), else None."""
    return model_path(out_dir, entry.name) if tables_use_model(settings) else None


def wants_model(entry, material, settings, out_dir):
    """Whether baking this entry needs a model that is not there yet (training comes first)."""
    model_file = _tables_model(entry, settings, out_dir)
    return material.isotropic and model_file is not None and not model_file.is_file()


def _choose_source(material, settings, model_file):
    from ..core.ideal import IdealSampler
    if model_file is not None:
        from ..core.flow import load_model
        return load_model(model_file), "flow"
    return IdealSampler(material, resolution=settings.ideal_resolution), "ideal"


def bake_entry(entry, out_dir, manifest_path, force=False, log=print):
    """Bake one manifest entry; returns (path, 'baked' | 'current')."""
    from ..core.planner import plan_tables
    settings = bake_settings(entry, manifest_path)
    material = entry.open()
    model_file = _tables_model(entry, settings, out_dir)
    if model_file is not None and not model_file.is_file():
        raise FlowBSDFError(f"material {entry.name!r}: bake source 'flow' but no model at {model_file} "
                            f"(`flowbsdf train {manifest_path} --material {entry.name} --out {out_dir}` writes it)")
    inputs, digest = inputs_of(material, settings, model_file)
    path = table_path(out_dir, entry.name)
    if not force and path.is_file():
        try:
            old = open_tables(path).meta
            if old.get("inputs_hash") == digest:
                return path, "current"
            log(f"[bake] {entry.name}: {path} is out of date ({_changed(old.get('inputs'), inputs)}): baking it again")
        except FlowBSDFError:
            pass       # unreadable or foreign: rebuild it
    source, used = _choose_source(material, settings, model_file)
    t0 = time.perf_counter()
    tables = plan_tables(material, source, replace(settings, carry=settings.carry and carriable(material)),
                         log=lambda s: log(f"[bake] {entry.name}: {s}"))
    # Nothing of the run (its time, the machine) goes into the file: the same inputs give the
    # same bytes, so the textures named by the file's hash and the node graphs built on them
    # stay current across re-bakes and machines.
    tables.meta.update(material=entry.name, source=used, inputs=inputs, inputs_hash=digest, nbytes=tables.nbytes)
    remove_stale_temps(path)
    tables.save(path)
    log(f"[bake] {entry.name}: tables in {time.perf_counter() - t0:.1f} s")
    return path, "baked"


def carriable(material):
    """Whether the material's tables can be carried along its own coordinates (bake/core/carried.py)."""
    from ..core.carried import check_carriable
    try:
        check_carriable(material)
        return True
    except FlowBSDFError:
        return False


def bake_with_derived(entry, out_dir, manifest_path, force=False, log=print):
    """bake_entry, then what the Blender node needs beside the tables (OSL and SVM textures,
    closure fit, the carried blend's texture: derived.bake_derived)."""
    from ..export.derived import bake_derived
    path, status = bake_entry(entry, out_dir, manifest_path, force=force, log=log)
    bake_derived(path, material=entry.open(), log=log)
    return path, status


def bake_manifest(manifest, out_dir, name=None, force=False, log=print):
    """Bake every selected entry (tables, then their OSL and SVM textures and closure fit); returns the
    table paths written. Failures are reported per material and raised together at the end,
    so one bad material does not stop the rest."""
    written, failures = [], []
    for entry in manifest.select(name, log=log):
        try:
            path, status = bake_with_derived(entry, out_dir, manifest.path, force=force, log=log)
        except FlowBSDFError as e:
            failures.append(f"{entry.name}: {e}")
            log(f"[fail] {entry.name}: {e}")
            continue
        if status == "current":
            log(f"[skip] {entry.name}: {path} is up to date")
        elif status == "baked":
            log(f"[wrote] {path}")
            written.append(path)
    if failures:
        raise FlowBSDFError(f"{len(failures)} material(s) failed to bake: " + "; ".join(failures),
                            manifest.path)
    return written


def open_current_tables(entry, out_dir, manifest_path):
    """The entry's tables if they exist and match its current inputs; None otherwise."""
    path = table_path(out_dir, entry.name)
    if not path.is_file():
        return None
    settings = bake_settings(entry, manifest_path)
    model_file = _tables_model(entry, settings, out_dir)
    if model_file is not None and not model_file.is_file():
        return None
    _, digest = inputs_of(entry.open(), settings, model_file)
    tables = open_tables(path)
    return tables if tables.meta.get("inputs_hash") == digest else None


class StaleTables(FlowBSDFError):
    """The baked tables are there but were built from other inputs than the current ones."""


def open_baked(kind, entry, material, out_dir, manifest_path=None):
    """The sampler `kind` (bake/core/sampler.py) of a manifest entry, its file read from `out_dir`:
    "tables" current only (StaleTables when the material, model or bake settings changed since),
    "flow" the trained model; the kinds that need no file as open_sampler opens them."""
    if kind == "tables":
        path = table_path(out_dir, entry.name)
        if not path.is_file():
            raise FlowBSDFError(f"no baked tables for {entry.name!r} (run flowbsdf bake)", path)
        if open_current_tables(entry, out_dir, manifest_path) is None:
            raise StaleTables(f"the tables of {entry.name!r} are stale (the material, model or "
                              "bake settings changed): run flowbsdf bake", path)
        return open_sampler("tables", material, path)
    if kind == "flow":
        path = model_path(out_dir, entry.name)
        if not path.is_file():
            raise FlowBSDFError(f"no trained flow for {entry.name!r} (run flowbsdf train); "
                                "the flow sampler is not available for it", path)
        return open_sampler("flow", material, path)
    return open_sampler(kind, material)
