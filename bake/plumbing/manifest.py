"""The manifest (`manifest.toml`): which materials a scene needs, and how to model them.

    [defaults]                      # optional; applies to every material
    domain = "auto"                 # "auto" (slope or disk, from the material) | "disk" | "spherical" | "slope"
    train = { preset = "balanced" } # settings for the trainer
    bake = { }                      # settings for the baker

    [[material]]
    name = "paper_white"                                  # letters, digits, _, - and . (not first)
    source = "../shared/data/rgl/paper_white_rgb.bsdf"    # a file, or a table (see open_material)
    optional = true                 # a missing source file skips the material with a note
    domain = "spherical"            # overrides the default
    train = { preset = "fast" }     # merged over defaults.train

    [run]                           # optional: the main job (`flowbsdf run`, bake/plumbing/job.py)
    max_materials = 3               # only the first 3 materials whose source is present
    report = { samples = 16384 }    # the speed-vs-error report (bake.plumbing.job.REPORT_DEFAULTS)
    render = { size = 96, spp = 32 }    # the shader-ball renders (bake.plumbing.job.RENDER_DEFAULTS)

Relative paths resolve against the manifest's folder. Source paths may name environment
variables: `$NAME`, `${NAME}`, and `${NAME:-default}` (NAME when set and not empty, else the
default), e.g. "${FLOWBSDF_RGL_DIR:-../shared/data/rgl}/chm_mint_rgb.bsdf".
"""
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..core.domains import DOMAINS
from ..errors import FlowBSDFError
from ..materials import open_material

MATERIAL_KEYS = {"name", "source", "domain", "optional", "train", "bake"}
DEFAULT_KEYS = {"domain", "train", "bake"}
TOP_KEYS = {"material", "defaults", "run"}
RUN_KEYS = {"max_materials", "report", "render"}
NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
ENV_DEFAULT_RE = re.compile(r"\$\{(\w+):-([^}]*)\}")


def expand_env(path):
    """A source path with its environment variables substituted (see the module's docstring)."""
    path = ENV_DEFAULT_RE.sub(lambda m: os.environ.get(m.group(1)) or m.group(2), path)
    return os.path.expandvars(path)


def _expand_source(source):
    if isinstance(source, str):
        return expand_env(source)
    if isinstance(source.get("path"), str):
        return {**source, "path": expand_env(source["path"])}
    return source


@dataclass
class MaterialEntry:
    name: str
    source: object
    domain: str = "auto"
    optional: bool = False
    train: dict = field(default_factory=dict)
    bake: dict = field(default_factory=dict)
    base_dir: Path = Path(".")

    def source_path(self):
        """The source file, if the source is a file (directly or as a table's path)."""
        path = self.source if isinstance(self.source, str) else (
            self.source.get("path") if isinstance(self.source, dict) else None)
        if path is None:
            return None
        path = Path(path).expanduser()
        return path if path.is_absolute() else self.base_dir / path

    def missing(self):
        """True when the source is a file that is not there."""
        path = self.source_path()
        return path is not None and not path.is_file()

    def open(self):
        return open_material(self.source, base_dir=self.base_dir)


@dataclass
class Manifest:
    path: Path
    materials: list
    run: dict = field(default_factory=dict)

    def select(self, name=None, skip_missing=True, log=print):
        """The entries to work on: one by name, or all; optional ones whose file is absent
        are skipped with a note."""
        chosen = self.materials
        if name is not None:
            chosen = [m for m in self.materials if m.name == name]
            if not chosen:
                raise FlowBSDFError(f"no material named {name!r} (have: "
                                    f"{', '.join(m.name for m in self.materials)})", self.path)
        out = []
        for entry in chosen:
            if skip_missing and entry.optional and entry.missing():
                log(f"[skip] {entry.name}: optional source {entry.source_path()} not found")
                continue
            out.append(entry)
        return out


def _check_keys(table, allowed, where, path):
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise FlowBSDFError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} "
                            f"{', '.join(map(repr, unknown))} (allowed: {', '.join(sorted(allowed))})", path)


DOMAIN_CHOICES = ("auto", *sorted(DOMAINS))


def _check_domain(value, where, path):
    if value not in DOMAIN_CHOICES:
        raise FlowBSDFError(f"{where}: domain must be one of {list(DOMAIN_CHOICES)}, not {value!r}", path)
    return value


def _check_table(value, key, where, path):
    if not isinstance(value, dict):
        raise FlowBSDFError(f"{where}: {key!r} must be a table, not {type(value).__name__}", path)
    return dict(value)


def load_manifest(path):
    path = Path(path)
    if not path.is_file():
        raise FlowBSDFError("manifest not found", path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise FlowBSDFError("manifest is not UTF-8 text", path) from None
    except tomllib.TOMLDecodeError as e:
        raise FlowBSDFError(f"not valid TOML: {e}", path) from None
    _check_keys(data, TOP_KEYS, "top level", path)
    defaults = _check_table(data.get("defaults", {}), "defaults", "top level", path)
    _check_keys(defaults, DEFAULT_KEYS, "[defaults]", path)
    default_domain = _check_domain(defaults.get("domain", "auto"), "[defaults]", path)
    default_train = _check_table(defaults.get("train", {}), "train", "[defaults]", path)
    default_bake = _check_table(defaults.get("bake", {}), "bake", "[defaults]", path)

    run = _check_table(data.get("run", {}), "run", "top level", path)
    _check_keys(run, RUN_KEYS, "[run]", path)
    limit = run.get("max_materials")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 1):
        raise FlowBSDFError(f"[run]: max_materials must be a positive integer, not {limit!r}", path)
    for key in ("report", "render"):
        if key in run:
            run[key] = _check_table(run[key], key, "[run]", path)

    entries = data.get("material", [])
    if not isinstance(entries, list) or not entries:
        raise FlowBSDFError("no [[material]] entries", path)
    materials, seen = [], set()
    for i, entry in enumerate(entries, 1):
        if not isinstance(entry, dict):
            raise FlowBSDFError(f"material #{i} must be a table", path)
        name = entry.get("name")
        where = f"material #{i}" + (f" ({name!r})" if isinstance(name, str) else "")
        _check_keys(entry, MATERIAL_KEYS, where, path)
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise FlowBSDFError(f"{where}: needs a 'name' of letters, digits, '_', '.' or '-'", path)
        if name in seen:
            raise FlowBSDFError(f"{where}: the name {name!r} is used twice", path)
        seen.add(name)
        source = entry.get("source")
        if not isinstance(source, (str, dict)):
            raise FlowBSDFError(f"{where}: needs a 'source': a file path or a table", path)
        optional = entry.get("optional", False)
        if not isinstance(optional, bool):
            raise FlowBSDFError(f"{where}: 'optional' must be true or false", path)
        materials.append(MaterialEntry(
            name=name, source=_expand_source(source),
            domain=_check_domain(entry.get("domain", default_domain), where, path),
            optional=optional,
            train={**default_train, **_check_table(entry.get("train", {}), "train", where, path)},
            bake={**default_bake, **_check_table(entry.get("bake", {}), "bake", where, path)},
            base_dir=path.resolve().parent))
    return Manifest(path=path, materials=materials, run=run)
