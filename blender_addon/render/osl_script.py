"""The OSL back end's Script node: osl/learned_bsdf.osl with its headers inlined into one text
block of the .blend ("flowbsdf_learned_bsdf.osl", compiled bytecode stored in the node), so a
saved file does not depend on where the add-on is installed; `source_hash` records which
shader a group was built with (node.upgrade rebuilds a group whose shader differs)."""
import contextlib
import sys
from pathlib import Path

import bpy

TEXT_NAME = "flowbsdf_learned_bsdf.osl"
SCRIPT = "FlowBSDF OSL"
OSL_SOURCE = Path(__file__).resolve().parent / "osl" / "learned_bsdf.osl"


def osl_compiler_available():
    """Whether this Blender's Cycles compiles and runs the OSL shader: Debian's 3.4 has no OSL;
    Cycles before 4.4 crashes optimizing its gettextureinfo() of a constant file name
    (OSLRenderServices::get_texture_info; seen with the bpy 4.2.23 wheel, 4.4 and 4.5 run it)."""
    if bpy.app.version < (4, 4, 0):
        return False
    try:
        import _cycles
    except ImportError:
        return False
    return bool(getattr(_cycles, "with_osl", False)) and hasattr(_cycles, "osl_compile")


def ensure_oslquery():
    """Make Cycles' `oslquery` importable (bpy as a Python module does not put Blender's own
    site-packages on sys.path; without it a Script node silently gets no sockets)."""
    try:
        import oslquery  # noqa: F401
        return
    except ImportError:
        pass
    root = Path(bpy.utils.resource_path("LOCAL"))
    for site in sorted(root.glob("python/lib/python3*/site-packages")):
        if str(site) not in sys.path:
            sys.path.append(str(site))
    try:
        import oslquery  # noqa: F401
    except ImportError:         # Cycles before 4.5 queries the shader in C++ (_cycles.osl_update_node)
        pass


def shader_source(probe=False):
    """The shader as one source text: Script nodes compile a text block on their own, so the
    shader's own headers (osl/*.h) are inlined; Cycles' stdcycles.h stays an include."""
    import re

    def inline(match):
        header = OSL_SOURCE.parent / match.group(1)
        return header.read_text() if header.is_file() else match.group(0)
    src = re.sub(r'^#include "([^"]+)"$', inline, OSL_SOURCE.read_text(), flags=re.M)
    return ("#define FLOWBSDF_PROBE\n" + src) if probe else src


def _report(kind, message):
    if "ERROR" in kind:
        raise RuntimeError(f"FlowBSDF OSL shader: {message}")


def script_text(probe=False):
    """The text block holding the shader source (refreshed when the add-on's source changed)."""
    name = TEXT_NAME if not probe else "flowbsdf_learned_bsdf_probe.osl"
    src = shader_source(probe)
    text = bpy.data.texts.get(name)
    if text is None:
        text = bpy.data.texts.new(name)
    if text.as_string().rstrip("\n") != src.rstrip("\n"):
        text.from_string(src)
    return text


@contextlib.contextmanager
def _own_tempdir():
    """Cycles leaves the compiled .oso of an internal Script node in the temporary folder
    (cycles/osl.py; it compiles on every script assignment too): run compiles with a
    temporary folder of our own, removed afterwards."""
    import shutil
    import tempfile
    folder, saved = tempfile.mkdtemp(prefix="flowbsdf_osl_"), tempfile.tempdir
    tempfile.tempdir = folder
    try:
        yield
    finally:
        tempfile.tempdir = saved
        shutil.rmtree(folder, ignore_errors=True)


def make_script_node(tree, probe=False):
    """A Script node running the shader, compiled (bytecode stored in the node)."""
    if not osl_compiler_available():
        raise RuntimeError("FlowBSDF OSL shader: this Blender's Cycles cannot compile OSL")
    import cycles.osl
    ensure_oslquery()
    with _own_tempdir():
        node = tree.nodes.new("ShaderNodeScript")
        node.mode = 'INTERNAL'
        node.script = script_text(probe)
        if not cycles.osl.update_script_node(node, _report) or "BSDF" not in node.outputs:
            raise RuntimeError("FlowBSDF OSL shader: compilation gave no sockets")
    return node


def source_hash():
    """The shipped shader's content hash: a group records the one it was built with."""
    import hashlib
    return hashlib.sha256(shader_source().rstrip("\n").encode()).hexdigest()
