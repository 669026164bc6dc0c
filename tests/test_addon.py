"""The Blender add-on with the bpy module: registration, scan, operators, batch command, zip."""
import os
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")
import cycles_scenes as cs  # noqa: E402  (tests/ helper of the node tests)

from bake.plumbing.manifest import load_manifest  # noqa: E402


def _addon():
    import blender_addon
    return blender_addon


def test_register_unregister_twice():
    addon = _addon()
    for _ in range(2):
        addon.register()
        assert hasattr(bpy.types.Material, "flowbsdf") and hasattr(bpy.types.Scene, "flowbsdf")
        assert bpy.ops.flowbsdf.scan.get_rna_type().identifier == "FLOWBSDF_OT_scan"
        assert "FLOWBSDF_PT_node_editor" in dir(bpy.types)
        addon.unregister()
        assert not hasattr(bpy.types.Material, "flowbsdf") and not hasattr(bpy.types.Scene, "flowbsdf")
        assert "FLOWBSDF_PT_node_editor" not in dir(bpy.types)
        with pytest.raises((AttributeError, KeyError, RuntimeError)):
            bpy.ops.flowbsdf.scan.get_rna_type()


@pytest.fixture(scope="module")
def addon():
    a = _addon()
    a.register()
    yield a
    a.unregister()


def learned(mat_name, analytic, quality="DRAFT", **kw):
    mat = bpy.data.materials.new(mat_name)
    s = mat.flowbsdf
    s.enabled, s.source_kind, s.analytic_preset, s.bake_quality = True, "ANALYTIC", analytic, quality
    for k, v in kw.items():
        setattr(s, k, v)
    return mat


def mesh_object(name, mat, coll=None):
    scene = bpy.context.scene
    ob = bpy.data.objects.new(name, bpy.data.meshes.new(name))
    (coll or scene.collection).objects.link(ob)
    if mat is not None:
        ob.data.materials.append(mat)
    return ob


def one_learned_object(out, name):
    """An empty scene baking into `out` with one object of a learned matte (Fast training)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.context.scene.flowbsdf.out_dir = str(out)
    mat = learned(name, "MATTE", preset="FAST")
    mesh_object("o", mat)
    return mat


def test_scan_lists_only_what_renders(addon, tmp_path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.flowbsdf.out_dir = str(tmp_path / "out")
    mesh_object("visible", learned("shown", "MATTE"))
    mesh_object("hidden", learned("hidden_obj", "MATTE")).hide_render = True
    hidden_coll = bpy.data.collections.new("hidden_coll")
    scene.collection.children.link(hidden_coll)
    hidden_coll.hide_render = True
    mesh_object("in_hidden", learned("hidden_coll_mat", "MATTE"), hidden_coll)
    excluded = bpy.data.collections.new("excluded")
    scene.collection.children.link(excluded)
    bpy.context.view_layer.layer_collection.children["excluded"].exclude = True
    mesh_object("in_excluded", learned("excluded_mat", "MATTE"), excluded)
    # a collection instanced by a visible empty, itself not in the scene
    lib = bpy.data.collections.new("instanced")
    mesh_object("instanced_obj", learned("via_instance", "PLASTIC", name="plastic_x"), lib)
    empty = bpy.data.objects.new("instancer", None)
    empty.instance_type, empty.instance_collection = "COLLECTION", lib
    scene.collection.objects.link(empty)
    mesh_object("plain", bpy.data.materials.new("not_learned"))
    learned("unused", "GOLD")

    bpy.ops.flowbsdf.scan()
    items = {i.material: i for i in scene.flowbsdf.scan_items}
    assert set(items) == {"shown", "via_instance"}
    assert items["via_instance"].learned == "plastic_x"
    assert items["shown"].state == "missing" and "theta_i only" in items["shown"].needs
    manifest = load_manifest(tmp_path / "out" / "manifest.toml")
    by_name = {e.name: e for e in manifest.materials}
    assert set(by_name) == {"shown", "plastic_x"}
    assert by_name["plastic_x"].source == {"kind": "analytic", "model": "plastic",
                                           "albedo": [0.7, 0.1, 0.08], "alpha": 0.12}
    assert by_name["shown"].bake["resolution"] == 16
    text = (tmp_path / "out" / "manifest.toml").read_text()
    assert "used by 1 object(s): instanced_obj" in text and "state: missing" in text


def test_the_manifest_names_a_measured_file_relative_to_itself(tmp_path):
    """The scan's manifest names a material's file relative to the manifest's folder (the project
    moves as one folder), and the bake finds the file from there."""
    from types import SimpleNamespace
    from blender_addon.artist import scan
    measured = tmp_path / "files" / "silk.bsdf"
    measured.parent.mkdir()
    measured.write_bytes(b"x")
    row = {"entry": {"name": "silk", "source": str(measured), "bake": {"resolution": 16}}, "name": "silk",
           "material": SimpleNamespace(name="silk"), "users": ["ball"]}
    path = scan.write_manifest([row], tmp_path / "out" / "manifest.toml")
    assert 'source = "../files/silk.bsdf"' in Path(path).read_text()
    entry = load_manifest(path).materials[0]
    assert entry.source_path().resolve() == measured.resolve() and not entry.missing()


def test_operator_errors_are_messages(addon, tmp_path, monkeypatch):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.context.scene.flowbsdf.out_dir = str(tmp_path)
    with pytest.raises(RuntimeError, match="no learned materials in use"):
        bpy.ops.flowbsdf.bake()
    mat = learned("broken", "MATTE")
    mat.flowbsdf.source_kind = "FILE"
    mesh_object("o", mat)
    with pytest.raises(RuntimeError, match="'broken': pick an RGL .bsdf or MERL .binary file"):
        bpy.ops.flowbsdf.scan()
    mat.flowbsdf.source_kind, mat.flowbsdf.analytic_params = "ANALYTIC", "{alpha: 2"
    with pytest.raises(RuntimeError, match="'broken': parameters are not JSON"):
        bpy.ops.flowbsdf.scan()
    mat.flowbsdf.analytic_params = '{"albedo": 7}'          # the worker reports the bad value
    with pytest.raises(RuntimeError, match="(?i)albedo"):
        bpy.ops.flowbsdf.bake()
    mat.flowbsdf.analytic_params = ""
    monkeypatch.setenv("FLOWBSDF_PYTHON", str(tmp_path / "no_python"))
    with pytest.raises(RuntimeError) as err:
        bpy.ops.flowbsdf.bake()
    # One short line for the report popup; what to do is in the panel (and the console).
    report = str(err.value).strip().splitlines()
    assert len(report) == 1 and len(report[0]) < 160, report
    assert "FlowBSDF Python does not exist: " in report[0] and "(details in the FlowBSDF panel)" in report[0]
    panel = bpy.context.window_manager.flowbsdf_job.message
    assert "Preferences > Add-ons > FlowBSDF > Python" in panel and "numpy and OpenEXR" in panel, panel
    assert "checkout" not in panel                      # baking needs no FlowBSDF checkout


def _fake_probe(monkeypatch, **over):
    from blender_addon import deps
    info = {"ok": True, "numpy": True, "openexr": True, "torch": False, "trainer": False, "bake": "/x/bake",
            "error": None, "executable": sys.executable, "base_prefix": sys.base_prefix,
            "version": list(sys.version_info[:3]), **over}
    monkeypatch.setattr(deps, "probe", lambda python, extra_paths=(): info)
    monkeypatch.delenv("FLOWBSDF_PYTHON", raising=False)
    return deps


def test_training_without_torch_says_where_to_set_python(addon, monkeypatch):
    deps = _fake_probe(monkeypatch)
    assert deps.choose_python("", need_train=False) == sys.executable
    with pytest.raises(deps.PythonNotFound) as err:
        deps.choose_python("", need_train=True)
    assert str(err.value) == f"cannot train: Blender's Python ({sys.executable}) lacks torch, FlowBSDF's trainer"
    assert "Preferences > Add-ons > FlowBSDF > Python" in err.value.details
    assert ".venv/bin/python" in err.value.details          # the trainer only comes with a checkout
    with pytest.raises(deps.PythonNotFound) as err:
        deps.choose_python("", need_train=True, where="batch")
    assert "--python PATH" in err.value.details
    # The preferences tell the truth about the same Python.
    text = " ".join(t for t, _ in deps.summary(""))
    assert "Blender's Python" in text and "cannot train" in text and "lacks torch" in text, text


def test_a_python_blender_only_reports_is_not_called_blenders_own(addon, monkeypatch):
    """Debian's Blender 3.4 reports the python3.11 first on PATH (here a pyenv shim) as
    sys.executable; messages must not call that "Blender's Python"."""
    deps = _fake_probe(monkeypatch, openexr=False, executable="/opt/pyenv/versions/3.11.7/bin/python3.11",
                       base_prefix="/opt/pyenv/versions/3.11.7")
    with pytest.raises(deps.PythonNotFound) as err:
        deps.choose_python("")
    text = str(err.value) + " " + err.value.details + " ".join(t for t, _ in deps.summary(""))
    assert "Blender's Python" not in text, text
    assert "the Python Blender finds on PATH" in text and "/opt/pyenv/versions/3.11.7/bin/python3.11" in text
    assert str(err.value) == "cannot bake: the default Python lacks OpenEXR"


def test_preferences_say_which_python_trains(addon, monkeypatch):
    """With torch and the trainer (this venv), the preferences say training happens there."""
    from blender_addon import deps
    monkeypatch.delenv("FLOWBSDF_PYTHON", raising=False)
    deps.clear_probes()
    info = deps.probe(sys.executable)
    if not (info["torch"] and info["trainer"]):
        pytest.skip("this Python has no torch/trainer")
    text = " ".join(t for t, _ in deps.summary(""))
    assert "has torch and the trainer: Train + Bake trains there; Bake never trains" in text, text
    assert "training is off" not in text


def test_bake_never_trains_and_the_two_buttons_say_what_they_do(addon, tmp_path, monkeypatch):
    """"Bake" with a Python that could train (this venv has torch) bakes from the ideal
    tabulation; only "Train + Bake" trains. Their tooltips differ and give the time."""
    from blender_addon.artist import operators
    monkeypatch.delenv("FLOWBSDF_PYTHON", raising=False)
    mat = one_learned_object(tmp_path, "never_trained")
    with bpy.context.temp_override(material=mat):
        assert bpy.ops.flowbsdf.bake(only_active=True) == {"FINISHED"}
    assert (tmp_path / "tables" / "never_trained.exr").is_file()
    assert not (tmp_path / "models").exists()
    manifest = (tmp_path / "manifest.toml").read_text()
    assert "state: current" in manifest and "tables from the material; no trained model" in manifest
    tips = {cls.bl_idname: cls.TOOLTIPS for cls in (operators.FLOWBSDF_OT_bake, operators.FLOWBSDF_OT_train_bake)}
    bake, train = tips["flowbsdf.bake"], tips["flowbsdf.train_bake"]
    assert "Never trains" in bake[True] and "Final: 1-4 min" in bake[True]
    assert "Balanced: 2-3 min" in train[True] and "torch" in train[True]
    assert bake[True] != train[True] and bake[False] != train[False] and bake[True] != bake[False]


def test_tables_from_a_model_without_one_fails_with_what_to_do(addon, tmp_path, monkeypatch):
    """Tables > From: Trained model makes the manifest's bake source "flow"; Bake (never trains)
    without a model fails that material with the ways out, and writes no tables; Material
    (the default) bakes from the material itself."""
    from blender_addon.artist.props import manifest_entry
    monkeypatch.delenv("FLOWBSDF_PYTHON", raising=False)
    mat = one_learned_object(tmp_path, "wants_model")
    assert mat.flowbsdf.tables_from == "MATERIAL" and manifest_entry(mat)["bake"]["source"] == "auto"
    mat.flowbsdf.tables_from = "MODEL"
    assert manifest_entry(mat)["bake"]["source"] == "flow"
    with bpy.context.temp_override(material=mat), pytest.raises(RuntimeError, match="its tables come from a trained model"):
        bpy.ops.flowbsdf.bake(only_active=True)       # an operator's ERROR report raises in background
    state = bpy.context.window_manager.flowbsdf_job
    assert state.failed and "it has none: Train + Bake, Load Model, or set From (under Tables): Material" in state.message
    assert not (tmp_path / "tables" / "wants_model.exr").exists()


def test_job_progress_and_cancel(tmp_path):
    """A worker job reports progress lines and a cancel ends it and its process group."""
    from blender_addon.artist import worker
    manifest = tmp_path / "m.toml"
    manifest.write_text('[[material]]\nname = "slow"\nsource = { kind = "analytic", model = "ggx", '
                        'alpha = 0.05 }\nbake = { tol = 0.0001, resolution = 256 }\n')
    job = worker.Job(sys.executable, ["bake", str(manifest), "--out", str(tmp_path / "out"), "--train", "never"])
    deadline = time.monotonic() + 120
    while not any(line.startswith("[progress 1/1]") for line in job.lines) and time.monotonic() < deadline:
        job.poll()
        time.sleep(0.05)
    assert job.message in ("bake slow", "Baking slow: tabulating the material") and job.fraction < 0.05
    job.cancel()
    while not job.done and time.monotonic() < deadline:
        job.poll()
        time.sleep(0.05)
    assert job.done and job.error == "cancelled"
    with pytest.raises(ProcessLookupError):
        os.killpg(job.proc.pid, 0)          # the whole group is gone
    assert not (tmp_path / "out" / "tables" / "slow.exr").exists()


def _worker_main():
    import importlib.util
    spec = importlib.util.spec_from_file_location("worker_main", ROOT / "blender_addon" / "artist" / "worker_main.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _fed_progress(monkeypatch, name, prefix=""):
    """(worker_main, a BakeProgress of `name` on a fake clock, the lines it emits, (done, line)
    per fed line, feed(t, text): log prefix + text at time t, the clock's [now])."""
    wm = _worker_main()
    lines, steps, now = [], [], [0.0]
    monkeypatch.setattr(wm, "emit", lines.append)
    from bake.core.settings import BakeSettings
    progress = wm.BakeProgress(name, BakeSettings(), clock=lambda: now[0])

    def feed(t, text):
        now[0] = t
        progress.log(prefix + text)
        steps.append((progress.done, lines[-1]))
    return wm, progress, lines, steps, feed, now


def test_bake_progress_in_words_from_the_planner_log(monkeypatch):
    """The planner's log (resolution probe, one line per added angle) becomes a moving fraction
    and words with the time left; between lines the time left counts down."""
    wm, progress, lines, steps, feed, now = _fed_progress(monkeypatch, "MilitaryGreen")
    feed(8.0, "[bake] MilitaryGreen: resolution 16: single-bin rv 100.25x the target or more")
    assert steps[-1][1] == "[step 0.050] Baking MilitaryGreen: choosing the table resolution (1 of 5)"
    for t, r in ((9, 24), (10, 32), (13, 48), (18, 64)):
        feed(float(t), f"[bake] MilitaryGreen: resolution {r}: single-bin rv 4.05x the target or more")
    from bake.core.planner import bin_bytes, layout_bytes
    assert progress.resolution == 64 and progress.max_bins() == 44      # 64² cells in 4 MB, beside two layouts' edges
    assert 44 * bin_bytes(64) + 2 * layout_bytes(64) <= 4_000_000 < 45 * bin_bytes(64) + 2 * layout_bytes(64)
    scores = [228.5, 141, 104, 73, 55, 54, 42.25, 21.85, 15.5, 9.9, 9.1]      # x the target
    for k, score in enumerate(scores):
        feed(30.0 + 10 * k, f"[bake] MilitaryGreen: bins {7 + k}: split 1.00-2.00 deg (midpoint loss {score}x its target)")
    assert all(text.startswith("[bake] ") or text.startswith("[step ") for text in lines)
    assert sum(text.startswith("[bake] MilitaryGreen: bins") for text in lines) == len(scores)  # the log keeps them
    words = steps[-1][1]
    import re
    m = re.match(r"\[step ([0-9.]+)\] Baking MilitaryGreen: 17 of about (\d+) angles, about (\d+) min left$", words)
    assert m, words
    assert 17 < int(m.group(2)) <= 34 and 0.3 < float(m.group(1)) < 0.95
    fractions = [f for f, _ in steps]
    assert fractions == sorted(fractions) and 0 < fractions[-1] < 1
    # The heartbeat: 60 s later the time left is a minute shorter, the bar has moved.
    before = int(m.group(3))
    now[0] += 60.0
    progress.report()
    m2 = re.match(r"\[step ([0-9.]+)\] .* about (\d+) (min|s) left$", lines[-1])
    assert m2 and float(m2.group(1)) > float(m.group(1)), lines[-1]
    assert (int(m2.group(2)) if m2.group(3) == "min" else 0) <= before - 1, (words, lines[-1])
    # The comparison of cell placements between bins (isotropic; test_bake_progress_through_the_placements)
    feed(200.0, "[bake] MilitaryGreen: between bins: comparing 5 cell placements on 17 angles")
    assert "comparing cell placements across 17 angles (0 of 5 done, about " in lines[-1], lines[-1]
    # The tables' build (from a flow's points it may take longer than the planning): its own pace.
    feed(300.0, "[bake] MilitaryGreen: tables: building 34 angles")
    assert "building the tables (0 of 34 angles done" in lines[-1], lines[-1]
    feed(320.0, "[bake] MilitaryGreen: tables: built 4 of 34")
    m3 = re.match(r"\[step ([0-9.]+)\] Baking MilitaryGreen: building the tables \(4 of 34 angles done, "
                  r"about (\d+) (min|s) left\)$", lines[-1])
    # 20 s per 4 angles: 150 s left, then the textures, the fit and the preview (AFTER_TABLES): 15.5 s
    assert m3 and m3.group(2, 3) == ("3", "min"), lines[-1]
    assert float(m3.group(1)) >= float(m2.group(1))
    feed(350.0, "[svm] wrote /x/MilitaryGreen.svm1-0.exr")
    assert lines[-1].endswith("Baking MilitaryGreen: writing the node's textures and closure fit, about 20 s left")
    assert wm.time_left(5) == "a few seconds left" and wm.time_left(40) == "about 40 s left"
    assert wm.time_left(75) == "about 1 min left" and wm.time_left(610) == "about 10 min left"


def test_bake_progress_through_the_placements(monkeypatch):
    """The comparison of cell placements between bins (planner._between_bins: a minute and a half
    of a Final bake, measured) has its share of the bar: counted before it begins (ISO_PLACEMENTS
    placements of PLACEMENT_COST split turns per angle), then each at its measured pace, so the bar
    moves while it runs and the time left falls. A plan that ends on its memory budget says it is
    done (planner.plan_tables), and its angles left count no more."""
    from bake.core import planner
    wm, progress, lines, steps, feed, now = _fed_progress(monkeypatch, "Silk", prefix="[bake] Silk: ")
    feed(2.0, "wo: resolution 48: single-bin rv 0.80x the target")
    feed(4.0, "halfpolar: resolution 48: single-bin rv 0.90x the target")
    t, wo, hp = 4.0, 100.0, 200.0
    for k in range(7, 12):      # turns of 2 s each; wo's midpoints come down slowly: many angles to go
        t += 2.0
        feed(t, f"wo: bins {k}: split 1.00-2.00 deg (midpoint loss {wo}x its target)")
        t += 2.0
        feed(t, f"halfpolar: bins {k}: split 1.00-2.00 deg (midpoint loss {hp}x its target)")
        wo, hp = wo / 1.25, hp / 2
    t += 2.0
    now[0] = t
    before = progress.estimate(t)[0]        # elapsed / (elapsed + time left)
    budget = planner._budget_full(11, 4_000_000)      # what the planner says
    assert progress.ENDED.match(budget), budget
    feed(t, "wo: " + budget)
    after = progress.estimate(t)[0]
    assert t / after - t < t / before - t - 20.0, (before, progress.estimate(t))      # wo's angles left: 2 s each
    for k in range(12, 16):
        t += 2.0
        feed(t, f"halfpolar: bins {k}: split 1.00-2.00 deg (midpoint loss {hp}x its target)")
        hp /= 2
    feed(t + 2.0, "halfpolar: bins 15: done, the worst midpoint loses 0.50x its target")
    feed(t + 2.0, "coordinates: halfpolar (midpoints over their targets, typical / worst: halfpolar 1.07x / 1.49x)")
    t += 2.0
    feed(t, "between bins: comparing 3 cell placements on 15 angles")
    # elapsed 36 s; the placements and the draws 4 x 0.15 x 15 angles x 2 s = 18 s, the build 3 s,
    # what follows the tables 15.5 s: 36.5 s
    assert lines[-1] == "[step 0.497] Baking Silk: comparing cell placements across 15 angles (0 of 3 done, " \
                        "about 40 s left)", lines[-1]
    during = [steps[-1]]
    for k in range(1, 4):       # the draws and each placement 5 s: the heartbeat between them
        now[0] = t + 5.0 * k + 2.5
        progress.report()
        during.append((progress.done, lines[-1]))
        feed(t + 5.0 * (k + 1), f"between bins: placement {k} of 3, two groups split at 55.10 deg: 1.21x the ideal's rv")
        during.append(steps[-1])
    bars, lefts = [f for f, _ in during], [_seconds_left(w) for _, w in during]
    assert all(a < b for a, b in zip(bars, bars[1:])) and bars[-1] < 0.99, during
    assert lefts == sorted(lefts, reverse=True) and lefts[-1] <= lefts[0] - 10, during     # (20 s of placements)
    assert lines[-1] == "[step 0.752] Baking Silk: comparing cell placements across 15 angles (3 of 3 done, " \
                        "about 20 s left)", lines[-1]


def test_bake_progress_moves_through_the_fit_and_preview(monkeypatch):
    """After the tables, the node's textures, the closure fit and the preview (AFTER_TABLES: their
    measured costs) move the bar and count the time left down, where the bar used to sit at a
    fixed 97 % and 98 % for the fit's ~13 s (minutes on a busy machine); once the textures are
    written, the steps left go at their pace (here twice their cost: twice the time left for the fit)."""
    wm, progress, lines, steps, feed, now = _fed_progress(monkeypatch, "Silk")
    costs = dict(progress.AFTER_TABLES)
    feed(100.0, "[bake] Silk: tables: building 10 angles")
    feed(110.0, "[bake] Silk: tables: built 10 of 10")
    feed(110.0, "[bake] Silk: tables in 110.0 s")
    assert "writing the node's textures and closure fit, about 20 s left" in lines[-1], lines[-1]
    feed(110.0 + 2 * costs["svm"], "[svm] wrote /x/Silk.svm4-0.exr")
    t = 110.0 + 2 * (costs["svm"] + costs["osl"])
    feed(t, "[osl] wrote /x/Silk.osl8-0.exr")
    assert lines[-1].endswith("Baking Silk: fitting the node's closures, about 30 s left"), lines[-1]   # 2 x 14.5 s
    during = [steps[-1]]
    for k in range(1, 5):       # heartbeats while the fit runs
        now[0] = t + 5.0 * k
        progress.report()
        during.append((progress.done, lines[-1]))
    feed(t + 2 * costs["fit"], "[fit] wrote /x/Silk.fit.json (relative L1 of f cos against the file: median 0.1, max 0.3)")
    feed(t + 2 * costs["fit"], "[preview] Silk: 96x96, 32 spp, shader ball under a soft sky")
    assert lines[-1].endswith("Baking Silk: rendering a preview, a few seconds left"), lines[-1]
    during.append(steps[-1])
    # (the bar holds while the fit's paced estimate catches up with what the build's promised, then moves)
    bars, lefts = [f for f, _ in during], [_seconds_left(w) for _, w in during]
    assert bars == sorted(bars) and bars[0] < bars[-2] < bars[-1] < 0.99, during
    assert lefts == sorted(lefts, reverse=True) and lefts[-1] < lefts[0], during

def _seconds_left(words):
    """The time left in a progress line's words, in seconds ("about 2 min left": 120)."""
    import re
    m = re.search(r"(a few seconds|about (\d+) (s|min)) left", words)
    assert m, words
    return 5 if m.group(2) is None else int(m.group(2)) * (60 if m.group(3) == "min" else 1)


def test_bake_progress_follows_plans_in_turns(monkeypatch):
    """An isotropic material's plans over each cell layout run in turns (planner._plan_in_turns):
    each plan is followed on its own, its pace is its own turns (from its line to the next plan's),
    and the time left is every running plan's angles left at its own pace, measured."""
    wm, progress, lines, steps, feed, now = _fed_progress(monkeypatch, "Satin", prefix="[bake] Satin: ")
    feed(5.0, "wo: resolution 64: single-bin rv 0.80x the target")
    feed(15.0, "halfpolar: resolution 48: single-bin rv 0.90x the target")      # wo's first round: 10 s
    t, wo, hp = 15.0, 100.0, 200.0
    for k in range(7, 12):      # wo's turns take 4 s, halfpolar's 6 s (its first round 12 s)
        t += 12.0 if k == 7 else 6.0
        feed(t, f"wo: bins {k}: split 1.00-2.00 deg (midpoint loss {wo}x its target)")
        t += 4.0
        feed(t, f"halfpolar: bins {k}: split 1.00-2.00 deg (midpoint loss {hp}x its target)")
        wo, hp = wo / 2, hp / 2
    assert progress.plans[0].turns == [10.0] + [4.0] * 5 and progress.plans[1].turns == [12.0] + [6.0] * 4
    words = [w for _, w in steps]
    # until both plans have three splits and a measured turn, no time left is made up
    assert all(w.endswith("estimating the time left") for w in words[:7]), words
    # after the plans the kept plan's placements (test_bake_progress_through_the_placements) and
    # build, at the costlier plan's angles and pace until one is kept: here halfpolar's
    assert words[7] == "[step 0.184] Baking Satin: layout 2 of 2, 9 of about 18 angles, about 4 min left", words[7]
    # halfpolar at 11 of about 16 angles (5 left at 6 s), wo 4 left at 4 s: 46 s, the placements and
    # their draws 4 x 0.15 x 16 x 6 s = 57.6 s, the build 16 x 6 s / 10 = 9.6 s, what follows the
    # tables 15.5 s: 129 s; 20 s later (the heartbeat) 109 s
    assert words[-1] == "[step 0.356] Baking Satin: layout 2 of 2, 11 of about 16 angles, about 2 min left", words[-1]
    now[0] = t + 20.0
    progress.report()
    assert lines[-1] == "[step 0.456] Baking Satin: layout 2 of 2, 11 of about 16 angles, about 2 min left", lines[-1]
    # a plan that ends counts no more: wo's 2 angles left at 4 s, the placements 4 x 0.15 x 14 x 4 s,
    # the build 14 x 4 s / 10, 15.5 s: 63 s
    feed(t + 26.0, "halfpolar: bins 11: done, the worst midpoint loses 0.50x its target")
    feed(t + 26.0, "wo: bins 12: split 1.00-2.00 deg (midpoint loss 3x its target)")
    assert lines[-1] == "[step 0.607] Baking Satin: layout 1 of 2, 12 of about 14 angles, about 1 min left", lines[-1]
    fractions = [f for f, _ in steps]
    assert fractions == sorted(fractions) and 0 < fractions[-1] < 1


def test_progress_moves_within_one_material(tmp_path):
    """One material's bake: the job's fraction moves between 0 and 1 and its message is the
    artist's words ("Baking plastic: 7 of about 12 angles, ..."), not the planner's."""
    from blender_addon.artist import worker
    manifest = tmp_path / "m.toml"
    manifest.write_text('[[material]]\nname = "plastic"\nsource = { kind = "analytic", model = "plastic", '
                        'albedo = [0.7, 0.1, 0.08], alpha = 0.12 }\nbake = { resolution = 16, tol = 0.02, '
                        'first_bins = 3, samples = 2048, grid = 96, ideal_resolution = 48 }\n')
    job = worker.Job(sys.executable, ["bake", str(manifest), "--out", str(tmp_path / "out")])
    seen = []
    deadline = time.monotonic() + 300
    while not job.done and time.monotonic() < deadline:
        job.poll()
        seen.append((job.fraction, job.message))
        time.sleep(0.02)
    assert job.done and not job.error, job.lines[-5:]
    import re
    inside = [(f, m) for f, m in seen if 0.0 < f < 1.0]
    assert inside and len({f for f, _ in inside}) >= 3, seen[-10:]
    # an isotropic material is planned over each cell layout in turn (planner.ISO_PLANNED)
    for layout in (1, 2):
        assert any(re.match(rf"Baking plastic: layout {layout} of 2, \d+ of about \d+ angles, "
                            r"(about \d+ s|a few seconds) left$", m) for _, m in inside), sorted({m for _, m in seen})
    assert not any(m.startswith("[bake]") for _, m in seen)
    assert any(line.startswith("[bake] plastic: halfpolar: bins ") for line in job.lines)      # the log keeps them
    assert any(line.startswith("[bake] plastic: coordinates: ") for line in job.lines)
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def EXACT():
    """What a bound node renders in a Cycles CPU scene with OSL on and no lamps, in this Blender:
    OSL where its Cycles runs our shader, else the SVM graph where it builds, else the fit."""
    from blender_addon.render import node, osl_script
    if osl_script.osl_compiler_available():
        return "OSL, exact"
    return "SVM, exact" if node.svm_available() else "Fit"


THREE = (("matte", "MATTE"), ("red_plastic", "PLASTIC"), ("gold", "GOLD"))


@pytest.fixture(scope="module")
def baked_scene(addon, tmp_path_factory):
    """Three learned materials on three spheres, scanned and baked (ideal tabulation, draft tables)."""
    cs.bpy_or_skip()
    out = tmp_path_factory.mktemp("addon") / "flowbsdf"
    scene = cs.reset(width=48, height=16, spp=8, osl=True)
    cs.set_world(scene, (1.0, 1.0, 1.0))
    cam = cs.ortho_camera(scene, scale=6.0)
    cam.location.z = 6.0
    scene.flowbsdf.out_dir = str(out)
    for i, (name, preset) in enumerate(THREE):
        # rough gold: a sharp lobe would need more incident bins and a longer bake
        extra = {"analytic_params": '{"alpha": 0.25}'} if name == "gold" else {}
        ob = cs.add_sphere(scene, learned(name, preset, **extra), radius=0.9, segments=32, rings=16)
        ob.location.x = 2.0 * (i - 1)
    assert bpy.ops.flowbsdf.scan() == {"FINISHED"}
    before = {i.material: i.state for i in scene.flowbsdf.scan_items}
    assert bpy.ops.flowbsdf.bake() == {"FINISHED"}
    return scene, out, before


def test_three_materials_scanned_baked_rendered(baked_scene):
    scene, out, before = baked_scene
    assert before == {name: "missing" for name, _ in THREE}
    items = {i.material: i for i in scene.flowbsdf.scan_items}
    assert {k: v.state for k, v in items.items()} == {name: "current" for name, _ in THREE}
    bins = {k: int(v.needs.split(": ")[1].split()[0]) for k, v in items.items()}
    assert all(v.needs.startswith("theta_i only: ") for v in items.values())
    assert bins["matte"] == 3 and min(bins.values()) >= 3, bins
    for name, _ in THREE:
        assert (out / "tables" / f"{name}.exr").is_file()
    from blender_addon.render import node
    for name, _ in THREE:
        group = next(n for n in bpy.data.materials[name].node_tree.nodes if n.bl_idname == "ShaderNodeGroup")
        status = node.node_state(group, scene).text
        assert status == EXACT() if EXACT().endswith("exact") else status.startswith(EXACT() + ", ~"), status
    _check_status_lines(scene, bpy.data.materials["gold"])
    mtime = (out / "tables" / "gold.exr").stat().st_mtime_ns
    assert bpy.ops.flowbsdf.bake() == {"FINISHED"}       # current tables are kept
    assert (out / "tables" / "gold.exr").stat().st_mtime_ns == mtime

    img = cs.render(scene)
    assert img.shape == (16, 48, 3) and np.all(np.isfinite(img))
    matte, red, gold = (img[5:11, c - 3:c + 3].reshape(-1, 3).mean(0) for c in (8, 24, 40))
    # White world, convex sphere: a Lambertian of albedo 0.8 reflects 0.8 in expectation.
    assert abs(matte.mean() - 0.8) < 0.08 and np.ptp(matte) < 0.05, matte
    assert red[0] > 2 * red[1] and red[0] > 2 * red[2], red
    assert gold[0] > 1.5 * gold[2] and gold.mean() > 0.3, gold


def _check_status_lines(scene, mat):
    """The material panel shows the node's status: its text, its step and its detail, each in
    whole lines that fit the sidebar; with OSL, the detail says that every render first compiles
    the shader and what keeps it (Persistent Data), and goes when Persistent Data is on."""
    from types import SimpleNamespace
    from blender_addon.artist import panels, uitext
    from blender_addon.render import node
    group = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeGroup")
    ctx = SimpleNamespace(material=mat, scene=scene, active_object=None, region=None,
                          window_manager=bpy.context.window_manager, preferences=bpy.context.preferences)
    try:
        for persistent in (False, True):
            scene.render.use_persistent_data = persistent
            status = node.node_state(group, scene)
            drawn = []
            panels.draw_renders(_Recorder(drawn), mat, scene, ctx)
            labels = [t for k, t in drawn if k == "label"]
            want = uitext.wrap(status.text, ctx, 1)
            if status.action and not status.operator:         # (with an operator: a button)
                want += uitext.wrap(status.action, ctx, 1)
            if status.detail:
                want += uitext.wrap(status.detail[:1].upper() + status.detail[1:], ctx, 1)
            assert labels == want, (labels, want)
            if status.backend == "osl":
                assert ("Persistent Data" in " ".join(labels)) is not persistent, labels
    finally:
        scene.render.use_persistent_data = False


def test_the_svm_back_end_renders_what_osl_does(baked_scene):
    """The same three spheres with the scene's back end on the SVM graph (every Cycles device),
    Cycles' shading system OSL and SVM: each sphere's mean within noise of the OSL render (all
    sample the baked tables). The graph's textures are packed (svm._image: a file texture read
    through OSL rendered a sphere black now and then)."""
    from blender_addon.render import node
    scene, _, _ = baked_scene
    if not node.svm_available():
        pytest.skip("this Blender cannot build the SVM back end (Ray Portal BSDF and Light Path Portal Depth: 5.0+)")
    means = {}
    try:
        for backend, shading_osl in (("osl", True), ("svm", True), ("svm", False)):
            node.set_backend(scene, backend)
            scene.cycles.shading_system = shading_osl
            for name, _ in THREE:
                group = next(n for n in bpy.data.materials[name].node_tree.nodes if n.bl_idname == "ShaderNodeGroup")
                assert node.node_state(group, scene).text == f"{backend.upper()}, exact", node.node_status(group, scene)
            img = cs.render(scene)
            means[backend, shading_osl] = [img[5:11, c - 3:c + 3].reshape(-1, 3).mean(0) for c in (8, 24, 40)]
    finally:
        node.set_backend(scene, "auto")
        scene.cycles.shading_system = True
    for key in (("svm", True), ("svm", False)):
        for osl, svm in zip(means["osl", True], means[key]):
            assert np.allclose(osl, svm, rtol=0.1, atol=0.03), (key, means)
    textures = [i for i in bpy.data.images if ".svm" in i.filepath]
    assert len(textures) == len(THREE) and all(i.packed_file is not None for i in textures), textures


def test_bake_writes_a_preview_beside_the_tables(baked_scene):
    """Each bake leaves <name>.preview.png beside its tables (the material on the reference
    tracer's shader ball under a soft sky, 96x96) and the panel finds it."""
    from blender_addon.artist import panels
    scene, out, _ = baked_scene
    colours = {}
    for name, _ in THREE:
        path = panels.preview_file(bpy.data.materials[name])
        assert path is not None and Path(path) == out / "tables" / f"{name}.preview.png"
        img = _read_png(path).astype(float)
        assert img.shape == (96, 96, 3)
        colours[name] = img[36:60, 38:58].reshape(-1, 3).mean(0)      # the ball's body
    red, gold, matte = colours["red_plastic"], colours["gold"], colours["matte"]
    assert red[0] > 1.5 * red[1] and red[0] > 1.5 * red[2], colours
    assert gold[0] > 1.3 * gold[2], colours
    assert np.ptp(matte) < 0.2 * matte.mean() and matte.mean() > 60, colours


def test_cli_command_bakes_binds_and_saves(baked_scene, tmp_path, capsys):
    from blender_addon import batch
    scene, out, _ = baked_scene
    assert batch.cli_command(["scan"]) == 0
    text = capsys.readouterr().out
    assert "[flowbsdf] matte -> matte: current; needs theta_i only: 3 bins" in text
    blend = tmp_path / "baked.blend"
    assert batch.cli_command(["bake", "--train", "never", "--save-as", str(blend)]) == 0
    text = capsys.readouterr().out
    assert "[progress 3/3] done" in text and f"[flowbsdf] saved {blend}" in text
    assert all(line == line.strip("\r") for line in text.splitlines())
    assert batch.cli_command(["bake", "--python", str(tmp_path / "nope")]) == 1
    text = capsys.readouterr().out
    assert "[flowbsdf] error: the FlowBSDF Python does not exist" in text and "Pass one with --python PATH" in text
    assert batch.cli_command(["bake", "--material", "not_there"]) == 1
    assert "not_there" in capsys.readouterr().out
    assert "FLOWBSDF_PYTHON" not in os.environ

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    for name, _ in THREE:
        groups = [n for n in bpy.data.materials[name].node_tree.nodes if n.bl_idname == "ShaderNodeGroup"]
        assert len(groups) == 1 and groups[0].node_tree.get("flowbsdf")["material"] == name


def _learned_group(mat):
    from blender_addon.artist import panels
    return panels._learned_group(mat)


def test_paths_follow_the_project_folder(addon, tmp_path):
    """Table paths are stored relative to the .blend: moving the project folder keeps the tables
    rendering; moving the .blend alone, the node and Scan both say the tables are missing."""
    import shutil
    from blender_addon.render import binding, node, osl_script
    cs.bpy_or_skip()
    project = tmp_path / "A"
    project.mkdir()
    scene = cs.reset(width=8, height=8, spp=1)
    cs.set_world(scene, (1.0, 1.0, 1.0))
    mat = learned("moving", "MATTE")
    cs.add_sphere(scene, mat, segments=16, rings=8)
    cs.ortho_camera(scene, scale=2.0)
    scene.flowbsdf.out_dir = "//flowbsdf"
    bpy.ops.wm.save_as_mainfile(filepath=str(project / "shot.blend"))
    assert bpy.ops.flowbsdf.bake() == {"FINISHED"}
    raw = _learned_group(mat).node_tree[binding.TREE_KEY]
    assert raw["tables"] == "//flowbsdf/tables/moving.exr", raw["tables"]
    assert all(raw[k].startswith("//flowbsdf/tables/moving.") for k in binding.PATH_KEYS if raw.get(k)), raw.to_dict()
    svm_images = [i for i in bpy.data.images if "svm" in i.filepath]
    assert all(i.filepath.startswith("//flowbsdf/tables/") for i in svm_images), [i.filepath for i in svm_images]
    bpy.ops.wm.save_mainfile()

    moved = tmp_path / "B"
    shutil.move(project, moved)
    bpy.ops.wm.open_mainfile(filepath=str(moved / "shot.blend"))
    scene, mat = bpy.context.scene, bpy.data.materials["moving"]
    group = _learned_group(mat)
    assert node.node_status(group, scene).startswith(EXACT())
    assert "tables missing" not in node.node_status(group, scene)
    script = group.node_tree.nodes.get(osl_script.SCRIPT)
    if script is not None:
        assert Path(script.inputs["Tables"].default_value).parent == moved / "flowbsdf" / "tables"
    assert all(Path(bpy.path.abspath(i.filepath)).is_file() for i in bpy.data.images if "svm" in i.filepath)
    assert bpy.ops.flowbsdf.scan() == {"FINISHED"}
    assert [i.state for i in scene.flowbsdf.scan_items] == ["current"]
    img = cs.render(scene)
    assert abs(img[3:5, 3:5].mean() - 0.8) < 0.15, img[3:5, 3:5]    # white world, albedo 0.8: not black

    alone = tmp_path / "C"
    alone.mkdir()
    shutil.copy(moved / "shot.blend", alone / "shot.blend")
    bpy.ops.wm.open_mainfile(filepath=str(alone / "shot.blend"))
    scene, mat = bpy.context.scene, bpy.data.materials["moving"]
    status = node.node_status(_learned_group(mat), scene)
    assert "(tables missing). Bake the Material" in status and str(alone / "flowbsdf" / "tables" / "moving.exr") in status
    assert bpy.ops.flowbsdf.scan() == {"FINISHED"}
    assert [i.state for i in scene.flowbsdf.scan_items] == ["missing"]


def test_an_unsaved_file_asks_to_save_first(addon, tmp_path, monkeypatch):
    """The panel and the interactive operators ask to save first (the tables go beside the
    .blend); a script's bake of an unsaved file says exactly where the tables went."""
    from blender_addon.artist import jobs, prefs
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    assert scene.flowbsdf.out_dir == "//flowbsdf"
    assert jobs.unsaved_problem(scene) == "save the .blend first: FlowBSDF writes the tables beside it, in //flowbsdf"
    monkeypatch.setattr(prefs, "user_dir", lambda *parts: str(tmp_path.joinpath("user", *parts)))
    mesh_object("o", learned("unsaved", "MATTE"))
    assert bpy.ops.flowbsdf.bake() == {"FINISHED"}
    message = bpy.context.window_manager.flowbsdf_job.message
    where = tmp_path / "user" / "unsaved" / "Scene"
    assert message.endswith(f"(unsaved file: tables in {where})"), message
    assert (where / "tables" / "unsaved.exr").is_file()
    scene.flowbsdf.out_dir = str(tmp_path / "absolute")
    assert jobs.unsaved_problem(scene) is None


def test_extension_zip_builds_validates_installs(tmp_path):
    """One command builds the zip; Blender's tool validates it; bpy 5.0 installs and enables it."""
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "build_extension.py"), "--out",
                           str(tmp_path / "dist"), "--build-dir", str(tmp_path / "build"), "--no-wheels"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    zip_path = tmp_path / "dist" / "flowbsdf-0.1.0.zip"
    assert "validated" in proc.stdout and zip_path.is_file()
    import zipfile
    names = zipfile.ZipFile(zip_path).namelist()
    assert "blender_manifest.toml" in names and "vendor/bake/plumbing/pipeline.py" in names
    assert "artist/worker_main.py" in names and "render/osl/learned_bsdf.osl" in names
    assert not [n for n in names if n.endswith((".so", ".pyc")) or "trainer/" in n]
    manifest = tomllib.loads(zipfile.ZipFile(zip_path).read("blender_manifest.toml").decode())
    assert manifest["id"] == "flowbsdf" and manifest["blender_version_min"] == "4.2.0"

    script = tmp_path / "install.py"
    script.write_text(INSTALL_SCRIPT)
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user")}
    env.pop("PYTHONPATH", None)
    proc = subprocess.run([sys.executable, str(script), str(zip_path)], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "ENABLED bl_ext.user_default.flowbsdf" in proc.stdout
    assert f"VENDORED {tmp_path / 'user'}" in proc.stdout, proc.stdout
    assert "SCAN ok" in proc.stdout, proc.stdout


INSTALL_SCRIPT = """
import sys, bpy
zip_path = sys.argv[-1]
assert bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                enable_on_install=True) == {"FINISHED"}
assert "bl_ext.user_default.flowbsdf" in bpy.context.preferences.addons.keys()
print("ENABLED bl_ext.user_default.flowbsdf")
from bl_ext.user_default.flowbsdf import deps
from bl_ext.user_default.flowbsdf.artist import prefs
print("VENDORED", deps.bake_root())
from bl_ext.user_default.flowbsdf.render import node
assert deps.bake.__name__ == "bl_ext.user_default.flowbsdf.vendor.bake", deps.bake.__name__
assert hasattr(bpy.types.Scene, "flowbsdf_backend")
assert prefs.get() is not None
mat = bpy.data.materials.new("m")
mat.flowbsdf.enabled = True
mat.flowbsdf.source_kind = "ANALYTIC"
bpy.context.scene.collection.objects.link(bpy.data.objects.new("o", bpy.data.meshes.new("o")))
bpy.data.objects["o"].data.materials.append(mat)
bpy.context.scene.flowbsdf.out_dir = "scan_out"
assert bpy.ops.flowbsdf.scan() == {"FINISHED"}
assert [i.state for i in bpy.context.scene.flowbsdf.scan_items] == ["missing"]
print("SCAN ok")
"""


def _read_png(path):
    """The RGB pixels of a PNG written by bake.tracer.images.write_png (8 bit, filter 0)."""
    import struct
    import zlib
    data, pos, idat = Path(path).read_bytes(), 8, b""
    while pos < len(data):
        n, tag = struct.unpack(">I4s", data[pos:pos + 8])
        if tag == b"IHDR":
            w, h = struct.unpack(">II", data[pos + 8:pos + 16])
        elif tag == b"IDAT":
            idat += data[pos + 8:pos + 8 + n]
        pos += 12 + n
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + 3 * w)
    assert not raw[:, 0].any()
    return raw[:, 1:].reshape(h, w, 3)


def _check_compare_png(folder, result):
    """compare.png: Cycles left, the reference in the middle (their pixels), captions saying so
    and the numbers of metrics.json under them; compare.md says the same."""
    from bake.tracer.images import read_exr, tonemap
    from bake.tracer.label import text_mask
    img = _read_png(folder / "compare.png")
    cycles, ref = (np.asarray(read_exr(folder / f), np.float32)[..., :3] for f in ("cycles.exr", "reference.exr"))
    h, w = cycles.shape[:2]
    k, gap = -(-256 // w), 8

    def panel(i):
        x0 = gap + i * (k * w + gap)
        return img[gap:gap + k * h, x0:x0 + k * w]

    def text_at(x, y, text):
        mask = text_mask(text)
        return np.array_equal((img[y:y + mask.shape[0], x:x + mask.shape[1]] == 235).all(axis=2), mask)
    assert np.array_equal(panel(0), np.kron(tonemap(cycles), np.ones((k, k, 1), np.uint8)))
    assert np.array_equal(panel(1), np.kron(tonemap(ref), np.ones((k, k, 1), np.uint8)))
    y = 2 * gap + k * h
    assert text_at(gap, y, "Cycles") and text_at(gap, y + 20, f"{result['cycles_spp']} spp")
    assert text_at(2 * gap + k * w, y, "Reference tracer")
    assert text_at(2 * gap + k * w, y + 20, f"{result['reference_spp']} spp, MIS")
    footer = f"MSE {result['mse']:.3g}   SSIM {result['ssim']:.3f}"
    assert text_at(gap, y + 2 * 20 + gap, footer), footer
    md = (folder / "compare.md").read_text()
    assert md.count("Left: Cycles") == 1 and footer in md and f"{result['mean_cycles']:.4f}" in md


def _validate_refuses_without_osl():
    """Where this Blender cannot render the OSL back end (the bpy 4.2 wheel), validate refuses,
    saying what renders instead; True then."""
    if EXACT() == "OSL, exact":
        return False
    with pytest.raises(RuntimeError, match="validate compares Cycles' OSL back end with the reference, but here "
                       r"\w+: (SVM|Fit), "):
        bpy.ops.flowbsdf.validate()
    return True


def test_validate_reference_vs_cycles(addon, tmp_path):
    """The validate operator exports the scene, renders it with the reference tracer and Cycles
    (OSL back end) and reports MSE/SSIM with a side-by-side image."""
    import math
    cs.bpy_or_skip()
    scene = cs.reset(width=32, height=32, spp=8)
    cs.set_world(scene, (1.0, 1.0, 1.0))
    cs.add_sphere(scene, learned("red", "PLASTIC"), radius=1.0, segments=32, rings=16)
    floor = cs.material_with(lambda t: t.nodes.new("ShaderNodeBsdfDiffuse").outputs[0], "floor")
    cs.add_plane(scene, floor, size=6).location.z = -1
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.location, cam.rotation_euler = (0, -5, 1.5), (math.radians(75), 0, 0)
    scene.camera = cam
    scene.flowbsdf.out_dir = str(tmp_path / "out")
    scene.flowbsdf.validate_spp, scene.flowbsdf.validate_size = 8, 32
    with pytest.raises(RuntimeError, match="bake first: no tables for red"):
        bpy.ops.flowbsdf.validate()                  # nothing baked yet: a message, no traceback
    assert bpy.ops.flowbsdf.bake() == {"FINISHED"}
    if _validate_refuses_without_osl():
        return
    assert bpy.ops.flowbsdf.validate() == {"FINISHED"}
    import json
    result = json.loads((tmp_path / "out" / "validate" / "metrics.json").read_text())
    assert result["reference_spp"] == 32 and result["cycles_spp"] == 8
    # Same scene, same material, both unbiased: the means agree, the images look alike.
    assert abs(result["mean_cycles"] - result["mean_reference"]) < 0.03 * result["mean_reference"], result
    assert result["ssim"] > 0.7 and result["mse"] < 0.01, result
    assert Path(result["image"]).is_file() and "FlowBSDF validate" in bpy.data.images
    _check_compare_png(tmp_path / "out" / "validate", result)
    assert scene.render.resolution_x == 32 and scene.cycles.samples == 8       # settings restored
    text = (tmp_path / "out" / "validate" / "scene.toml").read_text()
    assert 'manifest = "red"' in text and 'albedo = [0.8, 0.8, 0.8]' in text


@pytest.mark.slow
def test_validate_compares_like_with_like_under_a_sky_and_a_lamp(addon, tmp_path):
    """A Sky Texture world (rendered to an image for the reference) and an area lamp (exported
    with Cycles' radiometry): the OSL back end lights the material with both, the reference
    too, so the two renders agree."""
    import json
    import math
    cs.bpy_or_skip()
    scene = cs.reset(width=24, height=24, spp=16)
    world = bpy.data.worlds.new("sky")
    scene.world = world
    if world.node_tree is None:             # a new world has no node tree before Blender 5.0
        world.use_nodes = True
    tree = world.node_tree
    bg = next(n for n in tree.nodes if n.type == 'BACKGROUND')
    sky = tree.nodes.new("ShaderNodeTexSky")
    sky.sun_elevation, sky.sun_rotation = 0.6, 0.8
    tree.links.new(sky.outputs[0], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 0.05
    cs.add_sphere(scene, learned("red", "PLASTIC"), radius=1.0, segments=32, rings=16)
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", 'AREA'))
    lamp.data.energy, lamp.data.size = 60.0, 1.0
    lamp.location, lamp.rotation_euler = (1.5, -2.0, 2.5), (math.radians(40), 0, math.radians(30))
    scene.collection.objects.link(lamp)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.location, cam.rotation_euler = (0, -5, 0), (math.radians(90), 0, 0)
    scene.camera = cam
    scene.flowbsdf.out_dir = str(tmp_path / "out")
    scene.flowbsdf.validate_spp, scene.flowbsdf.validate_size = 16, 24
    assert bpy.ops.flowbsdf.bake() == {"FINISHED"}
    if _validate_refuses_without_osl():
        return
    assert bpy.ops.flowbsdf.validate() == {"FINISHED"}
    result = json.loads((tmp_path / "out" / "validate" / "metrics.json").read_text())
    assert abs(result["mean_cycles"] - result["mean_reference"]) < 0.05 * result["mean_reference"], result
    text = (tmp_path / "out" / "validate" / "scene.toml").read_text()
    assert "world.exr" in text and 'type = "area"' in text


class _Recorder:
    """A stand-in for UILayout that checks every property and operator the panel names."""

    def __init__(self, log):
        self.log = log

    def __getattr__(self, name):
        if name in ("column", "row", "box", "split"):
            return lambda *a, **k: _Recorder(self.log)
        raise AttributeError(name)

    def prop(self, data, attr, **kw):
        assert attr in data.bl_rna.properties.keys(), f"{type(data).__name__} has no property {attr!r}"
        self.log.append(("prop", attr))

    def operator(self, idname, **kw):
        mod, name = idname.split(".")
        rna = getattr(getattr(bpy.ops, mod), name).get_rna_type()
        self.log.append(("operator", idname))
        props = rna.properties.keys()

        class Props:
            def __setattr__(self, key, value):
                assert key in props, f"{idname} has no property {key!r}"
        return Props()

    def label(self, text="", **kw):
        self.log.append(("label", text))

    def template_icon(self, icon_value=0, scale=1.0):
        assert icon_value > 0
        self.log.append(("icon", icon_value))

    def progress(self, factor=0.0, type="BAR", text=""):
        assert 0.0 <= factor <= 1.0
        self.log.append(("progress", text))


def test_panel_draws_every_state(addon, tmp_path):
    from types import SimpleNamespace
    from blender_addon.artist import panels, worker
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.flowbsdf.out_dir = str(tmp_path)
    mat = bpy.data.materials.new("m")
    mesh_object("o", mat)
    item = scene.flowbsdf.scan_items.add()
    item.material, item.state, item.needs = "m", "current", "theta_i only: 3 bins"
    ctx = SimpleNamespace(material=mat, scene=scene, active_object=None, region=None,
                          window_manager=bpy.context.window_manager, preferences=bpy.context.preferences)
    (tmp_path / "tables").mkdir()
    for name, size in (("m.exr", 1_500_000), ("m.osl8-0123.exr", 600_000), ("world-0123.exr", 400_000)):
        (tmp_path / "tables" / name).write_bytes(b"\0" * size)
    seen = []
    for kind in ("off", "FILE", "ANALYTIC", "PYTHON"):
        mat.flowbsdf.enabled = kind != "off"
        if kind != "off":
            mat.flowbsdf.source_kind = kind
        layout = _Recorder(seen)
        panel = SimpleNamespace(layout=layout)
        panels.FLOWBSDF_PT_material.draw(panel, ctx)
    job = worker.Job(sys.executable, ["probe"])
    worker.current = job
    try:
        panels.draw_job(_Recorder(seen), ctx)
        assert ("operator", "flowbsdf.cancel") in seen
    finally:
        job.run(echo=False)
        worker.current = None
    assert ("label", "Tables: 2.5 MB, 3 files") in seen, [t for k, t in seen if k == "label"]
    _check_packed_line(ctx, tmp_path)
    ops = {name for kind, name in seen if kind == "operator"}
    assert {"flowbsdf.enable", "flowbsdf.bake", "flowbsdf.scan", "flowbsdf.validate", "flowbsdf.set_backend",
            "flowbsdf.make_library"} <= ops
    assert {"filepath", "analytic_preset", "python_callable", "out_dir"} <= {n for k, n in seen if k == "prop"}
    # Only what the chosen route uses: training's settings and buttons with tables from a trained model.
    training = {("prop", "preset"), ("prop", "domain"), ("operator", "flowbsdf.train_bake"),
                ("operator", "flowbsdf.load_model")}
    for tables_from, shown in (("MATERIAL", False), ("MODEL", True)):
        mat.flowbsdf.tables_from = tables_from
        drawn = []
        panels.FLOWBSDF_PT_material.draw(SimpleNamespace(layout=_Recorder(drawn)), ctx)
        assert (training <= set(drawn)) if shown else not training & set(drawn), (tables_from, drawn)
        assert ("operator", "flowbsdf.bake") in drawn


def _check_packed_line(ctx, tmp_path):
    """The scene panel says what FlowBSDF packed into the .blend, how much and why (the SVM back
    end's textures, svm._image), in lines that fit the sidebar; a texture is packed once
    however its path is spelled, and one nothing uses (not saved) is not counted."""
    import numpy as np
    from bake.io.exrio import write_rgba_exr
    from blender_addon.artist import panels, uitext
    from blender_addon.render import svm
    paths = []
    rng = np.random.default_rng(0)
    for k, side in enumerate((256, 128, 16)):       # noise: MBs that compression keeps
        paths.append(tmp_path / "tables" / f"m{k}.svm4-0123.exr")
        write_rgba_exr(paths[-1], rng.random((side, side, 4), np.float32), "flowbsdf", {})
    first = svm._image(str(paths[0]))
    again = [svm._image(p) for p in (paths[0], str(tmp_path / "tables" / ".." / "tables" / paths[0].name))]
    assert all(image == first for image in again)
    used = [first, svm._image(str(paths[1]))]
    svm._image(str(paths[2]))               # packed, but nothing uses it: not saved, not counted
    for image in used:
        image.use_fake_user = True
    assert not [i for i in bpy.data.images if i.packed_file is not None and not i.get(svm.PACKED)]
    size = sum(p.stat().st_size for p in paths[:2]) / 1e6
    assert size > 0.5
    text = f"Packed in the .blend: 2 textures, {size:.1f} MB (the SVM back end reads them)"
    assert panels.packed_use() == text
    drawn = []
    panels.draw_scene(_Recorder(drawn), ctx)
    lines = uitext.wrap(text, ctx)
    labels = [t for k, t in drawn if k == "label"]
    at = labels.index(lines[0])
    assert labels[at:at + len(lines)] == lines and len(lines) <= 3, lines
    assert " ".join(lines) == text          # whole words: nothing cut
    for image in used:
        bpy.data.images.remove(image)
    assert panels.packed_use() == ""


def test_make_asset_library_bakes_in_the_worker_then_writes_the_blend_in_a_background_blender(addon, tmp_path,
                                                                                               monkeypatch):
    """The panel's Make Asset Library: DIR/manifest.toml of the folder's measured files, their bake
    in the worker (the bake's arguments: its progress and Cancel are the bake's), then library.blend
    from a background Blender (`library ... --blend-only`: writing it here would replace the open
    file); a material that failed to bake does not stop the library (jobs are stand-ins here)."""
    from blender_addon.artist import jobs, library, worker
    started = []

    class Job:
        def __init__(self, python, args, extra_paths=(), label="FlowBSDF", script=worker.deps.WORKER_SCRIPT):
            self.python, self.args, self.label, self.script = python, [str(a) for a in args], label, script
            self.cancelled, self.done = False, False
            self.lines = ["[fail] b: unreadable", "[error] 1 material(s) failed"] if not started else ["wrote"]
            self.error = "1 material(s) failed" if not started else None
            started.append(self)

        def run(self, echo=True):
            self.done = True
            if self.error:
                raise worker.JobError(self.error)
            return self.lines
    monkeypatch.setattr(worker, "Job", Job)
    monkeypatch.setattr(worker, "python_for", lambda *a, **k: "/py/worker")
    monkeypatch.setattr(jobs, "blender_program", lambda: "/bin/blender")
    files, out = tmp_path / "measured", tmp_path / "lib"
    (files / "sub").mkdir(parents=True)
    (files / "a.bsdf").write_bytes(b"x")
    (files / "sub" / "b.binary").write_bytes(b"x")
    assert bpy.ops.flowbsdf.make_library(folder=str(files), out=str(out), quality="DRAFT") == {"FINISHED"}
    bake, blend = started
    manifest = out / library.MANIFEST_NAME
    assert (bake.python, bake.script) == ("/py/worker", worker.deps.WORKER_SCRIPT)
    assert bake.args == ["bake", str(manifest), "--out", str(out), "--train", "never"]
    entries = load_manifest(manifest).materials
    assert [e.name for e in entries] == ["a", "b"] and entries[0].bake == {**library.QUALITY["draft"], "carry": True}
    assert (blend.python, blend.script) == ("/bin/blender", None)
    assert blend.args[:3] == ["-b", "--factory-startup", "--python-expr"]
    assert blend.args[4:] == ["--", "library", str(files), "--out", str(out), "--quality", "draft",
                              "--python", "/py/worker", "--blend-only"]
    message = bpy.context.window_manager.flowbsdf_job.message
    assert message.startswith(f"FlowBSDF: asset library {out / 'library.blend'}, 1 material(s) (b failed to bake)")
    # the folder only: the library goes inside it, which the files' listing leaves out
    started.clear()
    assert bpy.ops.flowbsdf.make_library(folder=str(files)) == {"FINISHED"}
    assert started[0].args[3] == str(files / "flowbsdf_library") and started[1].args[-4] == "final"
    with pytest.raises(RuntimeError, match="pick the folder of measured files"):
        bpy.ops.flowbsdf.make_library(folder=str(tmp_path / "none"))


def test_modal_progress_and_cancel(addon, tmp_path):
    """The interactive path: the modal timer polls the job, shows progress, and Cancel stops it."""
    from types import SimpleNamespace
    from blender_addon.artist import operators, worker
    manifest = tmp_path / "m.toml"
    manifest.write_text('[[material]]\nname = "slow"\nsource = { kind = "analytic", model = "ggx", '
                        'alpha = 0.05 }\nbake = { tol = 0.0001, resolution = 256 }\n')

    class Op(operators._JobOperator):
        def __init__(self):
            self.reports = []

        def report(self, kind, message):
            self.reports.append((kind, message))

        def start(self, context):
            return worker.Job(sys.executable, ["bake", str(manifest), "--out", str(tmp_path), "--train", "never"],
                              label="Bake")

    state = SimpleNamespace(running=True, progress=0.0, message="", label="", failed=False)
    wm = SimpleNamespace(flowbsdf_job=state, windows=[], event_timer_remove=lambda timer: None)
    ctx = SimpleNamespace(window_manager=wm)
    op = Op()
    assert op._start(ctx)
    worker.current, op._timer = op._job, None
    timer = SimpleNamespace(type="TIMER")
    assert op.modal(ctx, SimpleNamespace(type="MOUSEMOVE")) == {"PASS_THROUGH"}
    deadline = time.monotonic() + 120
    while not state.message.startswith("Baking slow") and time.monotonic() < deadline:
        assert op.modal(ctx, timer) == {"PASS_THROUGH"}
        time.sleep(0.05)
    assert state.message == "Baking slow: tabulating the material" and state.progress < 5.0
    assert bpy.ops.flowbsdf.cancel() == {"FINISHED"}
    result = None
    while result in (None, {"PASS_THROUGH"}) and time.monotonic() < deadline:
        result = op.modal(ctx, timer)
        time.sleep(0.05)
    assert result == {"CANCELLED"} and not state.running
    assert op.reports == [({"WARNING"}, "FlowBSDF: Bake cancelled")]
    worker.current = None


@pytest.mark.slow
def test_train_then_bake_from_the_panel(addon, tmp_path):
    """Train + Bake: the trainer runs as a subprocess of the worker (torch never in Blender);
    the material's tables' From becomes Trained model and the tables are baked from the flow."""
    pytest.importorskip("torch")
    from blender_addon.artist import scan, worker
    mat = one_learned_object(tmp_path, "trained")
    with bpy.context.temp_override(material=mat):
        assert bpy.ops.flowbsdf.train_bake(only_active=True) == {"FINISHED"}
    assert (tmp_path / "models" / "trained.flow.npz").is_file() and mat.flowbsdf.tables_from == "MODEL"
    job = worker.Job(sys.executable, ["status", str(tmp_path / "manifest.toml"), "--out", str(tmp_path)])
    info = scan.parse_status(job.run(echo=False))["trained"]
    assert info["tables"] == "current" and info["tables_source"] == "flow", info
    assert scan.source_text(info) == "tables from its trained model"


def test_scan_measured_file_material(addon, tmp_path, rgl):
    path = rgl("paper_white_rgb")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.flowbsdf.out_dir = str(tmp_path)
    mat = learned("paper", "MATTE")
    mat.flowbsdf.source_kind, mat.flowbsdf.filepath = "FILE", str(path)
    mesh_object("o", mat)
    assert bpy.ops.flowbsdf.scan() == {"FINISHED"}
    item = scene.flowbsdf.scan_items[0]
    assert (item.learned, item.state) == ("paper", "missing") and item.needs.startswith("theta_i only")
    assert item.detail == "no trained model"
    entry = load_manifest(tmp_path / "manifest.toml").materials[0]
    assert entry.source == str(path) and entry.open().isotropic


def test_a_measured_file_carries_only_when_the_artist_asks(addon, tmp_path):
    """A material from a file bakes without the carried blend (the manifest's `carry`, the panel's
    "Carried": off by default), with it when ticked; an analytic material's entry does not mention it."""
    from blender_addon.artist.props import manifest_entry
    mat = one_learned_object(tmp_path, "measured")
    mat.flowbsdf.source_kind = "FILE"
    mat.flowbsdf.filepath = str(tmp_path / "x.bsdf")
    assert not mat.flowbsdf.carried and manifest_entry(mat)["bake"]["carry"] is False
    mat.flowbsdf.carried = True
    assert manifest_entry(mat)["bake"]["carry"] is True
    mat.flowbsdf.source_kind = "ANALYTIC"
    assert "carry" not in manifest_entry(mat)["bake"]
