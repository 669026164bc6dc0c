"""The main job (`flowbsdf run`, bake/plumbing/job.py) on tiny settings: it trains, bakes, reports and
renders, writes one page whose every linked image is there, a rerun skips all of it, and a
changed setting redoes only what depends on it. Also the progress estimates (bake/io/progress.py)
and the demo manifest."""
import re
import textwrap
from html.parser import HTMLParser
from pathlib import Path

import pytest

from bake.plumbing.cli import main
from bake.plumbing.job import Job, selected
from bake.plumbing.manifest import load_manifest
from bake.io.progress import Progress
from conftest import ROOT, TINY_TRAIN_TOML

TINY_TRAIN = "\n[defaults.train]\n" + TINY_TRAIN_TOML
TINY = """
[defaults]
bake = { resolution = 16, tol = 0.5, grid = 96, samples = 2048, first_bins = 3, ideal_resolution = 48 }

[run]
max_materials = 1
report = { samples = 1024, thetas = [0, 60] }
render = { size = 12, spp = 2, reference_spp = 6 }

[[material]]
name = "absent"
source = "nowhere/missing.bsdf"
optional = true

[[material]]
name = "rough"
source = { kind = "analytic", model = "ggx", alpha = 0.4 }

[[material]]
name = "unselected"
source = { kind = "analytic", model = "lambert", albedo = 0.5 }
"""


class Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links = [], []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs["src"])
        elif tag == "a":
            self.links.append(attrs["href"])


def page_links(page):
    parser = Links()
    parser.feed(page.read_text(encoding="utf-8"))
    return parser


def snapshot(out):
    """mtime of every file the job wrote."""
    return {p.relative_to(out): p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}


def run(manifest, out, capsys, *extra):
    assert main(["run", str(manifest), "--out", str(out), *extra]) == 0
    return capsys.readouterr().out


def test_main_job_writes_the_page_and_a_rerun_skips_the_work(tmp_path, capsys):
    manifest = tmp_path / "m.toml"
    manifest.write_text(textwrap.dedent(TINY_TRAIN) + textwrap.dedent(TINY))
    out = tmp_path / "out"
    first = run(manifest, out, capsys)
    # One line per stage, with the job's estimate; the first optional material is absent, so
    # max_materials = 1 picks the second and leaves the third alone.
    assert re.findall(r"^\[(\d)/4 (\w+) rough\] · job: ~\S+ left$", first, re.M) == [
        ("1", "train"), ("2", "bake"), ("3", "report"), ("4", "render")]
    assert "[run] 4 stage(s) ran, 0 current" in first and "unselected" not in first
    page = out / "index.html"
    assert f"[page] {page.resolve()}" in first
    for name in ("models/rough.flow.npz", "tables/rough.exr", "report/rough/job.json", "render/rough/job.json"):
        assert (out / name).is_file(), name

    links = page_links(page)
    # per material: reference, three equal-time renders and their error maps, Pareto plot, pdf slices
    assert len(links.images) == 9, links.images
    assert {"render/rough/tables_time.png", "render/rough/cosine_time_error.png",
            "report/rough/pdf_rough_60.png", "report/rough/pareto_rough.png"} <= set(links.images)
    for src in links.images:
        data = (out / src).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 100, src
    text = page.read_text(encoding="utf-8")
    for href in links.links:        # files beside the page, or a material's section
        assert f"id='{href[1:]}'" in text if href.startswith("#") else (out / href).exists(), href
    assert "unselected" not in text and "Same time for each" in text

    before = snapshot(out)
    second = run(manifest, out, capsys)
    assert "[run] 0 stage(s) ran, 4 current" in second
    assert second.count("current, skipped") == 4
    after = snapshot(out)
    assert {k for k, v in after.items() if v != before.get(k)} == {Path("index.html")}

    # A bake whose Blender files are missing (an export that failed, or an older layout's) is not
    # current: the stage runs again, the tables are kept and the files come back.
    svm_file, = (out / "tables").glob("rough.svm*-*.exr")
    svm_file.unlink()
    again = run(manifest, out, capsys)
    assert "[run] 1 stage(s) ran, 3 current" in again and svm_file.is_file()
    assert snapshot(out)[Path("tables/rough.exr")] == after[Path("tables/rough.exr")]
    after = snapshot(out)

    # Another spp: only the renders are redone, with the reference reused; nothing else changes.
    manifest.write_text(manifest.read_text().replace("spp = 2,", "spp = 3,"))
    third = run(manifest, out, capsys)
    assert "[run] 1 stage(s) ran, 3 current" in third and "reference: current, reused" in third
    changed = {k for k, v in snapshot(out).items() if v != after.get(k)}
    assert changed and all(k.parts[0] == "render" or k == Path("index.html") for k in changed), changed
    assert Path("render/rough/reference.npz") not in changed


def test_progress_estimates():
    """Estimates: priors until a stage of the kind ran, then its actual time; a slow machine
    scales the priors of the kinds not run yet; current stages cost nothing."""
    now = [0.0]
    lines = []
    p = Progress([("a", True), ("b", True), ("a", True), ("b", False)], {"a": 10.0, "b": 20.0},
                 out=lines.append, heartbeat=0, clock=lambda: now[0])
    assert p.job_left(None, 0.0) == 40.0
    p.stage("a", "x")
    assert lines[-1] == "[1/4 a x] · job: ~40s left"
    now[0] = 30.0                         # three times the prior
    p.update(0.5, "half", every=0)        # the stage's own rate: 30 s more
    assert "[a x] 50% half · 30s so far, ~30s left" in lines[-1]
    now[0] = 60.0
    p.end(note="done")
    assert p.estimate("a") == 60.0 and p.estimate("b") == 120.0     # 6x the prior so far
    p.stage("b", "y")
    assert lines[-1].endswith("job: ~3m00s left")                 # b 120 s + a 60 s, the last b is current
    p.close()


def test_demo_manifest_picks_three_materials():
    manifest = load_manifest(ROOT / "demo.toml")
    names = [e.name for e in selected(manifest, log=lambda *_: None)]
    assert len(names) == 3 and names[0] == "copper_glossy"
    everything = [e.name for e in manifest.materials]
    missing = [e.name for e in manifest.materials if e.missing()]
    assert names == [n for n in everything if n not in missing][:3]
    Job(manifest, "unused")         # its [run] settings are valid


def test_source_paths_expand_environment_variables(tmp_path, monkeypatch):
    path = tmp_path / "m.toml"
    path.write_text('[[material]]\nname = "a"\nsource = "${FLOWBSDF_TEST_DIR:-default/dir}/a.bsdf"\n')
    monkeypatch.delenv("FLOWBSDF_TEST_DIR", raising=False)
    assert load_manifest(path).materials[0].source_path() == tmp_path / "default/dir/a.bsdf"
    monkeypatch.setenv("FLOWBSDF_TEST_DIR", "/data")
    assert load_manifest(path).materials[0].source_path() == Path("/data/a.bsdf")


@pytest.mark.parametrize("text,match", [
    ("[run]\nmax_materials = 0\n", "max_materials must be a positive integer"),
    ("[run]\nrender = { sze = 3 }\n", r"\[run.render\]: unknown key\(s\) sze"),
    ("[run]\nmaterials = 3\n", "unknown key 'materials'"),
    ("[run]\nrender = { size = 9.5 }\n", r"size = 9.5 should be like 96"),
    ("[run]\nrender = { samplers = ['tables', 'mis'] }\n", "samplers are tables"),
])
def test_bad_run_settings(tmp_path, text, match):
    from bake.errors import FlowBSDFError
    path = tmp_path / "m.toml"
    path.write_text(text + '[[material]]\nname = "a"\nsource = { kind = "analytic", model = "lambert" }\n')
    with pytest.raises(FlowBSDFError, match=match):
        Job(load_manifest(path), tmp_path)
