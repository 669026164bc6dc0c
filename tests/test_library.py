"""The asset library of measured files: `flowbsdf library FOLDER --out DIR` (blender_addon/artist/library.py).

One library of three shared RGL files, baked once at Draft quality (about a minute and a half on
2 cores) and shared by the tests in file order: the last one changes a file.
"""
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")
import cycles_scenes as cs  # noqa: E402  (tests/ helper of the node tests)
from conftest import rgl_path, slow_unless  # noqa: E402

from bake.plumbing.manifest import load_manifest  # noqa: E402

FILES = ("paper_white_rgb", "satin_rosaline_rgb", "vch_golden_yellow_rgb")


@pytest.fixture(scope="module")
def addon():
    import blender_addon
    blender_addon.register()
    yield blender_addon
    blender_addon.unregister()


@pytest.fixture(scope="module")
def lib(addon, tmp_path_factory):
    """{root, files, out, lines, seconds}: the library of FILES, made by the CLI's code path."""
    from blender_addon.artist import library
    sources = [rgl_path(name) for name in FILES]
    root = tmp_path_factory.mktemp("library")
    files = root / "measured"
    files.mkdir()
    for src in sources:
        shutil.copy(src, files / src.name)
        os.chmod(files / src.name, 0o644)
    out = root / "lib"
    lines = []
    t0 = time.perf_counter()
    library.main(files, out, quality="draft", log=lines.append, bake_log=lines.append)
    return {"root": root, "files": files, "out": out, "lines": lines, "seconds": time.perf_counter() - t0}


def _group(mat):
    from blender_addon.render import binding
    return next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeGroup"
                and n.node_tree is not None and binding.TREE_KEY in n.node_tree.keys())


def test_quality_settings_match_the_panels():
    from blender_addon.artist import library, props
    assert library.QUALITY == {k.lower(): v for k, v in props.BAKE_QUALITY.items()}


def test_three_files_make_an_asset_library(lib):
    """library.blend: a material per file, marked as an asset, with the bake's preview (its
    pixels, surviving the save), in a catalog of blender_assets.cats.txt, naming its file."""
    from blender_addon.artist import library
    out = lib["out"]
    assert {p.name for p in out.iterdir()} >= {"library.blend", "blender_assets.cats.txt", "manifest.toml", "tables"}
    assert not (out / "library.blend1").exists()
    cats_text = (out / library.CATALOG_FILE).read_text()
    lines = [ln for ln in cats_text.splitlines() if ln.strip() and not ln.startswith("#")]
    assert lines[0] == "VERSION 1" and all(len(ln.split(":")) == 3 for ln in lines[1:]), cats_text
    cats = library.read_catalogs(out)
    assert set(cats) == {"FlowBSDF", "FlowBSDF/RGL"}
    manifest = load_manifest(out / "manifest.toml")
    assert [e.name for e in manifest.materials] == list(FILES)
    for entry in manifest.materials:
        assert entry.source == f"../measured/{entry.name}.bsdf"        # relative: the folders move together
        assert entry.source_path().resolve() == (lib["files"] / f"{entry.name}.bsdf").resolve()
        assert entry.bake["resolution"] == 16

    bpy.ops.wm.open_mainfile(filepath=str(out / "library.blend"))
    assert {m.name for m in bpy.data.materials} == set(FILES)
    for name in FILES:
        mat = bpy.data.materials[name]
        data = mat.asset_data
        assert data is not None, name
        assert data.catalog_id == cats["FlowBSDF/RGL"]
        assert f"{name}.bsdf" in data.description and "RGL" in data.description
        assert f"../measured/{name}.bsdf" in data.description
        assert {"FlowBSDF", "RGL", f"{name}.bsdf"} <= {t.name for t in data.tags}
        assert mat.flowbsdf.enabled and mat.flowbsdf.source_kind == "FILE"
        # the preview: the bake's exact render, not Blender's (which would render the fit)
        preview = mat.preview
        assert preview is not None and tuple(preview.image_size) == (128, 128)
        pixels = np.array(preview.image_pixels_float[:]).reshape(128, 128, 4)
        png = bpy.data.images.load(str(out / "tables" / f"{name}.preview.png"))
        png.scale(128, 128)
        want = np.array(png.pixels[:]).reshape(128, 128, 4)
        bpy.data.images.remove(png)
        assert pixels[..., :3].max() > 0.1 and np.abs(pixels - want).max() < 1e-2, name
        assert _group(mat).node_tree.library is None
    # the tables' paths: relative to library.blend, and absolute beside
    raw = _group(bpy.data.materials[FILES[0]]).node_tree["flowbsdf"].to_dict()
    assert raw["tables"] == f"//tables/{FILES[0]}.exr" and raw["absolute"]["tables"] == str(out / "tables" / f"{FILES[0]}.exr")


def _scene(scene, osl, width=48, height=16, spp=16):
    """cycles_scenes.reset's settings on the open file's scene (reset would read the factory file)."""
    return cs.configure(scene, width, height, spp, osl)


def _render_three(scene, mats):
    """The materials (None: no sphere there) on three spheres side by side under a white world,
    16x16 pixels each: each one's mean."""
    for k, mat in enumerate(mats):
        if mat is not None:
            ob = cs.add_sphere(scene, mat, segments=32, rings=16)
            ob.location.x = 2.2 * (k - 1)
    cs.set_world(scene, (1.0, 1.0, 1.0))
    cs.ortho_camera(scene, scale=6.6)
    img = cs.render(scene)
    assert np.isfinite(img).all()
    return [img[:, 16 * k:16 * (k + 1)].mean() if mat is not None else None for k, mat in enumerate(mats)]


@pytest.mark.parametrize("osl", slow_unless([True, False], default=[False]), ids=["osl", "svm"])
def test_appended_materials_find_their_tables(lib, tmp_path, osl):
    """A material appended from the library into a .blend in another folder renders exactly (its
    node finds the library's tables: the stored relative path points beside the new file) and as
    in the library itself; a linked one's node resolves them relative to the library. The
    library's render is the SVM graph's (exact, seconds); with OSL on, the appended file renders
    one material (Cycles compiles the OSL shader for each material on every render: ~25 s each
    on 2 shared cores)."""
    from blender_addon.render import binding, node
    cs.bpy_or_skip(need_osl=osl)
    exact = ("OSL", "exact") if osl else ("SVM", "exact")
    bpy.ops.wm.open_mainfile(filepath=str(lib["out"] / "library.blend"))
    scene = _scene(bpy.context.scene, False)
    in_library = _render_three(scene, [bpy.data.materials[n] for n in FILES])

    shot = tmp_path / "elsewhere" / "deeper" / "shot.blend"
    shot.parent.mkdir(parents=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = _scene(bpy.context.scene, osl)
    bpy.ops.wm.save_as_mainfile(filepath=str(shot))
    with bpy.data.libraries.load(str(lib["out"] / "library.blend"), link=False, relative=True) as (_, dst):
        dst.materials = list(FILES)
    mats = [bpy.data.materials[n] for n in FILES]
    assert all(m.library is None for m in mats)
    for mat in mats:
        state = node.node_state(_group(mat), scene)
        assert state.text.startswith(exact[0]) and state.text.endswith(exact[1]), (mat.name, state.line())
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(shot))        # and once saved there and reopened
    scene = bpy.context.scene
    mats = [bpy.data.materials[n] for n in FILES]
    for mat in mats:
        assert node.node_state(_group(mat), scene).text.startswith(exact[0]), mat.name
        assert binding.read(_group(mat).node_tree)["tables"] == str(lib["out"] / "tables" / f"{mat.name}.exr")
    appended = _render_three(scene, mats[:1] + [None, None] if osl else mats)
    for name, a, b in zip(FILES, appended, in_library):
        assert b > 0.05 and (a is None or abs(a / b - 1) < 0.1), (name, a, b)

    if osl:         # linked: the node's paths resolve against the library's folder
        bpy.ops.wm.read_factory_settings(use_empty=True)
        scene = _scene(bpy.context.scene, osl)
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "linked.blend"))
        with bpy.data.libraries.load(str(lib["out"] / "library.blend"), link=True, relative=True) as (_, dst):
            dst.materials = [FILES[0]]
        mat = bpy.data.materials[FILES[0]]
        assert mat.library is not None
        assert node.node_state(_group(mat), scene).text.startswith(exact[0])


def test_a_second_run_bakes_nothing_and_a_changed_file_rebakes_alone(lib):
    """Run again: every table current, library.blend not rewritten. Then one file's contents
    change: that material alone is rebaked and rebuilt."""
    from blender_addon.artist import library
    out, files = lib["out"], lib["files"]
    tables = {n: out / "tables" / f"{n}.exr" for n in FILES}
    blend = out / "library.blend"

    def stamps():
        return {p.name: p.stat().st_mtime_ns for p in [*tables.values(), blend, out / "manifest.toml",
                                                       out / library.CATALOG_FILE]}
    before = stamps()
    lines = []
    t0 = time.perf_counter()
    library.main(files, out, quality="draft", log=lines.append, bake_log=lines.append)
    assert time.perf_counter() - t0 < 0.5 * lib["seconds"]
    assert stamps() == before, lines
    assert sum(ln.startswith("[skip]") and "up to date" in ln for ln in lines) == 3, lines
    assert not any(ln.startswith("[wrote]") for ln in lines), lines
    assert any("is current: not rewritten" in ln for ln in lines), lines

    shutil.copy(files / f"{FILES[1]}.bsdf", files / f"{FILES[0]}.bsdf")      # new contents, same name
    old_hash = library._hash(tables[FILES[0]])
    lines = []
    library.main(files, out, quality="draft", log=lines.append, bake_log=lines.append)
    after = stamps()
    assert [ln for ln in lines if ln.startswith("[wrote]")] == [f"[wrote] {tables[FILES[0]]}"], lines
    assert sum(ln.startswith("[skip]") for ln in lines) == 2, lines
    assert {k for k in after if after[k] != before[k]} == {f"{FILES[0]}.exr", "library.blend"}, lines
    assert any(ln.startswith(f"{FILES[0]}: updated") for ln in lines), lines
    assert sum(ln.endswith(": current") for ln in lines) == 2, lines
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    import json
    record = json.loads(bpy.data.materials[FILES[0]][library.RECORD])
    assert record["tables_hash"] == library._hash(tables[FILES[0]]) != old_hash
    assert bpy.data.materials[FILES[0]].asset_data is not None
