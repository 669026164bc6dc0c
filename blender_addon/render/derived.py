"""The files the bake writes beside a table file that the node reads: the closure fit
(<name>.fit.json), the OSL texture (<name>.osl<LAYOUT>-<hash>.exr), the carried blend's texture and
the SVM texture, found by their content-hashed names without numpy (Debian's Blender 3.4); made
or refreshed by `bake` (deps.bake_module) where it imports."""
import json
from pathlib import Path

from .. import deps

# The fit file format (bake/export/closure_fit.py: load_fit, FIT_VERSION), read here without numpy.
FIT_FORMAT = "flowbsdf-closure-fit"
# The versions of bake/formats.py (deps.formats: read without numpy). OSL_LAYOUT: the OSL texture's
# layout, part of its file name; CARRY_LAYOUT the carried blend's texture's; READABLE_FIT_VERSIONS the
# fits the node renders: a version 6 fit (3 lobes, no tilts) or 7 (no EEVEE fit: EEVEE renders the
# fit's closures, anisotropy dropped) until `upgrade` refits it
_FORMATS = deps.formats()
OSL_LAYOUT, CARRY_LAYOUT = _FORMATS.OSL_LAYOUT, _FORMATS.CARRY_LAYOUT
FIT_VERSION, READABLE_FIT_VERSIONS = _FORMATS.FIT_VERSION, _FORMATS.READABLE_FIT_VERSIONS
fit_current = _FORMATS.fit_current


# sha256 of a file's bytes: bake/io/files.py's, read by its path (deps.files: without numpy)
file_hash = deps.files().file_hash


def load_fit(path):
    """The closure fit in a <name>.fit.json file (json only, no numpy); raises ValueError."""
    path = Path(path)
    try:
        fit = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"closure fit not found: {path}") from None
    except (OSError, ValueError) as e:
        raise ValueError(f"closure fit unreadable ({e}): {path}") from None
    if not isinstance(fit, dict) or fit.get("format") != FIT_FORMAT or fit.get("version") not in READABLE_FIT_VERSIONS:
        raise ValueError(f"not a current FlowBSDF closure fit, re-bake: {path}")
    for key in ("x", "diffuse", "specular", "roughness", "anisotropy", "rel_error", "cv"):
        if key not in fit:
            raise ValueError(f"closure fit without {key!r}: {path}")
    for key in ("x", "diffuse", "specular", "roughness", "anisotropy"):     # the EEVEE fit's (FIT_VERSION 8)
        if "eevee" in fit and key not in fit["eevee"]:
            raise ValueError(f"closure fit's EEVEE fit without {key!r}: {path}")
    if fit.get("match") and path.with_name(fit["match"]).is_file():
        fit["match_path"] = str(path.with_name(fit["match"]))      # the SVM control variate's match image
    return fit


def fit_file(tables_path):
    """The fit file beside a table file when it is current (its tables_hash matches, of
    FIT_VERSION), else the one `bake` (re)makes, else (no numpy) one of an older readable
    version made from these tables, else a ValueError saying why."""
    path = tables_path.with_name(tables_path.stem + ".fit.json")
    digest = file_hash(tables_path)
    older = False
    try:
        fit = load_fit(path)
        if fit.get("tables_hash") == digest and fit_current(fit.get("version"), fit.get("anisotropic", False)):
            return path
        older = fit.get("tables_hash") == digest
        why = f"closure fit of version {fit.get('version')}" if older else \
            f"closure fit stale (made from other tables): {path}"
    except ValueError as e:
        why = str(e)
    closure_fit = deps.bake_module("export.derived")
    if closure_fit is None:
        if older:
            return path         # rendered as it is (the version it says): refitting needs numpy
        raise ValueError(f"{why}; re-bake (refitting needs numpy, absent in this Blender)")
    return closure_fit.ensure_fit(tables_path)


def osl_texture(tables_path):
    """The OSL texture of a table file: made or refreshed by `bake` where it imports, else the
    one the bake wrote (its name carries the tables' hash: bake/export/osl_export.export_path)."""
    osl_export = deps.bake_module("export.derived")
    error = None
    if osl_export is not None:
        try:
            return str(osl_export.ensure_osl_export(tables_path))
        except Exception as e:      # noqa: BLE001  (e.g. no OpenEXR here: try the baked file)
            error = e
    path = texture_path(tables_path, file_hash(tables_path))
    if path.is_file():
        return str(path)
    raise ValueError(str(error) if error else f"OSL texture not exported (re-bake): {path}")


def texture_path(tables_path, digest):
    """The OSL texture's name beside the tables (bake/export/osl_export.export_path, without numpy)."""
    return tables_path.with_name(f"{tables_path.stem}.osl{OSL_LAYOUT}-{digest[:12]}.exr")


def carry_texture(tables_path):
    """The carried blend's texture the bake wrote beside a table file (its name carries the tables'
    hash: bake/export/carry_export.export_path), or "" (tables that do not carry, or not yet baked)."""
    tables_path = Path(tables_path)
    if not tables_path.is_file():
        return ""
    path = tables_path.with_name(f"{tables_path.stem}.carry{CARRY_LAYOUT}-{file_hash(tables_path)[:12]}.exr")
    return str(path) if path.is_file() else ""


def svm_texture(tables_path):
    """The SVM texture of a table file, made or refreshed by `bake` (bake/export/svm_export.py)."""
    return str(deps.bake_module("export.derived").ensure_svm_export(tables_path))


def is_current(tables_path):
    """Whether a table file's fit and OSL texture exist and were made from its contents."""
    tables_path = Path(tables_path)
    digest = file_hash(tables_path)
    try:
        fit_ok = load_fit(tables_path.with_name(tables_path.stem + ".fit.json")).get("tables_hash") == digest
    except ValueError:
        return False
    return fit_ok and texture_path(tables_path, digest).is_file()
