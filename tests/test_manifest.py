import re
import textwrap

import pytest

from bake.plumbing.cli import main
from bake.errors import FlowBSDFError
from bake.plumbing.manifest import load_manifest
from conftest import ROOT


def write(tmp_path, text, name="m.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_default_manifest_loads_and_opens():
    manifest = load_manifest(ROOT / "manifest.toml")
    names = [m.name for m in manifest.materials]
    assert "matte_white" in names and "chm_mint" in names
    for entry in manifest.select(log=lambda *_: None):
        assert entry.open().eval([0, 0, 1.0], [[0.6, 0, 0.8]]).shape == (1, 3)


def test_defaults_and_overrides(tmp_path):
    path = write(tmp_path, """
        [defaults]
        domain = "spherical"
        train = { preset = "fast", steps = 4 }
        [[material]]
        name = "a"
        source = { kind = "analytic", model = "lambert", albedo = 0.5 }
        train = { steps = 8 }
        [[material]]
        name = "b"
        source = { kind = "analytic", model = "lambert", albedo = 0.5 }
        domain = "disk"
    """)
    a, b = load_manifest(path).materials
    assert a.domain == "spherical" and a.train == {"preset": "fast", "steps": 8}
    assert b.domain == "disk" and b.train == {"preset": "fast", "steps": 4}


BAD = {
    "unknown key": ("""
        [[material]]
        name = "a"
        source = "x.bsdf"
        colour = 1
    """, "unknown key 'colour'"),
    "bad domain": ("""
        [[material]]
        name = "a"
        source = "x.bsdf"
        domain = "cube"
    """, "domain must be one of"),
    "duplicate": ("""
        [[material]]
        name = "a"
        source = "x.bsdf"
        [[material]]
        name = "a"
        source = "y.bsdf"
    """, "used twice"),
    "no source": ("""
        [[material]]
        name = "a"
    """, "needs a 'source'"),
    "bad name": ("""
        [[material]]
        name = "a b"
        source = "x.bsdf"
    """, "needs a 'name'"),
    "syntax": ("[[material]\nname = 1\n", "not valid TOML"),
    "empty": ("", "no [[material]] entries"),
    "top level": ("""
        material_list = 1
    """, "unknown key 'material_list'"),
    "optional type": ("""
        [[material]]
        name = "a"
        source = "x.bsdf"
        optional = "yes"
    """, "'optional' must be true or false"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_manifests_name_the_file_and_problem(tmp_path, case):
    text, message = BAD[case]
    path = write(tmp_path, text)
    with pytest.raises(FlowBSDFError, match=re.escape(message)) as err:
        load_manifest(path)
    assert str(path) in str(err.value)


def test_missing_material_file(tmp_path):
    path = write(tmp_path, """
        [[material]]
        name = "gone"
        source = "nowhere.bsdf"
        [[material]]
        name = "maybe"
        source = "nowhere.bsdf"
        optional = true
    """)
    manifest = load_manifest(path)
    notes = []
    entries = manifest.select(log=notes.append)
    assert [e.name for e in entries] == ["gone"] and "maybe" in notes[0]
    with pytest.raises(FlowBSDFError, match="material file not found") as err:
        entries[0].open()
    assert "nowhere.bsdf" in str(err.value)
    with pytest.raises(FlowBSDFError, match="no material named 'x'"):
        manifest.select("x")


def test_cli_reports_errors_without_traceback(tmp_path, capsys):
    path = write(tmp_path, "[[material]]\nname = 'a'\nsource = 'x.bsdf'\nfoo = 1\n")
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("flowbsdf: error: ") and str(path) in err and "Traceback" not in err


def test_cli_yardsticks_writes_tables(tmp_path, capsys):
    path = write(tmp_path, """
        [[material]]
        name = "rough"
        source = { kind = "analytic", model = "ggx", alpha = 0.3 }
    """)
    assert main(["yardsticks", str(path), "--samples", "4096", "--thetas", "0,60",
                 "--out", str(tmp_path / "out")]) == 0
    table = (tmp_path / "out" / "yardsticks.md").read_text()
    assert "| rough | ideal |" in table and "| rough | cosine |" in table
    csv = (tmp_path / "out" / "yardsticks.csv").read_text().splitlines()
    assert csv[0].startswith("material,sampler,theta_i,rv") and len(csv) == 1 + 2 * 3
