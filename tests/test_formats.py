"""bake/formats.py holds the version numbers of the files and graphs; the OSL shader's headers
write theirs as #defines (the shader is compiled from those sources as they are), held equal here:
a version bumped in formats.py and not in the shader's reader fails this test, not a render."""
import re
from pathlib import Path

from bake import formats

ROOT = Path(__file__).resolve().parent.parent
# (header, #define, formats.py's name)
DEFINES = [("tables.h", "LAYOUT", "OSL_LAYOUT"), ("carried.h", "CARRY_LAYOUT", "CARRY_LAYOUT"),
           ("world.h", "WORLD_LAYOUT", "WORLD_LAYOUT")]


def _osl_dir():
    """The add-on's osl/ folder, wherever the add-on keeps it."""
    found = sorted(p.parent for p in (ROOT / "blender_addon").rglob("osl/learned_bsdf.osl"))
    assert len(found) == 1, found
    return found[0]


def test_the_shader_headers_say_the_layouts_of_formats_py():
    for header, define, name in DEFINES:
        text = (_osl_dir() / header).read_text()
        got = re.findall(rf"^#define {define} (\d+)\b", text, re.M)
        assert got == [str(getattr(formats, name))], (header, define, got, getattr(formats, name))


def test_the_numpy_side_reads_formats_py():
    from bake.core import mixed_tables, tables
    from bake.export import carry_export, closure_fit, osl_export, svm_export, world_map
    from bake.plumbing import pipeline
    assert (tables.FORMAT_VERSION, mixed_tables.MIXED_FORMAT_VERSION) == (formats.FORMAT, formats.MIXED_FORMAT)
    assert pipeline.BUILDER_VERSION == formats.BUILDER
    assert (osl_export.LAYOUT, svm_export.LAYOUT, world_map.LAYOUT, carry_export.CARRY_LAYOUT) == (
        formats.OSL_LAYOUT, formats.SVM_LAYOUT, formats.WORLD_LAYOUT, formats.CARRY_LAYOUT)
    assert (closure_fit.FIT_VERSION, closure_fit.READABLE_VERSIONS) == (formats.FIT_VERSION,
                                                                         formats.READABLE_FIT_VERSIONS)


def test_the_addon_reads_formats_py_without_numpy():
    """deps.formats loads bake/formats.py by its path (the `bake` package needs numpy): the module
    imports nothing."""
    import ast
    tree = ast.parse((ROOT / "bake" / "formats.py").read_text())
    assert not [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    import importlib.util
    spec = importlib.util.spec_from_file_location("deps_under_test", ROOT / "blender_addon" / "deps.py")
    deps = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(deps)
    assert deps.formats().OSL_LAYOUT == formats.OSL_LAYOUT and deps.formats().GRAPH_VERSION == formats.GRAPH_VERSION
