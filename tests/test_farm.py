"""Farm jobs (bake/plumbing/farm.py): the Open Job Description bundle run by the real OpenJD runtime, and
the Flamenco job type compiled by a stub harness in node (not the Flamenco manager).

The OpenJD tools (`openjd-cli`, a test dependency) are found beside this Python, on PATH or at
$FLOWBSDF_OPENJD; the tests that need them skip without. The .blend is made and assembled by a
real `blender` where one is installed (Debian's 3.4), else by bpy through a `blender`-like shim
(FLOWBSDF_BLENDER=bpy forces that); the test's id says which ran.
"""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bake.plumbing import farm
from conftest import ROOT, TINY_TRAIN_TOML
from test_blender_batch import MAKE_SCENE, _stage_addon

DRAFT = '{ resolution = 16, tol = 0.5, grid = 96, samples = 2048, first_bins = 3, ideal_resolution = 48 }'
# A training run of seconds (the trainer's own test settings) for "rough", whose tables come
# from its model (source "flow"); the others bake from the ideal tabulation (auto: no model wanted).
TINY_TRAIN = f'preset = "fast"\n{TINY_TRAIN_TOML}ema = 0.9\n'
MANIFEST = f"""[defaults]
bake = {DRAFT}

[[material]]
name = "matte"
source = {{ kind = "analytic", model = "lambert", albedo = 0.8 }}

[[material]]
name = "broken"
source = "measured/missing.bsdf"

[[material]]
name = "rough"
source = {{ kind = "analytic", model = "ggx", alpha = 0.4 }}
bake = {{ source = "flow" }}
[material.train]
{TINY_TRAIN}
[[material]]
name = "plastic"
source = {{ kind = "analytic", model = "plastic", albedo = [0.7, 0.1, 0.08], alpha = 0.12 }}
bake = {{ source = "ideal" }}
"""


def _openjd():
    for cand in (os.environ.get("FLOWBSDF_OPENJD"), Path(sys.executable).with_name("openjd"), shutil.which("openjd")):
        if cand and Path(cand).is_file():
            return str(cand)
    return None


OPENJD = _openjd()
needs_openjd = pytest.mark.skipif(OPENJD is None, reason="the OpenJD tools are not installed "
                                  "(pip install openjd-cli: the `test` extra; or set FLOWBSDF_OPENJD)")


def _env():
    """The workers' environment: this checkout's bake/trainer for `python -m bake.plumbing.cli`."""
    env = {k: v for k, v in os.environ.items() if k not in ("FLOWBSDF_PYTHON", "FLOWBSDF_TRAIN_PYTHON")}
    env["PYTHONPATH"] = str(ROOT)
    return env


def _run(cmd, cwd=None, timeout=300):
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, env=_env(), cwd=cwd,
                          timeout=timeout)
    return proc.returncode, proc.stdout + proc.stderr


def _cli(*args):
    return _run([sys.executable, "-m", "bake.plumbing.cli", *args], cwd=ROOT)


def _progress(out):
    return [float(x) for x in re.findall(r"openjd_progress: ([\d.]+)", out)]


# -- the template -------------------------------------------------------------------------------

def test_template_defaults_are_relative_inside_the_bundle_else_required(tmp_path):
    job = tmp_path / "job"
    template, values = farm.job_template(["a", "b"], str(job), str(job / "m.toml"), str(tmp_path / "out"),
                                         "/opt/py", "never", scene=str(tmp_path / "s.blend"))
    params = {p["name"]: p for p in template["parameterDefinitions"]}
    assert params["Manifest"]["default"] == "m.toml"                        # inside the bundle
    assert "default" not in params["SharedOut"] and "default" not in params["Scene"]   # outside: required
    assert params["AddonDir"]["default"] == "" and params["Train"]["default"] == "never"
    assert values["SaveAs"] == str(tmp_path / "s.flowbsdf.blend") and values["Python"] == "/opt/py"
    bake, assemble = template["steps"]
    assert bake["parameterSpace"]["taskParameterDefinitions"][0]["range"] == ["a", "b"]
    assert assemble["dependencies"] == [{"dependsOn": "Bake"}]
    assert farm.blender_expr() in assemble["script"]["actions"]["onRun"]["args"]
    with pytest.raises(farm.FlowBSDFError, match="no materials"):
        farm.job_template([], str(job), "m.toml", "out", "py", "auto")


@needs_openjd
def test_openjd_check_passes_and_more_than_1024_materials_split_over_steps(tmp_path):
    """2500 materials: three Bake steps of <= 1024 tasks (a STRING task parameter's limit) and
    an Assemble after all of them; `openjd check` and `openjd summary` accept it (not run)."""
    lines = [f'[[material]]\nname = "m{i:04d}"\nsource = {{ kind = "analytic", model = "lambert", albedo = 0.5 }}\n'
             for i in range(2500)]
    (tmp_path / "m.toml").write_text("\n".join(lines))
    (tmp_path / "shot.blend").write_bytes(b"")
    code, out = _cli("farm", "openjd", tmp_path / "m.toml", "--out", tmp_path / "job",
                     "--scene", tmp_path / "shot.blend")
    assert code == 0, out
    template = json.loads((tmp_path / "job" / "template.json").read_text())
    steps = template["steps"]
    assert [s["name"] for s in steps] == ["Bake 1 of 3", "Bake 2 of 3", "Bake 3 of 3", "Assemble"]
    ranges = [s["parameterSpace"]["taskParameterDefinitions"][0]["range"] for s in steps[:3]]
    assert [len(r) for r in ranges] == [1024, 1024, 452]
    assert sum(ranges, []) == [f"m{i:04d}" for i in range(2500)]
    assert steps[3]["dependencies"] == [{"dependsOn": s["name"]} for s in steps[:3]]
    code, out = _run([OPENJD, "check", tmp_path / "job" / "template.json"])
    assert code == 0 and "passes validation checks" in out, out
    code, out = _run([OPENJD, "summary", tmp_path / "job" / "template.json",
                      "--job-param", f"file://{tmp_path / 'job' / 'params.json'}"])
    assert code == 0 and "Total tasks: 2501" in out, out
    values = json.loads((tmp_path / "job" / "parameter_values.json").read_text())["parameterValues"]
    params = json.loads((tmp_path / "job" / "params.json").read_text())
    assert {v["name"]: v["value"] for v in values} == params
    assert params["AddonDir"] == "" and params["SaveAs"] == str(tmp_path / "shot.flowbsdf.blend")
    assert params["SharedOut"] == str(tmp_path / "out") and params["Blender"] == "blender"


# -- the real OpenJD runtime ------------------------------------------------------------------------

@needs_openjd
def test_openjd_runs_each_bake_task_for_real_with_path_mapping(tmp_path):
    """The bundle is written on a 'submitter' (storage at studio/), the storage is then mounted at
    mnt/ and each task runs in its own `openjd run` session (as a farm runs tasks) with a path
    mapping rule studio -> mnt: the good materials train (rough) and bake, report progress and
    write their tables; the broken one fails its own task with our message."""
    studio, mnt = tmp_path / "studio", tmp_path / "mnt"
    (studio / "shot").mkdir(parents=True)
    (studio / "shot" / "m.toml").write_text(MANIFEST)
    code, out = _cli("farm", "openjd", studio / "shot" / "m.toml", "--out", studio / "jobs" / "j1",
                     "--python", sys.executable, "--train", "auto")
    assert code == 0 and "4 material(s); steps: Bake (4 tasks)" in out, out
    code, out = _run([OPENJD, "check", studio / "jobs" / "j1" / "template.json"])
    assert code == 0, out
    studio.rename(mnt)
    rules = {"version": "pathmapping-1.0", "path_mapping_rules": [
        {"source_path_format": "POSIX", "source_path": str(studio), "destination_path": str(mnt)}]}
    job = mnt / "jobs" / "j1"
    runs = {}
    for name in ("matte", "broken", "rough", "plastic"):
        runs[name] = _run([OPENJD, "run", job / "template.json", "--job-param", f"file://{job / 'params.json'}",
                           "--path-mapping-rules", json.dumps(rules), "--step", "Bake",
                           "--task-param", f"Material={name}"], cwd=tmp_path)
        print(f"--- {name}: exit {runs[name][0]}\n" + "\n".join(
            ln for ln in runs[name][1].splitlines() if re.search(r"\topenjd_|exited with code", ln)))
    tables = mnt / "shot" / "out" / "tables"
    for name in ("matte", "rough", "plastic"):
        code, out = runs[name]
        assert code == 0 and "Session ended successfully" in out, out[-3000:]
        progress = _progress(out)
        assert progress[0] == 0 and progress[-1] == 100 and progress == sorted(progress), progress
        assert f"openjd_status: {name}: baking tables" in out and "openjd_fail" not in out
        assert (tables / f"{name}.exr").is_file() and (tables / f"{name}.fit.json").is_file()
        assert str(studio) not in out.split("Output:", 1)[1], "a path was not mapped"
    if farm.can_train(sys.executable):
        assert "openjd_status: rough: training stage reflow done" in runs["rough"][1]
        assert (mnt / "shot" / "out" / "models" / "rough.flow.npz").is_file()
        from bake.core.table_files import open_tables
        assert open_tables(tables / "rough.exr").meta["source"] == "flow"        # baked from the trained model
    assert not (mnt / "shot" / "out" / "models" / "matte.flow.npz").exists()      # source auto: no training
    code, out = runs["broken"]
    assert code == 1 and "Session ended with errors" in out
    assert re.search(r"openjd_fail: material 'broken': \S*/mnt/shot/measured/missing.bsdf: material file not "
                     r"found", out), out[-3000:]
    assert "exited with code: 2" in out and not (tables / "broken.exr").exists()


BLENDER = os.environ.get("FLOWBSDF_BLENDER") or shutil.which("blender")
ENGINE = "blender" if BLENDER and BLENDER != "bpy" else "bpy"


def _blender_command(tmp_path):
    """(the executable that acts as `blender`, label): Blender itself, or bpy through a shim."""
    if ENGINE == "blender":
        blender = BLENDER
        version = subprocess.run([blender, "--version"], capture_output=True, text=True).stdout.split("\n")[0]
        return blender, version.strip() or "blender"
    pytest.importorskip("bpy", reason="neither `blender` nor bpy is installed")
    shim = tmp_path / "blender-bpy"
    shim.write_text(BPY_SHIM.format(python=sys.executable))
    shim.chmod(0o755)
    return str(shim), "bpy (no blender binary)"


# `blender -b [FILE] [--factory-startup] [--python-expr EXPR | --python FILE] [-- ARGS]` with bpy.
BPY_SHIM = """#!{python}
import sys
import bpy
args = sys.argv[1:]
sys.argv = ["blender", *args]
rest = args[:args.index("--")] if "--" in args else args
code = None
while rest:
    arg = rest.pop(0)
    if arg in ("-b", "--background") and rest and not rest[0].startswith("-"):
        bpy.ops.wm.open_mainfile(filepath=rest.pop(0))
    elif arg == "--python-expr":
        code = rest.pop(0)
    elif arg == "--python":
        code = open(rest.pop(0)).read()
if code:
    exec(compile(code, "<blender-bpy>", "exec"), {{"__name__": "__main__"}})
"""


@needs_openjd
@pytest.mark.parametrize("engine", [ENGINE])            # the test's id says which Blender ran
def test_openjd_assembles_the_blend_for_real(tmp_path, engine):
    """A .blend with three learned materials: `flowbsdf farm openjd SHOT.blend` scans it in Blender
    (the add-on's batch `farm openjd`), `openjd run --step Assemble --run-dependencies` bakes the
    three tasks and then binds and saves the file in Blender; the saved file holds the nodes."""
    blender, label = _blender_command(tmp_path)
    print(f"Blender used: {label} ({blender})")
    user = tmp_path / "scripts"
    _stage_addon(user)
    addons = user / "addons"
    shot = tmp_path / "shot"
    shot.mkdir()
    script = tmp_path / "make_scene.py"
    script.write_text(MAKE_SCENE.replace("import flowbsdf\n", f"sys.path.insert(0, {str(addons)!r})\n"
                                                              "import flowbsdf\n"))
    code, out = _run([blender, "-b", "--python", script, "--", shot / "scene.blend"])
    assert code == 0 and "SCENE SAVED" in out, out[-3000:]

    code, out = _cli("farm", "openjd", shot / "scene.blend", "--out", tmp_path / "job", "--train", "never",
                     "--python", sys.executable, "--blender", blender, "--addon-dir", addons)
    assert code == 0 and "3 material(s); steps: Bake (3 tasks), Assemble" in out, out[-3000:]
    template = tmp_path / "job" / "template.json"
    code, out = _run([OPENJD, "check", template])
    assert code == 0, out
    code, out = _run([OPENJD, "run", template, "--job-param", f"file://{tmp_path / 'job' / 'params.json'}",
                      "--step", "Assemble", "--run-dependencies"], cwd=tmp_path)
    print("\n".join(ln for ln in out.splitlines() if re.search(r"openjd_progress: 100|exited with code|Running step|"
                                                                r"\[flowbsdf\] (bound|saved)|Duration", ln)))
    assert code == 0 and "Session ended successfully" in out, out[-4000:]
    assert out.count("openjd_progress: 100") == 3 and out.count("exited with code: 0") == 4
    assert out.index("Running step 'Assemble'") > out.rindex("openjd_progress: 100")
    saved = shot / "scene.flowbsdf.blend"
    assert "[flowbsdf] bound 3 material(s): matte, plastic, rough_metal" in out
    assert f"[flowbsdf] saved {saved}" in out and saved.is_file()
    for name in ("matte", "plastic", "rough_metal"):
        assert (shot / "flowbsdf" / "tables" / f"{name}.exr").is_file()

    # The saved file holds the bound nodes; on the shot, the Flamenco job type's `eval` settings
    # (evaluated at submission by Flamenco's add-on, as it does: eval(expr, {}, {bpy, C})) find
    # this scene's materials, manifest, shared folder and save path.
    evals = {}
    if NODE is not None:
        settings = _compile(tmp_path)["jobType"]["settings"]
        evals = {s["key"]: s["eval"] for s in settings if "eval" in s}
    (tmp_path / "evals.json").write_text(json.dumps(evals))
    (tmp_path / "check.py").write_text(CHECK_SAVED)
    code, out = _run([blender, "-b", "--python", tmp_path / "check.py", "--", saved, shot / "scene.blend", addons,
                      tmp_path / "evals.json"])
    assert "GROUPS ['Learned BSDF: matte', 'Learned BSDF: plastic', 'Learned BSDF: rough_metal']" in out, out[-2000:]
    got = json.loads(re.search(r"^EVALS (.*)$", out, re.M).group(1))
    if evals:
        assert got == {"materials": "matte,plastic,rough_metal", "manifest": str(shot / "flowbsdf" / "manifest.toml"),
                       "shared_out": str(shot / "flowbsdf"), "save_as": str(saved)}


CHECK_SAVED = """
import json, sys, bpy
saved, scene, addons, evals = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.wm.open_mainfile(filepath=saved)
print("GROUPS", sorted(n.node_tree.name for m in bpy.data.materials if m.node_tree
                       for n in m.node_tree.nodes if n.bl_idname == "ShaderNodeGroup"))
bpy.ops.wm.open_mainfile(filepath=scene)
sys.path.insert(0, addons)
import flowbsdf
flowbsdf.register()
names = {"bpy": bpy, "C": bpy.context}
print("EVALS", json.dumps({k: eval(e, {}, names) for k, e in json.load(open(evals)).items()}))
"""


# -- the Flamenco job type (node, with a stub `author`: not the Flamenco manager) -----------------

JOB_TYPE = ROOT / "blender_addon" / "artist" / "farm" / "flowbsdf_bake.js"
NODE = shutil.which("node")
HARNESS = """
const fs = require("fs"), vm = require("vm");
const [file, settingsJson] = process.argv.slice(2);
const tasks = [];
const author = {
    Task: (name, type) => ({ name, type, commands: [], deps: [],
        addCommand(c) { this.commands.push(c); }, addDependency(t) { this.deps.push(t.name); } }),
    Command: (type, params) => ({ type, params }),
};
const context = vm.createContext({ author, print: () => {} });
vm.runInContext(fs.readFileSync(file, "utf8") + "\\nthis.JOB_TYPE = JOB_TYPE; this.compileJob = compileJob;", context);
const job = { settings: JSON.parse(settingsJson), addTask: (t) => tasks.push(t) };
try { context.compileJob(job); } catch (e) { console.log(JSON.stringify({ error: String(e) })); process.exit(0); }
console.log(JSON.stringify({ jobType: context.JOB_TYPE, tasks: tasks.map(
    ({ name, type, commands, deps }) => ({ name, type, commands, deps })) }));
"""
SETTINGS = {"materials": "matte, plastic", "manifest": "/s/flowbsdf/manifest.toml", "shared_out": "/s/flowbsdf",
            "train": "auto", "python": "/opt/fb/python", "train_task_type": "torch", "assemble": True,
            "save_as": "/s/shot.flowbsdf.blend", "addon_dir": "", "blendfile": "/jobs/shot.blend"}


def _compile(tmp_path, **overrides):
    harness = tmp_path / "harness.js"
    harness.write_text(HARNESS)
    proc = subprocess.run([NODE, harness, JOB_TYPE, json.dumps({**SETTINGS, **overrides})],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def _exec(name, stage, settings=SETTINGS):
    return {"type": "exec", "params": {"exe": settings["python"], "args": [
        "-m", "bake.plumbing.cli", "farm", "task", settings["manifest"], "--material", name, "--out",
        settings["shared_out"], "--train", settings["train"], "--stage", stage]}}


@pytest.mark.skipif(NODE is None, reason="node is not installed")
def test_flamenco_job_type_task_graph_in_a_node_stub_harness_not_the_flamenco_manager(tmp_path):
    proc = subprocess.run([NODE, "--check", JOB_TYPE], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    result = _compile(tmp_path)
    expected = []
    for name in ("matte", "plastic"):
        expected += [{"name": f"train-{name}", "type": "torch", "commands": [_exec(name, "train")], "deps": []},
                     {"name": f"bake-{name}", "type": "misc", "commands": [_exec(name, "bake")],
                      "deps": [f"train-{name}"]}]
    expected.append({"name": "assemble", "type": "blender", "deps": ["bake-matte", "bake-plastic"], "commands": [
        {"type": "blender-render", "params": {
            "exe": "{blender}", "exeArgs": "{blenderArgs}", "argsBefore": [], "blendfile": "/jobs/shot.blend",
            "args": ["--python-expr", farm.blender_expr(""), "--", "bake", "--train", "never", "--out",
                     "/s/flowbsdf", "--python", "/opt/fb/python", "--save-as", "/s/shot.flowbsdf.blend"]}}]})
    assert result["tasks"] == expected
    keys = {s["key"] for s in result["jobType"]["settings"]}
    assert keys == set(SETTINGS)

    never = _compile(tmp_path, train="never", assemble=False, addon_dir="/farm/addons")["tasks"]
    assert [(t["name"], t["deps"]) for t in never] == [("bake-matte", []), ("bake-plastic", [])]
    assert never[0]["commands"] == [_exec("matte", "bake", {**SETTINGS, "train": "never"})]
    with_dir = _compile(tmp_path, addon_dir="/farm/addons")["tasks"][-1]["commands"][0]["params"]["args"]
    assert with_dir[1] == farm.blender_expr("/farm/addons")
    assert "no materials" in _compile(tmp_path, materials=" , ")["error"]

    # What a worker's exec runs, in dependency order: each stage is a valid `flowbsdf farm task`.
    (tmp_path / "m.toml").write_text(f'[defaults]\nbake = {DRAFT}\n[[material]]\nname = "matte"\n'
                                     'source = { kind = "analytic", model = "lambert", albedo = 0.5 }\n'
                                     'bake = { source = "ideal" }\n')
    local = {**SETTINGS, "materials": "matte", "manifest": str(tmp_path / "m.toml"),
             "shared_out": str(tmp_path / "out"), "python": sys.executable}
    for task in _compile(tmp_path, **local)["tasks"][:2]:
        params = task["commands"][0]["params"]
        code, out = _run([params["exe"], *params["args"]])
        assert code == 0, out[-2000:]
        assert "[progress 100%] matte: done" in out
    assert (tmp_path / "out" / "tables" / "matte.exr").is_file()
