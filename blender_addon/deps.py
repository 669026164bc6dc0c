"""Where the add-on finds FlowBSDF's numpy runtime (`bake`) and the Python that runs it.

Nothing here imports numpy or `bake`: inside Blender the add-on only reads the scene and
starts worker subprocesses (Debian's Blender 3.4 has no numpy at all; Blender 4.2+ has
numpy but no OpenEXR unless the extension's bundled wheel is installed).

The extension zip vendors `bake` as `vendor/bake` (scripts/build_extension.py); in a
development checkout the repository's `bake` package sits beside this folder.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
WORKER_SCRIPT = HERE / "worker_main.py"
ENV_PYTHON = "FLOWBSDF_PYTHON"          # overrides the preference (farms, tests)
_probes = {}


def bake_root():
    """The folder to put on sys.path so that `import bake` finds the add-on's copy, or None
    (then the worker Python must have FlowBSDF installed)."""
    for root in (HERE / "vendor", HERE.parent):
        if (root / "bake" / "__init__.py").is_file():
            return root
    return None


def __getattr__(name):
    """`deps.bake`: the add-on's `bake` imported into Blender (numpy + OpenEXR needed, so only
    on first use: the UI, scan and batch never need it in Blender itself)."""
    if name != "bake":
        raise AttributeError(name)
    if (HERE / "vendor" / "bake" / "__init__.py").is_file():
        from .vendor import bake
    else:
        import bake
    return bake


def worker_env(python, extra_paths=()):
    """Environment of a worker subprocess: extra_paths and the add-on's `bake` first on
    PYTHONPATH; when the worker is Blender's own Python, also Blender's module folders (where
    the extension's bundled wheels are installed)."""
    env = dict(os.environ)
    paths = [str(p) for p in extra_paths if p]
    root = bake_root()
    if root is not None:
        paths.append(str(root))
    if str(python) == sys.executable:
        paths += [p for p in sys.path if p and os.path.isdir(p) and "site-packages" in p]
    if env.get("PYTHONPATH"):
        paths.append(env["PYTHONPATH"])
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    env.setdefault("PYTHONUNBUFFERED", "1")
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return env


def probe(python, extra_paths=()):
    """What a Python can do for FlowBSDF: {'ok', 'numpy', 'openexr', 'torch', 'trainer',
    'bake', 'error'}; cached per interpreter path."""
    key = (str(python), tuple(extra_paths))
    if key in _probes:
        return _probes[key]
    result = {"ok": False, "numpy": False, "openexr": False, "torch": False, "trainer": False,
              "bake": None, "error": None}
    try:
        proc = subprocess.run([str(python), str(WORKER_SCRIPT), "probe"], env=worker_env(python, extra_paths),
                              capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError) as e:
        result["error"] = f"cannot run {python}: {e}"
        _probes[key] = result
        return result
    for line in proc.stdout.splitlines():
        if line.startswith("[probe] "):
            result.update(json.loads(line[len("[probe] "):]))
            result["ok"] = True
    if not result["ok"]:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        result["error"] = f"{python} did not run the FlowBSDF worker ({tail})"
    _probes[key] = result
    return result


def clear_probes():
    """Forget what the probed Pythons could do (after the user changed one)."""
    _probes.clear()


class PythonNotFound(Exception):
    """No usable Python for a job; the message says what to set."""


HINT = ("set one in Preferences > Add-ons > FlowBSDF > Python (a Python 3.11 with FlowBSDF and its "
        "trainer: `pip install '<FlowBSDF checkout>[train]'`), or the FLOWBSDF_PYTHON environment variable")


def choose_python(configured="", need_train=False, extra_paths=()):
    """The Python for a worker job: FLOWBSDF_PYTHON, else the preference, else Blender's own
    (for baking only, when it has numpy and OpenEXR). Raises PythonNotFound saying why."""
    explicit = os.environ.get(ENV_PYTHON) or (configured or "").strip()
    candidates = [explicit] if explicit else [sys.executable]
    for python in candidates:
        if explicit and not Path(python).exists():
            raise PythonNotFound(f"the FlowBSDF Python {python} does not exist; {HINT}")
        info = probe(python, extra_paths)
        if not info["ok"]:
            raise PythonNotFound(f"{info['error']}; {HINT}")
        missing = [m for m in ("numpy", "openexr") if not info[m]]
        if info["bake"] is None:
            missing.append("bake (FlowBSDF)")
        if need_train:
            missing += [m for m in ("torch", "trainer") if not info[m]]
        if missing:
            what = "train" if need_train else "bake"
            which = "the configured Python" if explicit else "Blender's own Python"
            raise PythonNotFound(f"to {what}, {which} ({python}) lacks {', '.join(missing)}; "
                                 + ("" if explicit or not need_train else "training never runs in Blender: ")
                                 + HINT)
        return python
    raise PythonNotFound(f"no Python found; {HINT}")
