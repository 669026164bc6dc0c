"""One meaning of --out for every flowbsdf command working on a manifest: the output folder, with
models/, tables/ and report/ inside. `flowbsdf train --out X` then `flowbsdf bake --out X` finds
the model; a model that an older train left in X itself (its --out was the models folder) is
still found, moved into X/models with its checkpoints."""
import argparse
import textwrap

import pytest

from bake.core.flow import save_model
from bake.core.table_files import open_tables
from bake.plumbing.cli import build_parser, main
from bake.plumbing.job import OUT_HELP, train_models_dir
from bake.io.paths import model_path, table_path
from conftest import TINY_TRAIN_TOML
from test_bad_inputs import tiny_model_arrays, tiny_model_meta
from trainer.cli import main as train_main

# Tables from the trained model (source "flow"): a bake without it is an error, not a fallback.
MANIFEST = """
[[material]]
name = "rough"
source = { kind = "analytic", model = "ggx", alpha = 0.4 }
bake = { source = "flow", resolution = 8, tol = 5.0, grid = 32, samples = 256, first_bins = 2, ideal_resolution = 32 }
[material.train]
preset = "fast"
"""


@pytest.fixture(autouse=True)
def tables_only(monkeypatch):
    """The bake without the Blender node's files beside the tables (their closure fit takes seconds)."""
    import bake.export.derived
    monkeypatch.setattr(bake.export.derived, "bake_derived", lambda *a, **k: None)


def write_manifest(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(textwrap.dedent(MANIFEST) + TINY_TRAIN_TOML)
    return path


def test_train_then_bake_with_the_same_out(tmp_path):
    pytest.importorskip("torch")
    manifest, out = write_manifest(tmp_path), tmp_path / "out"
    # `flowbsdf train` runs this in a subprocess, with the same arguments (one parser)
    assert train_main(["train", str(manifest), "--out", str(out), "--no-progress"]) == 0
    assert (out / "models" / "rough.flow.npz").is_file() and (out / "models" / "rough.train").is_dir()
    assert sorted(p.name for p in out.iterdir()) == ["models"]
    assert main(["bake", str(manifest), "--out", str(out)]) == 0
    assert open_tables(table_path(out, "rough")).meta["source"] == "flow"


def test_a_model_an_older_train_left_in_out_is_found(tmp_path, capsys):
    manifest, out = write_manifest(tmp_path), tmp_path / "out"
    old = out / "rough.flow.npz"                # `flowbsdf train --out out` before --out meant the output folder
    (out / "rough.train" / "ckpt").mkdir(parents=True)
    save_model(old, tiny_model_meta(), tiny_model_arrays(seed=0))
    assert main(["bake", str(manifest), "--out", str(out)]) == 0
    new = out / "models" / "rough.flow.npz"
    assert f"[models] moved {old} to {new} (and its checkpoints)" in capsys.readouterr().err
    assert new.is_file() and not old.exists() and (out / "models" / "rough.train" / "ckpt").is_dir()
    assert open_tables(table_path(out, "rough")).meta["source"] == "flow"
    assert model_path(out, "rough") == new      # once moved, found where it belongs, silently
    assert capsys.readouterr().err == ""


def test_a_missing_model_says_which_train_writes_it(tmp_path, capsys):
    manifest, out = write_manifest(tmp_path), tmp_path / "out"
    assert main(["bake", str(manifest), "--out", str(out)]) == 2
    assert f"`flowbsdf train {manifest} --material rough --out {out}` writes it" in capsys.readouterr().err


def out_option(parser, *command):
    for name in command:
        parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
    return next(a for a in parser._actions if "--out" in a.option_strings)


@pytest.mark.parametrize("command", [("train",), ("bake",), ("report",), ("run",), ("yardsticks",), ("farm", "task")])
def test_every_command_says_the_same_about_out(command):
    option = out_option(build_parser(), *command)
    assert option.default == "out" and option.help == OUT_HELP == "output folder: models/, tables/, report/ inside " \
                                                                   "(default out)"


def test_an_out_named_models_is_the_models_folder(tmp_path):
    """What the Blender add-on and older scripts pass (--out OUT/models) still lands in OUT/models."""
    lines = []
    assert train_models_dir(tmp_path / "out", lines.append) == tmp_path / "out" / "models" and not lines
    assert train_models_dir(tmp_path / "out" / "models", lines.append) == tmp_path / "out" / "models"
    assert lines == [f"[train] --out {tmp_path / 'out' / 'models'} is a models folder: the models go there "
                     f"(--out is the output folder, with models/ inside: --out {tmp_path / 'out'} does the same)"]
