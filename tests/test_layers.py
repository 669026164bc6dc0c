"""The house's layers: no module imports a module of a higher layer, and no import circles.

Every import is read with `ast`, the ones inside functions included (a deferred import is still a
tie between two modules: it only hides the circle from Python's import machinery). Layers are
declared once below, bottom first; a module may import its own layer or lower ones. A package's
`__init__.py` is its face: it sits on top of what it re-exports, and importing `pkg.mod` does not
count as importing `pkg/__init__.py` (Python runs it, but it ties nothing). bake/ never imports
the add-on or the trainer (it is the bottom of the repository).

blender_addon's face is two modules: `__init__.py` (registration) and `batch.py`, the command
line (`blender -b f.blend --python-expr "import flowbsdf.batch as b; b.main()" -- bake`), which
farms run by that name: job bundles written by `flowbsdf farm openjd` (bake/plumbing/farm.py),
the Flamenco job type (artist/farm/flowbsdf_bake.js) and docs/farm.md all spell it, so it stays
where it is, on top of both sides, rather than moving into artist/.

bake/formats.py (the version numbers of the files and graphs: plain Python, no imports) sits in the
bottom layer beside errors.py: numpy, the OSL headers' test and the add-on (by its path, without
numpy: deps.formats) all read it.
"""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# (root package, [(layer name, [path prefixes relative to the repo])], bottom first). A module belongs
# to the first layer, bottom up, with a prefix of its path.
LAYERS = {
    "bake": [
        ("errors, formats", ["bake/errors.py", "bake/formats.py"]),
        ("io", ["bake/io/"]),
        ("maths", ["bake/maths/"]),
        ("materials", ["bake/materials/"]),
        ("core", ["bake/core/"]),
        ("export, quality, tracer", ["bake/export/", "bake/quality/", "bake/tracer/"]),
        ("plumbing", ["bake/plumbing/"]),
        ("face", ["bake/__init__.py"]),
    ],
    "blender_addon": [
        ("deps", ["blender_addon/deps.py"]),
        ("render", ["blender_addon/render/"]),
        ("artist", ["blender_addon/artist/"]),
        ("face", ["blender_addon/__init__.py", "blender_addon/batch.py"]),
    ],
}
FORBIDDEN = {"bake": ("blender_addon", "trainer", "scripts", "tests")}


def modules(root):
    """{dotted name: path} of every .py file under ROOT/root (vendored copies left out)."""
    out = {}
    for path in sorted((ROOT / root).rglob("*.py")):
        rel = path.relative_to(ROOT)
        if "vendor" in rel.parts:
            continue
        parts = list(rel.with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imports_of(name, path, known):
    """The dotted names of the modules `name` imports (absolute, resolved against `known`; others
    are returned as written so that the forbidden roots can be checked)."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            for alias in node.names:  # `from pkg import mod` imports the submodule pkg.mod
                sub = f"{target}.{alias.name}"
                found.add(sub if sub in known else target)
    return {_known_prefix(t, known) for t in found if ".vendor" not in f".{t}."}


def _known_prefix(target, known):
    parts = target.split(".")
    while parts and ".".join(parts) not in known:
        parts.pop()
    return ".".join(parts) if parts else target


def layer_of(path, root):
    rel = path.relative_to(ROOT).as_posix()
    for number, (_, prefixes) in enumerate(LAYERS[root]):
        if any(rel == p or (p.endswith("/") and rel.startswith(p)) for p in prefixes):
            return number
    return None


def graph(root):
    known = modules(root)
    return known, {name: imports_of(name, path, known) - {name} for name, path in known.items()}


@pytest.mark.parametrize("root", sorted(LAYERS))
def test_every_module_has_a_layer(root):
    known = modules(root)
    unplaced = [str(p.relative_to(ROOT)) for p in known.values() if layer_of(p, root) is None]
    assert not unplaced, f"modules in no declared layer of {root}: {unplaced}"


@pytest.mark.parametrize("root", sorted(LAYERS))
def test_no_import_runs_up_a_layer(root):
    known, edges = graph(root)
    upward = []
    for name, targets in edges.items():
        here = layer_of(known[name], root)
        for target in targets:
            if target in known and name != root and target != root:
                there = layer_of(known[target], root)
                if here is not None and there is not None and there > here:
                    upward.append(f"{name} ({LAYERS[root][here][0]}) -> {target} ({LAYERS[root][there][0]})")
            elif target.split(".")[0] in FORBIDDEN.get(root, ()):
                upward.append(f"{name} -> {target} (outside {root}'s reach)")
    assert not upward, "imports up a layer:\n" + "\n".join(sorted(upward))


@pytest.mark.parametrize("root", sorted(LAYERS))
def test_no_import_circles(root):
    known, edges = graph(root)
    edges = {n: {t for t in ts if t in known} for n, ts in edges.items()}
    circles, state = [], {}

    def visit(node, stack):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges[node]):
            if state.get(nxt) == "open":
                circles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node, [])
    assert not circles, "import circles:\n" + "\n".join(" -> ".join(c) for c in circles)


def test_the_builder_does_not_import_the_planner():
    """bake/core/tabulate.py builds tables; bake/core/planner.py plans them and runs the builder for
    every trial. The planner imports the builder, and nothing the builder imports, however
    indirectly, imports the planner: the builder is whole without it (its users, the stress
    tests and the report, load no planner)."""
    known, edges = graph("bake")
    assert "bake.core.tabulate" in edges["bake.core.planner"]
    reached, todo = set(), ["bake.core.tabulate"]
    while todo:
        for nxt in edges[todo.pop()] & known.keys():
            if nxt not in reached:
                reached.add(nxt)
                todo.append(nxt)
    assert "bake.core.planner" not in reached, sorted(reached)


def test_the_reader_sees_deferred_imports(tmp_path):
    """A negative control: an import inside a function is read."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from .other import thing\n")
    assert imports_of("pkg.m", src, {"pkg.m", "pkg.other"}) == {"pkg.other"}


@pytest.mark.parametrize("rel", ["formats.py", "io/files.py"])
def test_what_the_addon_reads_by_path_needs_only_the_standard_library(rel):
    """The add-on loads these modules of bake/ by their paths (blender_addon/deps.py `_stdlib_module`),
    where numpy may be missing: they import nothing but the standard library, and nothing relative."""
    import sys
    tree = ast.parse((ROOT / "bake" / rel).read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module if not n.level else "." * n.level + (n.module or "")
              for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    outside = [m for m in names if m.split(".")[0] not in sys.stdlib_module_names]
    assert not outside, f"bake/{rel} imports beyond the standard library: {outside}"


def test_the_addon_hashes_with_bake_io_files(tmp_path):
    """One file_hash: the add-on's render side (blender_addon/render/derived.py) uses bake/io/files.py's,
    loaded by its path, and it hashes as the bake's does."""
    import importlib.util
    from bake.io import files
    spec = importlib.util.spec_from_file_location("deps_under_test", ROOT / "blender_addon" / "deps.py")
    deps = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(deps)
    assert deps.files().__file__ == files.__file__
    path = tmp_path / "f.bin"
    path.write_bytes(bytes(range(256)) * 5000)
    assert deps.files().file_hash(path) == files.file_hash(path)
