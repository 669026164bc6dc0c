"""The batch command in a real `blender --background` (Debian's Blender 3.4, legacy add-on form).

The add-on is staged as the extension build does (bake/ vendored), installed as the legacy
add-on `flowbsdf` in a temporary user scripts folder; the worker runs in this venv's Python.
The batch binds the Learned BSDF nodes and saves; the saved file is reopened in that Blender
(without the add-on) to check the node's fit against the fit files and to render it with
Cycles, and in bpy 5.0 (with the add-on), which adds the OSL back end.
Skips (saying why) where no `blender` binary is on PATH (./test.sh installs it with apt).
"""
import importlib.util
import json
import math
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


BAKE_ARGS = ["--python-expr", BATCH, "--", "bake", "--python", sys.executable, "--train", "never"]


@pytest.fixture(scope="module")
def batch_bake(batch_scene):
    """The batch bake of the scene (bind + save); a copy of the saved file as bound.blend."""
    tmp, user, blend = batch_scene
    code, out = _blender([str(blend), *BAKE_ARGS], user, tmp)
    if code == 0:
        shutil.copy(blend, tmp / "bound.blend")
    return code, out


def _bound_blend(batch_scene, batch_bake):
    code, out = batch_bake
    assert code == 0, "the batch bake failed:\n" + out[-3000:]
    return batch_scene[0] / "bound.blend"


def test_batch_bakes_in_blender_background(batch_scene, batch_bake):
    tmp, user, blend = batch_scene
    args = [str(blend), *BAKE_ARGS]
    code, out = batch_bake
    print(out[-4000:])
    for name in ("matte", "plastic", "rough_metal"):
        assert (tmp / "flowbsdf" / "tables" / f"{name}.exr").is_file(), out[-3000:]
    assert "[progress 1/3] bake matte" in out and "[progress 3/3] done" in out
    assert "[flowbsdf] 3 learned material(s) in use" in out
    assert code == 0 and f"[flowbsdf] saved {blend}" in out, out[-3000:]
    assert "[flowbsdf] bound 3 material(s): matte, plastic, rough_metal" in out, out[-3000:]
    for name in ("matte", "plastic", "rough_metal"):      # the default scene renders the fit (OSL off)
        assert f"[flowbsdf] {name}: node 'Learned BSDF: {name}' renders Fit, ~" in out, out[-3000:]
    with_osl = _blender_compiles_osl(user, tmp)
    assert out.count("OSL back end in the node" if with_osl else "OSL back end not in the node") == 3, out[-3000:]

    code, out = _blender(args + ["--no-bind"], user, tmp)          # bake only: current tables are kept
    assert code == 0, out[-3000:]
    assert out.count("is up to date") == 3 and "[flowbsdf] done" in out

    code, out = _blender([str(blend), "--python-expr", BATCH, "--", "scan", "--python", sys.executable], user, tmp)
    assert code == 0, out[-3000:]
    from bake.core.table_files import open_tables
    bins = len(open_tables(tmp / "flowbsdf" / "tables" / "plastic.exr").theta_bins)
    assert f"[flowbsdf] plastic -> plastic: current; needs theta_i only: {bins} bins" in out, out[-3000:]
    assert (tmp / "flowbsdf" / "manifest.toml").is_file()


def test_batch_failure_exit_code(batch_scene):
    tmp, user, blend = batch_scene
    code, out = _blender([str(blend), "--python-expr", BATCH, "--", "bake", "--python",
                          str(tmp / "no_such_python")], user, tmp)
    assert code == 1
    assert "[flowbsdf] error: the FlowBSDF Python does not exist" in out
    assert "Pass one with --python PATH" in out, out[-2000:]
    assert "checkout" not in out.split("[flowbsdf] error:", 1)[1]      # baking needs numpy + OpenEXR only


def test_batch_names_the_python_blender_reports_honestly(batch_scene):
    """Without --python the worker is the Python Blender reports as sys.executable; Debian's 3.4
    reports the python3.11 first on PATH (e.g. a pyenv shim), which is not the interpreter
    Blender runs: the batch must not call it "Blender's Python"."""
    tmp, user, blend = batch_scene
    code, out = _blender(["--python-expr", "import sys; print('EXE', sys.executable, '|', sys.base_prefix)"],
                         user, tmp)
    exe, blender_prefix = out.split("EXE ", 1)[1].splitlines()[0].split(" | ")
    own = subprocess.run([exe, "-c", "import sys; print(sys.base_prefix)"], capture_output=True, text=True)
    code, out = _blender([str(blend), "--python-expr", BATCH, "--", "scan"], user, tmp)
    named = [ln for ln in out.splitlines() if ln.startswith("[flowbsdf] worker Python:")
             or ln.startswith("[flowbsdf] error:")]
    assert named, out[-3000:]
    if own.returncode == 0 and own.stdout.strip() == blender_prefix:
        assert "Blender's Python" in named[0], named
    else:
        assert "Blender's Python" not in out, out[-3000:]
        assert f"python blender finds on path ({exe}".lower() in out.lower(), out[-3000:]


def _blender_compiles_osl(user, tmp):
    code, out = _blender(["--python-expr", "import _cycles; print('WITH_OSL', bool(_cycles.with_osl))"], user, tmp)
    assert "WITH_OSL" in out, out[-1000:]
    return "WITH_OSL True" in out


# Runs in the batch's Blender without the add-on: the saved file must render on its own.
REOPEN = """
import json, math, sys, bpy
out_path = sys.argv[-1]
scene = bpy.context.scene
result = {}

def chain(socket):
    # (base, [(x0, x1, diff)]) of a piecewise-linear vector built by fit_nodes.piecewise, in the
    # fit's node group (fit_nodes.fit_group): per channel a chain of Math Multiply Adds on Map Ranges
    # into one Combine XYZ
    link = socket.links[0]
    inner = next(n for n in link.from_node.node_tree.nodes if n.bl_idname == "NodeGroupOutput")
    combine = inner.inputs[link.from_socket.name].links[0].from_node
    assert combine.bl_idname == "ShaderNodeCombineXYZ", combine.bl_idname
    base, segments = [0.0] * 3, {}
    for c in range(3):
        node = combine.inputs[c].links[0].from_node if combine.inputs[c].links else None
        while node is not None:
            assert node.bl_idname == "ShaderNodeMath" and node.operation == 'MULTIPLY_ADD', node.bl_idname
            ramp = node.inputs[0].links[0].from_node
            key = (ramp.inputs["From Min"].default_value, ramp.inputs["From Max"].default_value)
            segments.setdefault(key, [0.0] * 3)[c] = node.inputs[1].default_value
            if node.inputs[2].links:
                node = node.inputs[2].links[0].from_node
            else:
                base[c] = node.inputs[2].default_value
                node = None
        if not combine.inputs[c].links:
            base[c] = combine.inputs[c].default_value
    return base, [(x0, x1, diff) for (x0, x1), diff in sorted(segments.items())]

def upstream(socket):
    # the nodes feeding socket in its tree
    seen, todo = {}, [socket]
    while todo:
        for link in todo.pop().links:
            if link.from_node.name not in seen:
                seen[link.from_node.name] = link.from_node
                todo.extend(link.from_node.inputs)
    return list(seen.values())

for mat in bpy.data.materials:
    groups = [n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeGroup"] if mat.node_tree else []
    if not groups:
        continue
    g = groups[0]
    tree = g.node_tree
    outs = {n.target: n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"}
    out = outs["CYCLES"]
    group_out = next(n for n in tree.nodes if n.bl_idname == "NodeGroupOutput")
    fit_nodes, eevee_nodes = upstream(group_out.inputs["BSDF"]), upstream(group_out.inputs["EEVEE"])
    nodes = {n.bl_idname: n for n in fit_nodes}
    diffuse = nodes["ShaderNodeBsdfDiffuse"]
    glossies = sorted((n for n in fit_nodes if n.bl_idname == "ShaderNodeBsdfAnisotropic"),
                      key=lambda n: n.inputs["Color"].links[0].from_socket.name)
    eevee_glossies = [n for n in eevee_nodes if n.bl_idname == "ShaderNodeBsdfAnisotropic"]
    sep = glossies[0].inputs["Roughness"].links[0].from_node
    aniso = glossies[0].inputs["Anisotropy"].links[0].from_node
    result[mat.name] = {
        "group": tree.name, "label": g.label, "raw": tree["flowbsdf"].to_dict(),
        "info": {k: bpy.path.abspath(v) if isinstance(v, str) and v.startswith("//") else v
                 for k, v in tree["flowbsdf"].to_dict().items()},
        "surface_from": out.inputs["Surface"].links[0].from_node.name,
        "group_outputs": [s.name for s in g.outputs],
        "node_types": sorted(n.bl_idname for n in tree.nodes),
        "diffuse": chain(diffuse.inputs["Color"]), "specular": [chain(n.inputs["Color"]) for n in glossies],
        "roughness": chain(sep.inputs[0]), "anisotropy": chain(aniso.inputs[0]),
        "distribution": sorted({n.distribution for n in glossies}),
        "view_tangent": [n.inputs["Tangent"].is_linked for n in glossies],
        "normal_linked": [n.inputs["Normal"].is_linked for n in [diffuse] + glossies],
        "outputs": sorted(outs), "eevee_from": outs["EEVEE"].inputs["Surface"].links[0].from_socket.name,
        "eevee_diffuse": chain(next(n for n in eevee_nodes if n.bl_idname == "ShaderNodeBsdfDiffuse").inputs["Color"]),
        "eevee_anisotropy_linked": [n.inputs["Anisotropy"].is_linked for n in eevee_glossies],
        "shared": len(set(n.name for n in fit_nodes) & set(n.name for n in eevee_nodes)),
    }
    fit_node = next(n for n in fit_nodes if n.bl_idname == "ShaderNodeGroup" and n.node_tree.name.startswith("FlowBSDF fit"))
    for key, name in (("tilt", "Tilt"), ("lobe4", "Lobe 4")):
        if name in fit_node.outputs and fit_node.outputs[name].is_linked:
            result[mat.name][key] = chain(fit_node.outputs[name].links[0].to_socket)

# A uniform white environment, each sphere alone in an orthographic 16x16 view, 4 spp.
world = bpy.data.worlds.new("white")
world.use_nodes = True
world.node_tree.nodes["Background"].inputs["Color"].default_value = (1, 1, 1, 1)
world.node_tree.nodes["Background"].inputs["Strength"].default_value = 1.0
scene.world = world
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = 4
scene.cycles.use_denoising = False
scene.render.resolution_x = scene.render.resolution_y = 16
scene.render.resolution_percentage = 100
scene.render.film_transparent = True
scene.render.threads_mode = "FIXED"
scene.render.threads = 1
scene.view_settings.view_transform = "Standard"
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
cam.data.type = "ORTHO"
cam.data.ortho_scale = 2.0
scene.collection.objects.link(cam)
scene.camera = cam
for ob in scene.objects:
    if ob.type != "MESH":
        continue
    mat = ob.data.materials[0].name
    cam.location = (ob.location.x, ob.location.y - 5.0, ob.location.z)
    cam.rotation_euler = (math.pi / 2, 0.0, 0.0)
    scene.render.filepath = out_path + "." + mat + ".exr"
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(scene.render.filepath)
    px = list(img.pixels)
    w = img.size[0]
    inner = []          # pixels fully inside the disc: (rho, rgb)
    for i in range(len(px) // 4):
        x, y = (i % w + 0.5) / w * 2 - 1, (i // w + 0.5) / w * 2 - 1
        rho = math.hypot(x, y)
        if rho < 0.85:
            inner.append((rho, px[4 * i:4 * i + 3], px[4 * i + 3]))
    result[mat]["render"] = inner
json.dump(result, open(out_path, "w"))
print("REOPENED")
"""


def _lerp(xs, ys, x):
    for k in range(len(xs) - 1):
        if xs[k] <= x <= xs[k + 1]:
            t = (x - xs[k]) / (xs[k + 1] - xs[k]) if xs[k + 1] > xs[k] else 0.0
            return [a + t * (b - a) for a, b in zip(ys[k], ys[k + 1])]
    return list(ys[-1] if x > xs[-1] else ys[0])


def _eval_chain(chain, x):
    base, steps = chain
    return [b + sum(min(max((x - x0) / (x1 - x0), 0.0), 1.0) * d[c] for x0, x1, d in steps)
            for c, b in enumerate(base)]


def test_saved_blend_reopens_in_blender_with_the_fit_and_renders(batch_scene, batch_bake):
    """The batch's saved file, reopened in the same Blender without the add-on: each material's
    Learned BSDF group carries its fit (the node's piecewise-linear colours and roughness equal
    the .fit.json at every knot) and renders with Cycles: a sphere under a white environment
    shows its directional albedo, not pink or black."""
    tmp, user, _ = batch_scene
    bound = _bound_blend(batch_scene, batch_bake)
    dump = tmp / "reopen.json"
    code, out = _blender([str(bound), "--python-expr", REOPEN, "--", str(dump)], user, tmp)
    assert code == 0 and "REOPENED" in out, out[-3000:]
    result = json.loads(dump.read_text())
    assert sorted(result) == ["matte", "plastic", "rough_metal"]
    tables = tmp / "flowbsdf" / "tables"
    means = {}
    for name, r in result.items():
        fit = json.loads((tables / f"{name}.fit.json").read_text())
        assert r["group"] == f"Learned BSDF: {name}" and r["label"] == "Learned BSDF"
        assert r["surface_from"] == "Learned BSDF" and r["group_outputs"] == ["BSDF", "EEVEE"]
        # EEVEE its own Material Output, fed by the EEVEE fit's closures alone (isotropic lobes)
        assert r["outputs"] == ["CYCLES", "EEVEE"] and r["eevee_from"] == "EEVEE" and r["shared"] == 0
        assert not any(r["eevee_anisotropy_linked"]) and len(r["eevee_anisotropy_linked"]) == len(fit["roughness"][0])
        for x, want in zip(fit["eevee"]["x"], fit["eevee"]["diffuse"]):
            assert _eval_chain(r["eevee_diffuse"], x) == pytest.approx(want, abs=1e-5), (name, "eevee", x)
        info = r["info"]
        # stored relative to the .blend, so the project folder can move
        assert r["raw"]["tables"] == f"//flowbsdf/tables/{name}.exr" and r["raw"]["fit"].startswith("//"), r["raw"]
        assert info["material"] == name and info["has_fit"] and Path(info["fit"]) == tables / f"{name}.fit.json"
        assert info["fit_error"] == pytest.approx(fit["error"]) and info["fit_version"] == fit["version"]
        # the worker wrote the OSL texture beside the tables and the group records it even where
        # Cycles cannot compile OSL (Debian's 3.4), so a Blender that can rebuilds from it; such a
        # group holds no Script node (node.py)
        assert len(list(tables.glob(f"{name}.osl*-*.exr"))) == 1
        assert Path(info["osl_texture"]).is_file() and Path(info["osl_texture"]).parent == tables
        if not info["has_osl"]:
            assert "ShaderNodeScript" not in r["node_types"]
        assert r["distribution"] == ["GGX"]
        # the fit's lobes: the first fit["view_aligned"] take the view's tangent
        lobes = len(fit["roughness"][0])
        assert r["view_tangent"] == [j < fit["view_aligned"] for j in range(lobes)], r["view_tangent"]
        for x, want in zip(fit["x"], fit["diffuse"]):
            assert _eval_chain(r["diffuse"], x) == pytest.approx(want, abs=1e-5), (name, x)
        for j, lobe in enumerate(r["specular"]):
            for x, want in zip(fit["x"], fit["specular"]):
                assert _eval_chain(lobe, x) == pytest.approx(want[j], abs=1e-5), (name, j, x)
        for key in ("roughness", "anisotropy"):
            for x, want in zip(fit["x"], fit[key]):
                assert _eval_chain(r[key], x) == pytest.approx(want[:3], abs=1e-5), (name, key, x)
        # FIT_VERSION 7: the tilts (t_1, t_2, t_3) and (r_4, t_4, t_d), each tilted closure's Normal linked
        tilt, dtilt = fit.get("tilt", [[0.0] * lobes] * len(fit["x"])), fit.get("diffuse_tilt", [0.0] * len(fit["x"]))
        assert r["normal_linked"] == [any(dtilt)] + [any(t[j] for t in tilt) for j in range(lobes)], r["normal_linked"]
        if "tilt" in r:
            for x, want in zip(fit["x"], tilt):
                assert _eval_chain(r["tilt"], x) == pytest.approx(want[:3], abs=1e-6), (name, "tilt", x)
        if lobes > 3:
            for x, rough, t, d in zip(fit["x"], fit["roughness"], tilt, dtilt):
                assert _eval_chain(r["lobe4"], x) == pytest.approx([rough[3], t[3], d], abs=1e-6), (name, "lobe 4", x)

        # The render: each inner pixel sees the fit's directional albedo at its view angle
        # (orthographic: cos theta = sqrt(1 - rho^2)); 4 spp of a white environment.
        pixels = r["render"]
        assert len(pixels) > 100 and all(a > 0.99 for _, _, a in pixels), name
        got = [sum(p[c] for _, p, _ in pixels) / len(pixels) for c in range(3)]
        want = [0.0, 0.0, 0.0]
        for rho, _, _ in pixels:
            alb = _lerp(fit["x"], fit["fit_albedo"], 1.0 - math.sqrt(1.0 - rho * rho))
            want = [w + a / len(pixels) for w, a in zip(want, alb)]
        means[name] = (got, want)
        assert all(0.02 < g < 1.0 for g in got), (name, got)          # not black, not blown out
        assert got == pytest.approx(want, rel=0.08, abs=0.02), (name, got, want)
    print("render means (got, fit albedo):", means)


# Runs in bpy 5.0 (this venv) with the add-on: opening the 3.4 file adds the OSL back end.
UPGRADE = """
import sys, bpy
sys.path.insert(0, sys.argv[1])
import blender_addon
from blender_addon.render import binding, node, osl_script
blender_addon.register()
bpy.ops.wm.open_mainfile(filepath=sys.argv[2])
scene = bpy.context.scene
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.shading_system = True
for mat in ("matte", "plastic", "rough_metal"):
    g = bpy.data.materials[mat].node_tree.nodes["Learned BSDF"]
    script = g.node_tree.nodes[osl_script.SCRIPT]
    assert script.bytecode and "Fallback" in script.inputs, mat
    assert g.node_tree[binding.TREE_KEY]["has_osl"], mat
    node.sync(scene)
    print("STATUS", mat, node.node_status(g, scene))
blender_addon.unregister()
"""


def test_saved_blend_gets_the_osl_back_end_in_bpy(batch_scene, batch_bake):
    """The file bound in a Blender without OSL, opened with the add-on in bpy 5.0 (Cycles with
    OSL): the load handler rebuilds each group with the OSL Script node, which then renders."""
    tmp, _, _ = batch_scene
    bound = _bound_blend(batch_scene, batch_bake)
    if importlib.util.find_spec("bpy") is None:
        pytest.skip("bpy (Blender as a Python module) is not installed")
    copy = tmp / "bound_in_bpy.blend"
    shutil.copy(bound, copy)
    proc = subprocess.run([sys.executable, "-c", UPGRADE, str(ROOT), str(copy)], capture_output=True,
                          text=True, timeout=600, cwd=tmp)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    for mat in ("matte", "plastic", "rough_metal"):
        assert f"STATUS {mat} OSL, exact" in out, out[-3000:]


def test_node_reads_the_fit_format_bake_writes(batch_scene, batch_bake, tmp_path):
    """derived.load_fit (json only, what a numpy-less Blender uses) reads the fits the batch's bake
    wrote, and refuses one of another format version."""
    tmp, _, _ = batch_scene
    pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from bake.export import closure_fit
    from blender_addon.render import derived
    _bound_blend(batch_scene, batch_bake)
    assert derived.FIT_VERSION == closure_fit.FIT_VERSION
    fits = sorted((tmp / "flowbsdf" / "tables").glob("*.fit.json"))
    assert len(fits) == 3
    for path in fits:
        assert derived.load_fit(path) == closure_fit.load_fit(path)
    data = json.loads(fits[0].read_text())
    data["version"] = closure_fit.FIT_VERSION + 1
    (tmp_path / "old.fit.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="not a current FlowBSDF closure fit"):
        derived.load_fit(tmp_path / "old.fit.json")
