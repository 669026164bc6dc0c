"""The batch command in a real `blender --background` (Debian's Blender 3.4, legacy add-on form).

The add-on is staged as the extension build does (bake/ vendored), installed as the legacy
add-on `flowbsdf` in a temporary user scripts folder; the worker runs in this venv's Python.
Skips (saying why) where no `blender` binary is on PATH (./test.sh installs it with apt).
"""
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLENDER = os.environ.get("FLOWBSDF_BLENDER") or shutil.which("blender")

pytestmark = pytest.mark.skipif(
    BLENDER is None, reason="no `blender` on PATH (apt-get install blender, or set FLOWBSDF_BLENDER)")

MAKE_SCENE = """
import sys, bpy
import flowbsdf
flowbsdf.register()
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob)
scene = bpy.context.scene
scene.flowbsdf.out_dir = "//flowbsdf"
for i, preset in enumerate(["MATTE", "PLASTIC", "ROUGH_METAL"]):
    bpy.ops.mesh.primitive_uv_sphere_add(location=(2.2 * i, 0, 0), segments=16, ring_count=8)
    mat = bpy.data.materials.new(preset.lower())
    s = mat.flowbsdf
    s.enabled, s.source_kind, s.analytic_preset, s.bake_quality = True, "ANALYTIC", preset, "DRAFT"
    bpy.context.object.data.materials.append(mat)
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
print("SCENE SAVED")
"""
BATCH = "import flowbsdf.batch as b; b.main()"


def _stage_addon(user_scripts):
    spec = importlib.util.spec_from_file_location("build_extension", ROOT / "scripts" / "build_extension.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    build.stage(user_scripts / "addons" / "flowbsdf", wheels=[], platforms=[])


def _blender(args, user_scripts, cwd):
    env = {**os.environ, "BLENDER_USER_SCRIPTS": str(user_scripts)}
    for key in ("PYTHONPATH", "FLOWBSDF_PYTHON"):
        env.pop(key, None)
    proc = subprocess.run([BLENDER, "--background", "--factory-startup", *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=600)
    return proc.returncode, proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def batch_scene(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("batch")
    user = tmp / "scripts"
    _stage_addon(user)
    script = tmp / "make_scene.py"
    script.write_text(MAKE_SCENE)
    blend = tmp / "scene.blend"
    code, out = _blender(["--python", str(script), "--", str(blend)], user, tmp)
    assert code == 0 and "SCENE SAVED" in out, out[-3000:]
    return tmp, user, blend


def test_batch_bakes_in_blender_background(batch_scene):
    tmp, user, blend = batch_scene
    args = [str(blend), "--python-expr", BATCH, "--", "bake", "--python", sys.executable, "--train", "never"]
    code, out = _blender(args, user, tmp)
    print(out[-4000:])
    for name in ("matte", "plastic", "rough_metal"):
        assert (tmp / "flowbsdf" / "tables" / f"{name}.exr").is_file(), out[-3000:]
    assert "[progress 1/3] bake matte" in out and "[progress 3/3] done" in out
    assert "[flowbsdf] 3 learned material(s) in use" in out
    node_ok, why = _node_importable(user, tmp)
    if node_ok:
        assert code == 0 and f"[flowbsdf] saved {blend}" in out, out[-3000:]
    else:          # this Blender cannot build the node: a clear message and a failing exit code
        assert code == 1, out[-3000:]
        assert "[flowbsdf] error: the Learned BSDF node cannot be built in this Blender" in out, why

    code, out = _blender(args + ["--no-bind"], user, tmp)          # bake only: current tables are kept
    assert code == 0, out[-3000:]
    assert out.count("is up to date") == 3 and "[flowbsdf] done" in out

    code, out = _blender([str(blend), "--python-expr", BATCH, "--", "scan", "--python", sys.executable], user, tmp)
    assert code == 0, out[-3000:]
    assert "[flowbsdf] plastic -> plastic: current; needs theta_i only: 3 bins" in out
    assert (tmp / "flowbsdf" / "manifest.toml").is_file()


def test_batch_failure_exit_code(batch_scene):
    tmp, user, blend = batch_scene
    code, out = _blender([str(blend), "--python-expr", BATCH, "--", "bake", "--python",
                          str(tmp / "no_such_python")], user, tmp)
    assert code == 1
    assert "[flowbsdf] error: the FlowBSDF Python" in out and "does not exist" in out


def _node_importable(user, tmp):
    code, out = _blender(["--python-expr", "import flowbsdf.node; print('NODE OK')"], user, tmp)
    return "NODE OK" in out, out[-500:]
