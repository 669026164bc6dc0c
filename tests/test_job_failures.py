"""The main job (`flowbsdf run`, bake/plumbing/job.py) on every kind of material, and never stopped
by one: an anisotropic material goes through bake, report and render (its report once stopped
`./run.sh --all` at "an anisotropic material needs bins over phi_i"), and a material whose stage
fails is recorded (log, page, exit code at the end) while the next material's stages run."""
import json
import textwrap

import pytest

from bake.errors import FlowBSDFError
from bake.plumbing.cli import main
from bake.plumbing.job import Job

ANISOTROPIC = """
[run]
report = { samples = 1024, thetas = [60], speed_samples = 256, speed_repeat = 1 }
render = { size = 8, spp = 2, reference_spp = 4 }

[[material]]
name = "brushed"
source = { kind = "analytic", model = "ggx", alpha_x = 0.3, alpha_y = 0.05, angle = 20 }
bake = { source = "ideal", resolution = 16, grid = 64, samples = 1024, first_bins = 2, tol = 5.0, ideal_resolution = 32, phi_count = 2 }
"""


def test_an_anisotropic_material_goes_through_the_job(tmp_path, capsys):
    manifest = tmp_path / "m.toml"
    manifest.write_text(textwrap.dedent(ANISOTROPIC))
    out = tmp_path / "out"
    assert main(["run", str(manifest), "--out", str(out), "--no-train"]) == 0
    log = capsys.readouterr().out
    assert "[run] 3 stage(s) ran, 0 current (skipped), " in log and "[fail]" not in log
    assert "[report] brushed: tables 8x8: 4 tables built" in log     # 2 theta_i x 2 phi_i, rebuilt at half resolution
    report = json.loads((out / "report" / "brushed" / "job.json").read_text())
    samplers = {r["sampler"] for r in report["rows"]}
    # the tables, and their half-resolution rebuild on the same theta_i x phi_i bins
    assert {"ideal", "ggx", "tables", "tables 8x8"} <= samplers, samplers
    assert (out / "report" / "brushed" / report["pdf_slice"]).is_file()
    assert (out / "render" / "brushed" / "job.json").is_file()
    page = (out / "index.html").read_text(encoding="utf-8")
    assert "report/brushed/speed_error.md" in page and "render/brushed/tables_time.png" in page


TWO = """
[[material]]
name = "first"
source = { kind = "analytic", model = "lambert", albedo = 0.5 }

[[material]]
name = "second"
source = { kind = "analytic", model = "lambert", albedo = 0.7 }
"""


@pytest.mark.parametrize("error", [FlowBSDFError("no tables: the disk is full"), ValueError("a bug")])
def test_a_failing_material_does_not_stop_the_next(tmp_path, capsys, monkeypatch, error):
    """Stages stubbed (the job's bookkeeping only): `first` fails in its bake, so its report does
    not run; `second` runs both; the page says what failed; the exit code is 2, at the end."""
    ran = []

    def stage(kind):
        def work(self, entry, material):
            if entry.name == "first" and kind == "bake":
                raise error
            ran.append((entry.name, kind))
        return work

    for kind in ("bake", "report"):
        monkeypatch.setattr(Job, kind, stage(kind))
        monkeypatch.setattr(Job, f"{kind}_current", lambda self, entry, material: False)
    manifest = tmp_path / "m.toml"
    manifest.write_text(textwrap.dedent(TWO))
    out = tmp_path / "out"
    assert main(["run", str(manifest), "--out", str(out), "--no-train", "--no-render"]) == 2
    assert ran == [("second", "bake"), ("second", "report")]
    captured = capsys.readouterr()
    message = str(error) if isinstance(error, FlowBSDFError) else "ValueError: a bug"
    lines = captured.out.splitlines()
    assert f"[fail] first bake: {message} (its other stages are not run; the job goes on)" in lines
    assert "[report first] not run: its bake failed (0s)" in lines
    assert any(line.startswith("[run] 2 stage(s) ran, 0 current (skipped), 1 failed, 1 not run after a failure, ")
               for line in lines)
    assert ("Traceback" in captured.out) is not isinstance(error, FlowBSDFError)    # a bug shows where it is
    assert captured.err.strip() == f"flowbsdf: error: {manifest}: 1 of 2 material(s) failed, the others are done: " \
                                   f"first (bake: {message})"
    assert f"<b>bake failed</b>: {message}<br>" in (out / "index.html").read_text(encoding="utf-8")
