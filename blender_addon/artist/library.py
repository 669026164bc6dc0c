"""An asset library of measured materials: a folder of RGL `*.bsdf` / MERL `*.binary` files,
baked, as a .blend that Blender's Asset Browser opens (issue 54, item 6).

    flowbsdf library FOLDER --out DIR [--quality draft|preview|final]         (a Python with bake)
    blender -b --python-expr "import flowbsdf.batch as b; b.main()" -- library FOLDER --out DIR
        (the bake in the worker Python: --python PY, as the batch `bake`)

DIR then holds (add DIR in Preferences > File Paths > Asset Libraries; Blender's convention since 3.0:
a folder of .blend files with marked assets and the catalog file):
    manifest.toml               one entry per file (sources relative to DIR where inside its parent,
                                as the scene scan writes them), baked by the normal pipeline into
    tables/                     the tables, the node's textures and fit, <name>.preview.png
    library.blend               one material per file, named after it (its stem), bound to its tables
                                by a Learned BSDF node (node.assign_learned_bsdf), marked as an
                                asset: preview = the bake's preview (the reference tracer's exact
                                render of the tables, set as the ID's preview pixels: Blender's
                                own preview job would render the fit), description and tags
                                naming the file and its source, catalog FlowBSDF/<RGL|MERL>[/subfolder]
    blender_assets.cats.txt     the catalogs (existing lines kept; ids stable across runs)

Incremental: the bake skips current tables (pipeline.bake_manifest), the preview is remade only
when older than its tables, and a material is rebuilt only when its record (the tables' and
preview's hashes, its file, catalog, the add-on's shader) changed; when none did, library.blend
is not rewritten. Materials of files that left the folder are removed.

The module imports without bpy and numpy: listing the files and writing the manifest and catalog
need neither; `bake` needs numpy (the `bake` package), `build` needs bpy.
"""
import hashlib
import json
import os
import re
import sys
import uuid
from pathlib import Path

KINDS = {".bsdf": "RGL", ".binary": "MERL"}
# = props.BAKE_QUALITY (props imports bpy; tests/test_library.py checks they agree)
QUALITY = {
    "draft": {"resolution": 16, "tol": 0.5, "grid": 96, "samples": 2048, "first_bins": 3,
              "ideal_resolution": 48},
    "preview": {"tol": 0.05, "samples": 4096, "ideal_resolution": 128},
    "final": {},
}
MANIFEST_NAME = "manifest.toml"
BLEND_NAME = "library.blend"
CATALOG_FILE = "blender_assets.cats.txt"
CATALOG_ROOT = "FlowBSDF"
RECORD = "flowbsdf_library"         # a library material's custom property: what it was built from
NAME_RE = re.compile(r"[^A-Za-z0-9_.-]+")
CATALOG_HEADER = """# This is an Asset Catalog Definition file for Blender.
#
# Empty lines and lines starting with `#` will be ignored.
# The first non-ignored line should be the version indicator.
# Other lines are of the format "UUID:catalog/path/for/assets:simple catalog name"

VERSION 1
"""


class LibraryError(ValueError):
    """The folder cannot make a library; the message says why."""


def log_line(message):
    print(f"[library] {message}", flush=True)


# -- the files and the manifest (no numpy, no bpy) -------------------------------------------

def table_name(stem):
    """A file's name in the manifest and of its tables (pipeline names: letters, digits, _ . -)."""
    name = NAME_RE.sub("_", stem.strip()).strip("._-") or "material"
    return name if re.match(r"^[A-Za-z0-9_]", name) else "m_" + name


def measured_files(folder, out=None):
    """The measured files below `folder` (subfolders too; hidden ones and `out` left out), sorted."""
    folder, out = Path(folder).resolve(), Path(out).resolve() if out else None
    if not folder.is_dir():
        raise LibraryError(f"not a folder: {folder}")
    found = []
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and (out is None or Path(root, d).resolve() != out))
        found += [Path(root, f) for f in files if Path(f).suffix.lower() in KINDS and not f.startswith(".")]
    return sorted(found, key=lambda p: p.relative_to(folder).as_posix().lower())


def items_of(folder, out, quality="final"):
    """One dict per file: material (the Blender material's name: the file's stem), name (the
    manifest's), file, kind, catalog, tables, preview, quality. Raises LibraryError on two files
    of one name."""
    folder, out = Path(folder).resolve(), Path(out).resolve()
    if quality not in QUALITY:
        raise LibraryError(f"quality must be one of {', '.join(QUALITY)}, not {quality!r}")
    items, by_name = [], {}
    for path in measured_files(folder, out):
        kind = KINDS[path.suffix.lower()]
        sub = path.parent.relative_to(folder).parts
        item = {"material": path.stem, "name": table_name(path.stem), "file": path, "kind": kind,
                "catalog": "/".join((CATALOG_ROOT, kind) + sub), "quality": quality,
                "tables": out / "tables" / f"{table_name(path.stem)}.exr",
                "preview": out / "tables" / f"{table_name(path.stem)}.preview.png"}
        for key in ("material", "name"):
            other = by_name.get((key, item[key].lower()))
            if other is not None:
                raise LibraryError(f"{other['file']} and {path} would both be material {item[key]!r}: rename one")
            by_name[(key, item[key].lower())] = item
        items.append(item)
    if not items:
        raise LibraryError(f"no measured files (*.bsdf, *.binary) in {folder}")
    return items


def _portable(path, base):
    """`path` relative to the manifest's folder `base` when inside base's parent (the library and
    its files move together), else absolute (as blender_addon/artist/scan.py's _portable)."""
    try:
        rel = os.path.relpath(path, base).replace(os.sep, "/")
    except ValueError:              # another drive (Windows)
        return str(path)
    return str(path) if rel.startswith("../../") else rel


def _toml(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + " }"
    return json.dumps(str(v))


def manifest_text(items, out):
    lines = ["# FlowBSDF manifest written by `flowbsdf library` (one material per measured file);",
             "# regenerated on each run. library.blend holds the materials.", ""]
    for item in items:
        lines += [f"# {item['kind']} file {item['file'].name}: Blender material {item['material']!r}",
                  "[[material]]", f"name = {_toml(item['name'])}",
                  f"source = {_toml(_portable(item['file'], out))}",
                  f"bake = {_toml({**QUALITY[item['quality']], 'carry': True})}", ""]
    return "\n".join(lines)


def _write_if_changed(path, text):
    """Write `text` (atomically) unless the file holds it already; returns True when written."""
    path = Path(path)
    if path.is_file() and path.read_text(encoding="utf-8") == text:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return True


def write_manifest(items, out):
    path = Path(out).resolve() / MANIFEST_NAME
    _write_if_changed(path, manifest_text(items, path.parent))
    return path


def catalog_id(path):
    """A catalog's UUID: the same for the same path on every run and machine."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"flowbsdf-catalog:{path}"))


def read_catalogs(out):
    """{catalog path: UUID} of DIR's catalog file (empty without one)."""
    path = Path(out) / CATALOG_FILE
    found = {}
    if path.is_file():
        for line in path.read_text(encoding="utf-8").splitlines():
            line = line.strip()
            if not line or line.startswith("#") or line.startswith("VERSION"):
                continue
            parts = line.split(":", 2)
            if len(parts) >= 2:
                found.setdefault(parts[1], parts[0])
    return found


def write_catalogs(out, paths):
    """Add the catalogs `paths` (and their parents) to DIR's blender_assets.cats.txt in
    Blender's format (`VERSION 1`, then `UUID:path:simple name` lines), keeping its other lines
    and ids. Returns {catalog path: UUID}."""
    file = Path(out) / CATALOG_FILE
    known = read_catalogs(out)
    text = file.read_text(encoding="utf-8") if file.is_file() else CATALOG_HEADER
    wanted = sorted({"/".join(p.split("/")[:k]) for p in paths for k in range(1, len(p.split("/")) + 1)})
    new = [p for p in wanted if p not in known]
    if new:
        text = text.rstrip("\n") + "\n\n" + "".join(f"{catalog_id(p)}:{p}:{p.replace('/', '-')}\n" for p in new)
        _write_if_changed(file, text)
        known.update({p: catalog_id(p) for p in new})
    return {p: known[p] for p in wanted}


def prepare(folder, out, quality="final"):
    """List the files and write DIR/manifest.toml: (items, manifest path)."""
    items = items_of(folder, out, quality)
    return items, write_manifest(items, out)


# -- the bake (numpy: the `bake` package) ---------------------------------------------------

def bake(manifest_path, out, log=print):
    """Bake the manifest's materials with the pipeline (current tables skipped), then each one's
    preview (remade only when older than its tables). Returns the names that failed (their
    messages logged); the others are baked."""
    from bake.errors import FlowBSDFError
    from bake.plumbing.manifest import load_manifest
    from bake.io.paths import table_path
    from bake.plumbing.pipeline import bake_manifest
    from .worker_main import write_preview
    manifest = load_manifest(manifest_path)
    failed = set()

    def relay(line):
        m = re.match(r"\[fail\] ([^:]+):", line)
        if m:
            failed.add(m.group(1))
        log(line)
    try:
        bake_manifest(manifest, out, log=relay)
    except FlowBSDFError:
        if not failed:
            raise
    for entry in manifest.materials:
        if entry.name not in failed:
            try:
                write_preview(entry, manifest, out, table_path(out, entry.name), log=log)
            except Exception as e:      # noqa: BLE001  (the asset then has no preview of its own)
                log(f"[fail] {entry.name}: no preview: {e}")
    return sorted(failed)


# -- library.blend (bpy) ---------------------------------------------------------------------

def _hash(path):
    path = Path(path)
    if not path.is_file():
        return ""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _record(item, out, catalog):
    from ..render import derived, osl_script
    shader = osl_script.source_hash() if osl_script.osl_compiler_available() else ""
    return {"file": item["file"].name, "kind": item["kind"], "source": _portable(item["file"], out),
            "name": item["name"], "catalog": item["catalog"], "catalog_id": catalog,
            "tables_hash": _hash(item["tables"]), "preview_hash": _hash(item["preview"]),
            "shader": shader, "fit_version": derived.FIT_VERSION, "quality": item["quality"]}


def _ensure_registered():
    import bpy
    if not hasattr(bpy.types.Scene, "flowbsdf"):
        import importlib
        importlib.import_module(__package__.rpartition(".")[0]).register()


def _set_preview(mat, path):
    """The asset's preview from the PNG: the ID's preview pixels (Blender keeps what is set
    here: a user-edited preview is not re-rendered, and it is saved with the file)."""
    import bpy
    preview = mat.preview_ensure()
    if not Path(path).is_file():
        return False
    image = bpy.data.images.load(str(path), check_existing=False)
    try:
        for size, attr in ((128, "image"), (32, "icon")):
            image.scale(size, size)
            setattr(preview, f"{attr}_size", (size, size))
            setattr(preview, f"{attr}_pixels_float", image.pixels[:])
    finally:
        bpy.data.images.remove(image)
    return True


def _describe(mat, item, record, catalog):
    data = mat.asset_data
    data.description = (f"{item['file'].name}: measured {item['kind']} BSDF, baked by FlowBSDF "
                        f"({item['quality']} tables; exact in Cycles through the Learned BSDF node). "
                        f"Source: {record['source']} (relative to the library's folder)")
    data.catalog_id = catalog
    while len(data.tags):
        data.tags.remove(data.tags[0])
    for tag in ("FlowBSDF", "measured", item["kind"], item["file"].name):
        data.tags.new(tag, skip_if_exists=True)


def _learned_settings(mat, item):
    """The material's FlowBSDF settings (the add-on's panel, a re-bake in another project)."""
    s = getattr(mat, "flowbsdf", None)
    if s is None:
        return
    s.enabled, s.source_kind, s.filepath = True, "FILE", str(item["file"])
    s.name, s.bake_quality = item["name"], item["quality"].upper()


def _remove(mat):
    import bpy
    from ..render import binding
    trees = {n.node_tree for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeGroup"
             and n.node_tree is not None and binding.TREE_KEY in n.node_tree.keys()} if mat.node_tree else set()
    bpy.data.materials.remove(mat)
    for tree in trees:
        if tree.users == 0:
            bpy.data.node_groups.remove(tree)


def build(items, out, log=log_line):
    """Write (or update) DIR/library.blend: one asset material per item. Returns the names of
    the materials (re)built or removed; none when the file was current (then not rewritten).
    Opens the library in this Blender session (the open file is replaced)."""
    import bpy
    from ..render import binding, node, osl_script
    _ensure_registered()
    out = Path(out).resolve()
    blend = out / BLEND_NAME
    existed = blend.is_file()
    if existed:
        bpy.ops.wm.open_mainfile(filepath=str(blend), load_ui=False)
    else:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        out.mkdir(parents=True, exist_ok=True)
        _save(blend)                    # saved first: the node stores paths relative to it
    catalogs = write_catalogs(out, [i["catalog"] for i in items])
    changed = []
    wanted = {i["material"] for i in items}
    for mat in [m for m in bpy.data.materials if m.library is None and RECORD in m.keys() and m.name not in wanted]:
        changed.append(mat.name)
        log(f"{mat.name}: its file left the folder: removed")
        _remove(mat)
    for item in items:
        name, catalog = item["material"], catalogs[item["catalog"]]
        record = _record(item, out, catalog)
        mat = bpy.data.materials.get(name)
        if mat is not None and mat.library is None and mat.asset_data is not None and RECORD in mat.keys() \
                and json.loads(mat[RECORD]) == record:
            log(f"{name}: current")
            continue
        if not item["tables"].is_file():
            log(f"{name}: no tables ({item['tables']}): left out")
            continue
        if mat is None:
            mat = bpy.data.materials.new(name)
        group = node.assign_learned_bsdf(mat, item["name"], item["tables"])
        if mat.asset_data is None:
            mat.asset_mark()
        mat.use_fake_user = True
        _describe(mat, item, record, catalog)
        _learned_settings(mat, item)
        has_preview = _set_preview(mat, item["preview"])
        mat[RECORD] = json.dumps(record, sort_keys=True)
        changed.append(name)
        tree = group.node_tree
        ends = [e for e, on in (("OSL", tree.nodes.get(osl_script.SCRIPT) is not None), ("SVM", binding.has_svm(tree)),
                                ("fit", True)) if on]
        problems = binding.read(tree).get("problems")
        log(f"{name}: {'updated' if existed else 'added'} (back ends {' + '.join(ends)}; "
            f"{'preview from the bake' if has_preview else 'no preview'}; catalog {item['catalog']}"
            f"{'; problems: ' + problems if problems else ''})")
    if existed and not changed:
        log(f"{blend} is current: not rewritten")
        return []
    _save(blend)
    log(f"wrote {blend} ({len(items)} material(s), {len(changed)} changed)")
    return changed


def _save(blend):
    """Save as `blend`, compressed (each node's compiled OSL shader is megabytes of text), without a
    .blend1 backup (the library folder holds the library only)."""
    import bpy
    paths = bpy.context.preferences.filepaths
    versions = paths.save_version
    paths.save_version = 0
    try:
        bpy.ops.wm.save_as_mainfile(filepath=str(blend), compress=True, relative_remap=True)
    finally:
        paths.save_version = versions


def blender_args(folder, out, quality, python=None, blender="blender", blend_only=False):
    """The command (a list) that writes library.blend with a background Blender: the batch
    `library` command, the bake in `python` first unless blend_only (the tables baked already)."""
    addon = Path(__file__).resolve().parents[1]          # the add-on's folder (this module is in artist/)
    expr = (f"import sys; sys.path.insert(0, {json.dumps(str(addon.parent))}); "
            f"import {addon.name}.batch as b; b.main()")
    return [blender, "-b", "--factory-startup", "--python-expr", expr, "--", "library",
            str(Path(folder).resolve()), "--out", str(Path(out).resolve()), "--quality", quality,
            "--python", str(python or sys.executable)] + (["--blend-only"] if blend_only else [])


def blender_command(folder, out, quality, python=None):
    """The command that writes library.blend with Blender (where this Python has no bpy)."""
    import shlex
    return " ".join(shlex.quote(a) for a in blender_args(folder, out, quality, python))


def have_bpy():
    try:
        import bpy  # noqa: F401
        return True
    except ImportError:
        return False


def main(folder, out, quality="final", blend=True, log=log_line, bake_log=print):
    """`flowbsdf library`: manifest, bake, previews, then library.blend in this process where bpy
    imports, else the Blender command that writes it. Raises FlowBSDFError when a material
    failed to bake (after the library is written with the others)."""
    from bake.errors import FlowBSDFError
    try:
        items, manifest = prepare(folder, out, quality)
    except LibraryError as e:
        raise FlowBSDFError(str(e)) from None
    log(f"{len(items)} measured file(s) in {Path(folder).resolve()}; manifest {manifest}")
    failed = bake(manifest, out, log=bake_log)
    items = [i for i in items if i["name"] not in failed]
    if not blend:
        log("library.blend not written (--no-blend)")
    elif have_bpy():
        build(items, out, log=log)
        log(f"asset library: {Path(out).resolve()} (add it in Preferences > File Paths > Asset Libraries)")
    else:
        log("this Python has no bpy: write library.blend with Blender:")
        print(blender_command(folder, out, quality), flush=True)
    if failed:
        raise FlowBSDFError(f"{len(failed)} material(s) failed to bake, left out of the library: {', '.join(failed)}")
