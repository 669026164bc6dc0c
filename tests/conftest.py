import fcntl
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from bake.materials.rgl import SHARED_FILES as RGL_FILES, shared_dir as rgl_dir  # noqa: F401 (tests import them from here)

ROOT = Path(__file__).resolve().parents[1]
# A training run of seconds: the trainer's test settings, as lines of a manifest's train table.
TINY_TRAIN_TOML = """theta_i = [10, 45, 70]
resolution = 32
pool = 20000
batch = 256
base_steps = 20
flow_steps = 40
flow_eval_every = 20
reflow_pairs = 1024
reflow_steps = 20
reflow_eval_every = 10
holdout = 128
warmup = 5
teacher = { vel_width = 16, vel_depth = 1 }
student = { vel_width = 8, vel_depth = 2 }
"""


def rgl_path(name):
    path = rgl_dir() / f"{name}.bsdf"
    if not path.is_file():
        pytest.skip(f"shared RGL data not found at {path} (set FLOWBSDF_RGL_DIR)")
    return path


@pytest.fixture
def rgl():
    """rgl(name) -> path of a shared RGL file, or skip the test with the reason."""
    return rgl_path


@pytest.fixture(scope="module")
def shared_fits(tmp_path_factory):
    """Closure fits shared between the test modules that use this fixture (pytestmark): the fit
    of a table file (its content hash and name, the fit's version) is made once per test run,
    by the first module to need it, with this run's closure_fit (a fit that breaks still fails
    there, and in every module after it: nothing is stored, they fit again), then written beside
    every other module's copy of those tables. The fit is a function of the tables alone (fixed
    seed); the small test tables are the same bytes in every module (test_cycles, _lights and
    test_svm each fitted plastic, ~10 s CPU a fit). Shared by both xdist workers (the run's
    base temp folder, a lock per fit: one waits while the other fits). Only fits measured
    against the tables (material=None, what the node makes); the modules that test the fit and
    its files themselves (test_closure_fit, the pipeline's) make their own."""
    from bake.export import closure_fit
    base = tmp_path_factory.getbasetemp()
    store = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared_fits"
    store.mkdir(exist_ok=True)
    real = closure_fit.write

    def write(path, tables_path, tables, digest, material=None):
        if material is not None:
            return real(path, tables_path, tables, digest, material=material)
        path, tables_path = Path(path), Path(tables_path)
        entry = store / f"{digest}-{closure_fit.FIT_VERSION}-{tables_path.name}"
        with open(f"{entry}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not entry.is_dir():
                note = real(path, tables_path, tables, digest)
                made = Path(f"{entry}.tmp")
                shutil.rmtree(made, ignore_errors=True)
                made.mkdir()
                match = json.loads(path.read_text()).get("match")
                for f in [path] + ([tables_path.with_name(match)] if match else []):
                    shutil.copyfile(f, made / f.name)
                (made / "note").write_text(note or "")
                made.rename(entry)
                return note
        fit = entry / path.name
        for f in entry.iterdir():               # the match image first, the fit file last (what is_current reads)
            if f not in (fit, entry / "note"):
                shutil.copyfile(f, tables_path.with_name(f.name))
        shutil.copyfile(fit, path.with_name(f".{path.name}.tmp"))
        os.replace(path.with_name(f".{path.name}.tmp"), path)
        return (entry / "note").read_text() + " (this run's fit of the same tables)"

    mp = pytest.MonkeyPatch()
    mp.setattr(closure_fit, "write", write)
    yield
    mp.undo()


def write_npz(path, meta, arrays):
    """A model file as bake.core.flow reads it: the arrays, and `meta` (a dict, or a string as it
    is; None: left out) as the JSON string `meta`."""
    payload = dict(arrays)
    if meta is not None:
        payload["meta"] = np.array(meta if isinstance(meta, str) else json.dumps(meta))
    with open(path, "wb") as fh:
        np.savez(fh, **payload)
    return path


def slow_unless(values, default, unpack=False):
    """Parameters for pytest.mark.parametrize: those not in `default` run only with `-m slow`
    (the default suite keeps one representative of each behaviour and stays short); with
    `unpack`, each value is a tuple of several arguments."""
    return [pytest.param(*(v if unpack else (v,)), marks=() if v in default else pytest.mark.slow)
            for v in values]


# The files whose tests take longest, longest first (summed CPU seconds of each file's tests in
# the default run, session 47, main 412a969, under load; scripts/pytest_cpu.py: cycles_lights 247,
# cycles 211, tables 210, svm 146, addon 104, pipeline 87, farm 83, closure_fit 70, crash_safety 62,
# library 56, aniso_tables 50, tracer_lamps 49, flow 49, blender_batch 45, fit_rings 38, hard_cases
# 36, fit_render 30, carried 24; the rest under 20 each). Two workers take whole files (test.sh:
# --dist loadfile) in the order collected (with --no-loadscope-reorder; xdist's default order,
# most tests first, left test_cycles_lights.py near the end), so the run waited for one worker.
# Longest first, the short files fill the gaps.
LONGEST_FIRST = ("test_cycles_lights.py", "test_cycles.py", "test_tables.py", "test_svm.py", "test_addon.py",
                 "test_pipeline.py", "test_farm.py", "test_closure_fit.py", "test_crash_safety.py",
                 "test_library.py", "test_aniso_tables.py", "test_tracer_lamps.py", "test_flow.py",
                 "test_blender_batch.py", "test_fit_rings.py", "test_hard_cases.py", "test_fit_render.py",
                 "test_carried.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))     # stable: a file's own order kept
