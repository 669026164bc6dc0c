"""The panel in the real Blender UI (Debian's Blender 3.4, legacy add-on form) under Xvfb.

tests/blender_ui_script.py drives it: the Shader Editor's sidebar (FlowBSDF tab) and the
Material tab at Blender's default sizes (1920x1080 window, UI scale 1); Bake of an unsaved
file; save; Bake from the panel (modal, as a click runs it) of a measured material (Draft),
watched while it runs; the result. Screenshots (unsaved, before, baking, after .png) stay in
the test's temporary folder (printed). Skips, saying why, where there is no `blender` or no
`xvfb-run` (apt-get install blender xvfb).
"""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import rgl_dir
from test_blender_batch import BLENDER, _stage_addon

HERE = Path(__file__).resolve().parent
XVFB = shutil.which("xvfb-run")

pytestmark = [
    pytest.mark.skipif(BLENDER is None, reason="no `blender` on PATH (apt-get install blender)"),
    pytest.mark.skipif(XVFB is None, reason="no `xvfb-run` for a headless display (apt-get install xvfb)"),
]


@pytest.fixture(scope="module")
def ui_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ui")
    user = tmp / "scripts"
    _stage_addon(user)
    out = tmp / "out"
    out.mkdir()
    env = {**os.environ, "BLENDER_USER_SCRIPTS": str(user), "FLOWBSDF_PYTHON": sys.executable}
    env.pop("PYTHONPATH", None)
    material = rgl_dir() / "cm_military_green_rgb.bsdf"      # an analytic plastic when absent
    proc = subprocess.run([XVFB, "-a", "-s", "-screen 0 1920x1080x24", BLENDER, "--factory-startup",
                           "--enable-event-simulate", "--python", str(HERE / "blender_ui_script.py"), "--",
                           str(out), str(material)], capture_output=True, text=True, env=env, cwd=tmp, timeout=900)
    log = proc.stdout + proc.stderr
    assert "UI SCRIPT DONE" in log, log[-3000:]
    result = json.loads((out / "result.json").read_text())
    assert not result["errors"], result["errors"]
    print(f"screenshots: {out}/{{unsaved,before,baking,after,error,library_dialog}}.png")
    return out, result


def test_every_text_fits_the_default_sidebar_and_material_tab(ui_run):
    """No label, button or value is cut at the default widths, before, during and after a bake
    (each text measured in the UI font against the width the layout gives it)."""
    out, result = ui_run
    assert set(result["stages"]) == {"unsaved", "before", "baking", "after", "error"}
    cut = []
    for stage, panels in result["stages"].items():
        for panel, data in panels.items():
            assert data["items"], (stage, panel)
            cut += [(stage, panel, i["kind"], i["text"], i["need"], round(i["width"])) for i in data["items"]
                    if not i["fits"]]
    assert not cut, cut
    sidebar = result["stages"]["before"]["FLOWBSDF_PT_node_editor"]["region_width"]
    assert sidebar < 260, sidebar               # Blender's default sidebar width, not a widened one
    texts = {i["text"] for i in result["stages"]["after"]["FLOWBSDF_PT_node_editor"]["items"]}
    assert {"Bake", "Scan Scene", "Bake Scene"} <= texts
    assert not {"Train + Bake", "Load Model"} & texts, texts      # training's: only with From: Trained model
    # What renders (3.4 starts in EEVEE: the fit) and the step to the exact material, as a button.
    assert any(t.startswith("Fit, ~") for t in texts) and "Render with Cycles" in texts, texts
    for stage in result["stages"]:
        assert (out / f"{stage}.png").stat().st_size > 10_000


def test_material_tab_panel_starts_open(ui_run):
    assert "DEFAULT_CLOSED" not in ui_run[1]["material_panel_options"]


def test_unsaved_file_is_asked_to_save_first(ui_run):
    _, result = ui_run
    assert "save the .blend first" in result["unsaved_bake"], result["unsaved_bake"]
    assert result["unsaved_message"].startswith("save the .blend first: FlowBSDF writes the tables beside it")


def test_bake_from_the_panel_shows_progress_then_a_preview(ui_run):
    """The modal Bake of one material: the bar moves within it, the words are an artist's; at the
    end the node is bound, the preview shows as an icon."""
    out, result = ui_run
    assert result["bake"] == ["RUNNING_MODAL"]
    messages = result["bake_messages"]
    inside = {p for _, p, _ in messages if 0.0 < p < 100.0}
    assert len(inside) >= 2, messages
    assert any(m.startswith("Baking MilitaryGreen: ") for _, _, m in messages), messages
    assert not any(m.startswith("[") for _, _, m in messages), messages      # no log lines as the message
    assert result["after_message"] == "FlowBSDF: baked 1 table(s), 1 material(s) bound"
    assert result["icons"] and all(i > 0 for i in result["icons"])
    assert Path(result["preview_file"]) == out / "project" / "flowbsdf" / "tables" / "MilitaryGreen.preview.png"


def test_make_asset_library_from_the_panel_bakes_then_writes_the_library(ui_run):
    """Make Asset Library from its button: the dialog opens and waits (nothing runs before OK),
    Return confirms it; then modal, the bake's words and bar in the worker, then library.blend from
    a background Blender; the open file stays open. (Its folder holds the shared measured file: a
    checkout without ../shared has nothing for the library to bake.)"""
    if not (rgl_dir() / "cm_military_green_rgb.bsdf").is_file():
        pytest.skip("the asset library needs a measured file (../shared/data/rgl)")
    out, result = ui_run
    assert result["library_dialog"] == ["RUNNING_MODAL"] and result["library_before_ok"] is False, result
    assert (out / "library_dialog.png").is_file()
    assert result["library"] == ["RUNNING_MODAL"]
    seen = result["library_messages"]
    assert {label for label, _, _ in seen} == {"Asset Library: Bake", "Asset Library: library.blend"}, seen
    # The bake's words and bar, where the UI's 0.25 s sampler looked during the bake at all: on a
    # busy machine (a full suite beside it) Blender's ticks can miss a Draft bake of seconds
    # entirely (seen twice in session 42: one sample, "starting"); the same modal path's words and
    # bar are checked by test_bake_from_the_panel_shows_progress_then_a_preview in every run.
    baking = [(p, m) for label, p, m in seen if label == "Asset Library: Bake"]
    if len(baking) >= 3:
        assert any(m.startswith("Baking ") and 0 < p < 100 for p, m in baking), seen
    assert result["library_message"].startswith(f"FlowBSDF: asset library {out / 'library' / 'library.blend'}, "
                                                "1 material(s)"), result["library_message"]
    assert (out / "library" / "library.blend").is_file() and (out / "library" / "blender_assets.cats.txt").is_file()


def test_a_bake_error_is_one_short_line_with_the_details_in_the_panel(ui_run):
    """Blender's report popup is one line wide: the error is one short line; what to do (which
    Python, what it needs, where to set it) is in the panel, wrapped."""
    _, result = ui_run
    report = result["error_bake"].strip().splitlines()
    assert len(report) == 1 and len(report[0]) <= 140, report
    assert "the FlowBSDF Python does not exist" in report[0] and "details in the FlowBSDF panel" in report[0]
    details = result["error_message"]
    assert details.startswith("the FlowBSDF Python does not exist: /nonexistent/bin/python3.11\n")
    assert "numpy and OpenEXR" in details and "Preferences > Add-ons > FlowBSDF > Python" in details
    assert "Blender's own" not in details and "checkout" not in details
