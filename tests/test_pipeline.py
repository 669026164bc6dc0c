"""flowbsdf bake: only what changed is rebuilt, files are atomic, stale tables are never used."""
import textwrap

import numpy as np
import pytest

from bake.plumbing.cli import main
from bake.errors import FlowBSDFError
from bake.plumbing.manifest import load_manifest
from bake.export.osl_export import LAYOUT
from bake.io.paths import table_path
from bake.plumbing.pipeline import bake_manifest, open_current_tables
from bake.core.table_files import open_tables
from bake.io.files import file_hash

FAST = "bake = { resolution = 16, tol = 0.5, grid = 96, samples = 2048, first_bins = 3, ideal_resolution = 48 }"


def manifest(tmp_path, albedo=0.5, extra="", bake=FAST):
    path = tmp_path / "m.toml"
    path.write_text(textwrap.dedent(f"""
        [[material]]
        name = "matte"
        source = {{ kind = "analytic", model = "lambert", albedo = {albedo} }}
        {bake}
        {extra}
    """))
    return load_manifest(path)


def test_bake_skips_current_and_rebuilds_changed(tmp_path, monkeypatch):
    out = tmp_path / "out"
    log = []
    m = manifest(tmp_path)
    assert bake_manifest(m, out, log=log.append) == [table_path(out, "matte")]
    first = table_path(out, "matte").stat().st_mtime_ns
    assert bake_manifest(m, out, log=log.append) == []
    assert any("up to date" in line for line in log)
    assert table_path(out, "matte").stat().st_mtime_ns == first
    entry = m.materials[0]
    assert open_current_tables(entry, out, m.path) is not None

    changed = manifest(tmp_path, albedo=0.6)                 # the material changed
    assert open_current_tables(changed.materials[0], out, changed.path) is None, "stale tables used"
    assert bake_manifest(changed, out, log=log.append) == [table_path(out, "matte")]
    assert f"[bake] matte: {table_path(out, 'matte')} is out of date (the material changed): baking it again" in log
    assert open_current_tables(changed.materials[0], out, changed.path) is not None

    resettled = manifest(tmp_path, albedo=0.6, bake=FAST.replace("tol = 0.5", "tol = 0.4"))
    assert open_current_tables(resettled.materials[0], out, resettled.path) is None
    assert bake_manifest(resettled, out, log=log.append) == [table_path(out, "matte")]
    assert any("out of date (the bake settings changed)" in line for line in log)
    assert not list((out / "tables").glob(".*")), "temporary files left behind"
    # Tables of an older table builder (an update of FlowBSDF): baked again, saying why.
    from bake.plumbing import pipeline
    builder = pipeline.BUILDER_VERSION
    monkeypatch.setattr(pipeline, "BUILDER_VERSION", builder + 1)
    assert bake_manifest(resettled, out, log=log.append) == [table_path(out, "matte")]
    assert any(f"(the table builder {builder} -> {builder + 1} changed)" in line for line in log), log


def test_a_bake_is_reproducible(tmp_path):
    """Baking the same material again (forced) writes the same bytes: the file's hash names its
    OSL and SVM textures, which then stay current (a bake's time in the file made every re-bake
    a new file, new textures and rebuilt node graphs)."""
    out = tmp_path / "out"
    m = load_manifest_text(tmp_path, """
        [[material]]
        name = "gold"
        source = { kind = "analytic", model = "ggx", alpha = 0.25, f0 = [0.9, 0.6, 0.3] }
        """ + FAST)
    path = table_path(out, "gold")
    bake_manifest(m, out, log=lambda *_: None)
    first, textures = path.read_bytes(), sorted(p.name for p in path.parent.glob("gold.*-*.exr"))
    assert bake_manifest(m, out, force=True, log=lambda *_: None) == [path]
    assert path.read_bytes() == first
    assert sorted(p.name for p in path.parent.glob("gold.*-*.exr")) == textures and len(textures) == 2


def test_auto_tables_ignore_models_and_flow_tables_follow_theirs(tmp_path):
    """source "auto" builds the tables from the ideal tabulation whether or not a model exists
    (a model appearing leaves them current); source "flow" builds them from the model, goes
    stale when the model is replaced, and without a model is an error that says what to do."""
    from bake.core.flow import save_model
    from test_bad_inputs import tiny_model_arrays, tiny_model_meta
    out, quiet = tmp_path / "out", (lambda *_: None)
    auto = manifest(tmp_path)
    bake_manifest(auto, out, log=quiet)
    model = out / "models" / "matte.flow.npz"
    save_model(model, tiny_model_meta(), tiny_model_arrays(seed=0))
    assert open_current_tables(auto.materials[0], out, auto.path) is not None
    assert bake_manifest(auto, out, log=quiet) == []
    assert open_tables(table_path(out, "matte")).meta["source"] == "ideal"

    flow = manifest(tmp_path, bake=FAST.replace("}", ', source = "flow" }'))
    assert open_current_tables(flow.materials[0], out, flow.path) is None
    assert bake_manifest(flow, out, log=quiet) == [table_path(out, "matte")]
    assert open_tables(table_path(out, "matte")).meta["source"] == "flow"
    assert open_current_tables(flow.materials[0], out, flow.path) is not None
    save_model(model, tiny_model_meta(), tiny_model_arrays(seed=1))
    assert open_current_tables(flow.materials[0], out, flow.path) is None, "tables of a replaced model used"
    model.unlink()
    with pytest.raises(FlowBSDFError, match="bake source 'flow' but no model"):
        bake_manifest(flow, out, log=quiet)


def load_manifest_text(tmp_path, text):
    path = tmp_path / "m.toml"
    path.write_text(textwrap.dedent(text))
    return load_manifest(path)


def test_broken_table_file_is_rebuilt(tmp_path):
    out = tmp_path / "out"
    m = manifest(tmp_path)
    bake_manifest(m, out, log=lambda *_: None)
    path = table_path(out, "matte")
    path.write_bytes(path.read_bytes()[:300])
    assert bake_manifest(m, out, log=lambda *_: None) == [path]
    tables = open_current_tables(m.materials[0], out, m.path)
    wo, pdf = tables.sample(np.array([0.0, 0.0, 1.0]), np.random.default_rng(0).random((100, 2)))
    assert np.all(pdf > 0)


def test_one_failure_does_not_stop_the_others(tmp_path, capsys):
    out = tmp_path / "out"
    m = manifest(tmp_path, extra=textwrap.dedent("""
        [[material]]
        name = "gone"
        source = "missing.bsdf"
        [[material]]
        name = "brushed"
        source = { kind = "analytic", model = "ggx", alpha_x = 0.3, alpha_y = 0.05 }
        bake = { resolution = 16, phi_count = 4, first_bins = 3, memory_budget = 20000 }
    """))
    log = []
    with pytest.raises(FlowBSDFError, match="1 material\\(s\\) failed.*gone.*not found"):
        bake_manifest(m, out, log=log.append)
    assert table_path(out, "matte").is_file()
    brushed = open_tables(table_path(out, "brushed"))      # anisotropic: baked over phi_i too
    assert brushed.anisotropic and len(brushed.phi_bins) == 5 and brushed.coords == "halfvector"   # 4 + the closing bin
    assert main(["bake", str(m.path), "--out", str(out)]) == 2
    assert "gone" in capsys.readouterr().err


def test_unknown_bake_setting(tmp_path):
    m = manifest(tmp_path, bake="bake = { resolutoin = 16 }")
    with pytest.raises(FlowBSDFError, match="unknown bake setting.*resolutoin"):
        bake_manifest(m, tmp_path / "out", log=lambda *_: None)


def test_bake_writes_readable_files_and_the_node_products_and_clears_dead_temporaries(tmp_path):
    import os
    import time
    out = tmp_path / "out"
    m = manifest(tmp_path)
    path = table_path(out, "matte")
    path.parent.mkdir(parents=True)
    dead = path.parent / f".{path.name}.abc123.tmp"          # what a bake killed mid-write leaves
    dead.write_bytes(b"half a file")
    old = time.time() - 3600
    os.utime(dead, (old, old))
    bake_manifest(m, out, log=lambda *_: None)
    assert not dead.exists()
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask, oct(path.stat().st_mode)   # not mkstemp's 0600
    names = sorted(p.name for p in path.parent.iterdir())
    assert names[:3] == ["matte.exr", "matte.fit.json", "matte.match.exr"], names
    assert names[3].startswith(f"matte.osl{LAYOUT}-"), names


def test_a_measured_file_bakes_which_intervals_carry(tmp_path):
    """With `carry = true` an isotropic RGL file's bake says per interval whether carrying along
    the file's coordinates samples closer (tables.meta["carried"]), writes the carried blend's
    texture for the OSL node, and the `tables` sampler (the reference tracer's, the report's) is
    then the carried blend; by default (`carry = false`) it bakes the tables alone, removes the
    texture, and the sampler is the fixed cells the SVM graph renders too."""
    from bake.core.carried import CarriedTables
    from bake.export.carry_export import read
    from bake.plumbing.pipeline import open_baked
    from bake.materials.rgl import write_tensor_file
    from test_rgl import synthetic_fields
    write_tensor_file(tmp_path / "s.bsdf", synthetic_fields(n_theta=5))
    out = tmp_path / "out"
    text = '[[material]]\nname = "s"\nsource = "s.bsdf"\n' + FAST.replace("}", ", memory_budget = 40000 }")
    m = load_manifest_text(tmp_path, text.replace("}", ", carry = true }"))
    bake_manifest(m, out, log=lambda line: None)
    path = table_path(out, "s")
    tables = open_tables(path)
    flags = tables.meta["carried"]
    assert len(flags) == len(tables.theta_bins) - 1 >= 2
    (texture,) = (out / "tables").glob("s.carry*-*.exr")
    image, meta = read(texture)
    assert meta["tables_hash"] == file_hash(path)
    np.testing.assert_array_equal(image[0, 2 + 5:2 + 5 + len(flags), 1], np.asarray(flags, np.float32))
    sampler = open_baked("tables", m.materials[0], m.materials[0].open(), out, m.path)
    assert isinstance(sampler, CarriedTables) and list(sampler.carry) == flags
    from bake.plumbing.reports import learned_samplers
    from bake.quality.report import manifest_samplers      # the report compares them as they render
    material = m.materials[0].open()
    flow, tables = learned_samplers(m.materials[0], material, out, m.path, log=lambda line: None)
    report = manifest_samplers(m.materials[0], material, flow, tables, steps=(), log=lambda line: None)
    assert isinstance(report["tables"], CarriedTables) and "plain (equal memory)" in report

    m = load_manifest_text(tmp_path, text)
    bake_manifest(m, out, log=lambda line: None)
    assert "carried" not in open_tables(path).meta and not list((out / "tables").glob("s.carry*"))
    sampler = open_baked("tables", m.materials[0], m.materials[0].open(), out, m.path)
    assert not isinstance(sampler, CarriedTables)
    assert load_manifest_text(tmp_path, text.replace("}", ", carry = false }")).materials[0].bake.get("carry") is False
    with pytest.raises(FlowBSDFError, match="carry = 'yes'"):
        bake_manifest(load_manifest_text(tmp_path, text.replace("}", ", carry = 'yes' }")), out)


def test_tables_baked_before_bake_settings_stay_current(tmp_path):
    """A table file records its bake settings as the manifest gave them, source and carry always
    (pipeline.inputs_of): BakeSettings records the same table the untyped dict did before it (the
    value as written, 1 not 1.0; the defaults not given left out), so tables baked before stay
    current (their inputs hash is the one 2f4871e computed for these two entries: checked beside it)."""
    import json
    from bake.plumbing.pipeline import bake_settings, inputs_of
    path = tmp_path / "m.toml"
    path.write_text('[[material]]\nname = "matte"\nsource = { kind = "analytic", model = "lambert", albedo = 0.5 }\n'
                    'bake = { resolution = 16, tol = 1, ideal_ratio = 2.0, lobe_width = "auto", carry = true }\n'
                    '[[material]]\nname = "plain"\nsource = { kind = "analytic", model = "lambert", albedo = 0.5 }\n')
    matte, plain = load_manifest(path).materials
    recorded = inputs_of(matte.open(), bake_settings(matte, path), None)[0]["settings"]
    assert json.dumps(recorded, sort_keys=True) == ('{"carry": true, "ideal_ratio": 2.0, "lobe_width": "auto", '
                                                    '"resolution": 16, "source": "auto", "tol": 1}')
    assert inputs_of(plain.open(), bake_settings(plain, path), None)[0]["settings"] == {"source": "auto", "carry": False}
