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
WORKER_SCRIPT = HERE / "artist" / "worker_main.py"
ENV_PYTHON = "FLOWBSDF_PYTHON"          # overrides the preference (farms, tests)
_probes = {}


def bake_root():
    """The folder to put on sys.path so that `import bake` finds the add-on's copy, or None
    (then the worker Python must have FlowBSDF installed)."""
    for root in (HERE / "vendor", HERE.parent):
        if (root / "bake" / "__init__.py").is_file():
            return root
    return None


def _stdlib_module(rel):
    """A module of the add-on's `bake` that imports only the standard library, read by its path
    (`rel` below the package, as "io/files.py"): importing the `bake` package needs numpy, which
    Debian's Blender 3.4 lacks. Loaded once (sys.modules, as flowbsdf_<its name>)."""
    import importlib.util
    name = "flowbsdf_" + Path(rel).stem
    if name not in sys.modules:
        root = bake_root()
        package = root / "bake" if root is not None else \
            Path(importlib.util.find_spec("bake").submodule_search_locations[0])
        spec = importlib.util.spec_from_file_location(name, package / rel)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules[name] = module
    return sys.modules[name]


def formats():
    """bake/formats.py: the version numbers numpy, the OSL shader and the add-on share (the node
    names its textures by these numbers without numpy too)."""
    return _stdlib_module("formats.py")


def files():
    """bake/io/files.py: file hashes (a texture's name carries its tables' hash) and atomic writes."""
    return _stdlib_module("io/files.py")


def _import_bake():
    if (HERE / "vendor" / "bake" / "__init__.py").is_file():
        from .vendor import bake
    else:
        import bake
    return bake


def __getattr__(name):
    """`deps.bake`: the add-on's `bake` imported into Blender (numpy + OpenEXR needed, so only
    on first use: the UI, scan and batch never need it in Blender itself)."""
    if name != "bake":
        raise AttributeError(name)
    return _import_bake()


def bake_module(name):
    """A module of the add-on's `bake` (numpy) by its name below the package ("export.world_map"),
    or None where this Blender's Python cannot import it (no numpy: Debian's Blender 3.4). Both
    sides of the add-on use it (render/: the fit, textures, world map; artist/: jobs)."""
    import importlib
    try:
        return importlib.import_module(f"{_import_bake().__name__}.{name}")
    except ImportError:
        return None


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
    """What a Python can do for FlowBSDF: {'ok', 'numpy', 'openexr', 'torch', 'trainer', 'bake',
    'executable', 'version', 'base_prefix', 'error'}; cached per interpreter path."""
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


# What each job needs in its Python (bake/ comes with the add-on; the trainer does not).
NEEDS = {"bake": ("numpy", "openexr"), "train": ("numpy", "openexr", "torch", "trainer")}
INSTALL = {"bake": "a Python 3.11 with numpy and OpenEXR (pip install 'numpy<2' OpenEXR)",
           "train": "a Python 3.11 with torch and FlowBSDF's trainer, which the add-on does not ship: "
                    "the FlowBSDF checkout's .venv/bin/python (made by scripts/venv.sh)"}
WHERE = {"ui": "Set one in Preferences > Add-ons > FlowBSDF > Python", "batch": "Pass one with --python PATH"}


class PythonNotFound(Exception):
    """No usable Python for a job: str(e) is one short line (fits Blender's report popup),
    `details` says which Python was tried, what it needs and where to set one."""

    def __init__(self, short, details):
        super().__init__(short)
        self.details = details


def candidate(configured=""):
    """(python, explicit): FLOWBSDF_PYTHON, else the configured path, else sys.executable."""
    explicit = os.environ.get(ENV_PYTHON) or (configured or "").strip()
    return (explicit, True) if explicit else (sys.executable, False)


def describe(python, explicit, info=None):
    """How messages name a Python. "Blender's Python" only for the interpreter Blender runs:
    Blender may report another as sys.executable (Debian's 3.4: the python3.11 first on PATH,
    e.g. a pyenv shim)."""
    if explicit:
        return f"the FlowBSDF Python {python}"
    info = info or {}
    same = (info.get("base_prefix") in (None, sys.base_prefix)
            and tuple(info.get("version") or sys.version_info[:3]) == tuple(sys.version_info[:3]))
    if same:
        return f"Blender's Python ({python})"
    runs = info.get("executable") or python
    version = ".".join(map(str, info.get("version") or ())) or "?"
    return f"the Python Blender finds on PATH ({python}, which runs Python {version} at {runs})"


def missing(info, job):
    """What `info` (a probe) lacks for a job ("bake" or "train")."""
    names = {"openexr": "OpenEXR", "trainer": "FlowBSDF's trainer"}
    lacks = [names.get(m, m) for m in NEEDS[job] if not info.get(m)]
    if info.get("bake") is None:
        lacks.append("FlowBSDF's bake package")
    return lacks


def choose_python(configured="", need_train=False, extra_paths=(), where="ui"):
    """The Python for a worker job: FLOWBSDF_PYTHON, else the preference, else the Python
    Blender reports (sys.executable). PythonNotFound (short line + details) when it cannot do
    the job; `where` names the place to set one ("ui" or "batch")."""
    python, explicit = candidate(configured)
    job = "train" if need_train else "bake"
    fix = f"{WHERE[where]}, or set the {ENV_PYTHON} environment variable."
    if explicit and not Path(python).exists():
        raise PythonNotFound(f"the FlowBSDF Python does not exist: {python}",
                             f"To {job}, FlowBSDF needs {INSTALL[job]}. {fix}")
    info = probe(python, extra_paths)
    name = describe(python, explicit, info)
    if not info["ok"]:
        raise PythonNotFound(f"{name} does not run the FlowBSDF worker",
                             f"{info['error']}. To {job}, FlowBSDF needs {INSTALL[job]}. {fix}")
    lacks = missing(info, job)
    if lacks:
        short = name if len(name) < 60 else ("the FlowBSDF Python" if explicit else "the default Python")
        raise PythonNotFound(f"cannot {job}: {short} lacks {', '.join(lacks)}",
                             f"{name[0].upper() + name[1:]} lacks {', '.join(lacks)}. To {job}, FlowBSDF "
                             f"needs {INSTALL[job]}. {fix}")
    return python


def summary(configured="", extra_paths=()):
    """The truth about the Python jobs use, for the preferences: [(text, icon)]."""
    python, explicit = candidate(configured)
    lines = []
    if os.environ.get(ENV_PYTHON):
        lines.append((f"{ENV_PYTHON} overrides this setting: {python}", "INFO"))
    elif not explicit:
        lines.append(("Empty: jobs use the Python Blender reports", "INFO"))
    if explicit and not Path(python).exists():
        return lines + [(f"{python} does not exist: nothing bakes or trains", "ERROR")]
    info = probe(python, extra_paths)
    name = describe(python, explicit, info)
    if not info["ok"]:
        return lines + [(f"{name} does not run the FlowBSDF worker: nothing bakes or trains", "ERROR")]
    if not missing(info, "train"):
        return lines + [(f"{name} has torch and the trainer: Train + Bake trains there; Bake never trains",
                         "CHECKMARK")]
    if not missing(info, "bake"):
        return lines + [(f"{name} bakes (Bake) but cannot train: it lacks {', '.join(missing(info, 'train'))}. "
                         "Train + Bake needs " + INSTALL["train"], "INFO")]
    return lines + [(f"{name} cannot bake: it lacks {', '.join(missing(info, 'bake'))}. Bake needs "
                     + INSTALL["bake"], "ERROR")]
