"""Build the FlowBSDF Blender extension zip in one command.

    .venv/bin/python scripts/build_extension.py [--out dist] [--platform linux-x64]... [--no-wheels]

1. stages blender_addon/ (sources, OSL shader, manifest) with the numpy runtime `bake/`
   vendored as `vendor/bake` (Python sources and the optional C source; no compiled
   libraries, no torch: the build fails if a vendored file imports torch or imports
   `bake` absolutely);
2. adds the OpenEXR wheel for each platform (`pip download`, cached in build/wheels/;
   Blender installs it when the extension is enabled: bake/ writes tables with it) and
   lists the wheels and platforms in the staged manifest; --no-wheels leaves them out
   (the add-on then bakes with the Python set in its preferences);
3. runs Blender's own extension tool (the bpy wheel's `blender_ext.py`, what
   `blender --command extension` runs): `build`, then `validate` on the zip.
Prints the zip's path. Exit code 0 on success, 1 with the reason on failure.
"""
import argparse
import importlib.util
import platform
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ADDON = ROOT / "blender_addon"
BAKE = ROOT / "bake"
# Blender platform tag -> pip platform tag of the OpenEXR wheel.
PIP_PLATFORMS = {"linux-x64": "manylinux_2_28_x86_64", "linux-arm64": "manylinux_2_28_aarch64",
                 "windows-x64": "win_amd64", "macos-arm64": "macosx_11_0_arm64",
                 "macos-x64": "macosx_10_15_x86_64"}
SKIP_DIRS = {"__pycache__", "vendor", ".pytest_cache"}
SKIP_SUFFIXES = {".pyc", ".so", ".pyd", ".dylib", ".zip", ".tmp"}
BAD_IMPORT = re.compile(r"^\s*(import torch|from torch|import bake\b|from bake\b)", re.M)


class BuildError(Exception):
    pass


def host_platform():
    machine = platform.machine().lower()
    arch = "arm64" if machine in ("arm64", "aarch64") else "x64"
    system = {"linux": "linux", "darwin": "macos", "win32": "windows"}.get(sys.platform, sys.platform)
    return f"{system}-{arch}"


def blender_ext_tool():
    """Path of Blender's extension tool shipped in the bpy wheel."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        raise BuildError("bpy is not installed in this Python (pip install bpy==5.0.1): it ships "
                         "Blender's extension tool")
    hits = sorted(Path(spec.origin).parent.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not hits:
        raise BuildError(f"Blender's extension tool (bl_pkg/cli/blender_ext.py) not found under "
                         f"{Path(spec.origin).parent}")
    return hits[-1]


def _copy_tree(src, dst):
    for path in sorted(src.rglob("*")):
        rel = path.relative_to(src)
        if any(part in SKIP_DIRS or part.startswith(".") for part in rel.parts):
            continue
        if path.is_dir() or path.suffix in SKIP_SUFFIXES:
            continue
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, dst / rel)


def check_vendored(bake_dir):
    """No torch and no absolute `bake` imports in the vendored runtime."""
    bad = []
    for path in sorted(bake_dir.rglob("*.py")):
        for m in BAD_IMPORT.finditer(path.read_text(encoding="utf-8")):
            line = path.read_text(encoding="utf-8")[:m.start()].count("\n") + 1
            bad.append(f"{path.relative_to(bake_dir.parent)}:{line}: {m.group(1)}")
    if bad:
        raise BuildError("the vendored bake/ must import numpy only, with relative imports:\n  "
                         + "\n  ".join(bad))


def fetch_wheels(platforms, cache):
    """The OpenEXR wheel (the version installed here) for each platform, via pip download."""
    try:
        from importlib.metadata import version
        exr_version = version("OpenEXR")
    except Exception:        # noqa: BLE001
        raise BuildError("OpenEXR is not installed in this Python: cannot pick the wheel version") from None
    wheels = []
    for plat in platforms:
        if plat not in PIP_PLATFORMS:
            raise BuildError(f"unknown platform {plat!r} (known: {', '.join(PIP_PLATFORMS)})")
        target = cache / plat
        found = sorted(target.glob(f"openexr-{exr_version}-cp311-*.whl"))
        if not found:
            cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
                   "--python-version", "3.11", "--platform", PIP_PLATFORMS[plat], f"OpenEXR=={exr_version}",
                   "-d", str(target)]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            found = sorted(target.glob(f"openexr-{exr_version}-cp311-*.whl"))
            if proc.returncode != 0 or not found:
                raise BuildError(f"pip could not download the OpenEXR {exr_version} wheel for {plat} "
                                 f"({(proc.stderr.strip().splitlines() or ['no output'])[-1]}); "
                                 "build with --no-wheels to leave it out")
        wheels.append(found[-1])
    return wheels


def stage(staging, wheels, platforms):
    if staging.exists():
        shutil.rmtree(staging)
    _copy_tree(ADDON, staging)
    vendor = staging / "vendor"
    vendor.mkdir()
    (vendor / "__init__.py").write_text('"""Vendored copy of FlowBSDF\'s numpy runtime (built by '
                                        'scripts/build_extension.py)."""\n')
    _copy_tree(BAKE, vendor / "bake")
    check_vendored(vendor / "bake")
    manifest = (staging / "blender_manifest.toml").read_text(encoding="utf-8")
    if wheels:
        (staging / "wheels").mkdir()
        for w in wheels:
            shutil.copy2(w, staging / "wheels" / w.name)
        extra = ("\n# Added by scripts/build_extension.py\n"
                 f"wheels = [{', '.join(repr('./wheels/' + w.name) for w in wheels)}]\n"
                 f"platforms = [{', '.join(repr(p) for p in platforms)}]\n").replace("'", '"')
        # top-level keys must precede the first [table]
        head, sep, tail = manifest.partition("\n[")
        manifest = head.rstrip("\n") + "\n" + extra + sep + tail
    (staging / "blender_manifest.toml").write_text(manifest, encoding="utf-8")


def run_tool(tool, *args):
    proc = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise BuildError(f"blender_ext {args[0]} failed:\n{proc.stdout}{proc.stderr}")
    return proc.stdout


def build(out_dir=ROOT / "dist", platforms=None, wheels=True, build_dir=ROOT / "build"):
    """Build and validate the zip; returns its path."""
    import tomllib
    platforms = platforms or [host_platform()]
    tool = blender_ext_tool()
    version = tomllib.loads((ADDON / "blender_manifest.toml").read_text())["version"]
    wheel_files = fetch_wheels(platforms, build_dir / "wheels") if wheels else []
    staging = build_dir / "extension" / "flowbsdf"
    stage(staging, wheel_files, platforms)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    suffix = "" if not wheels else "-" + "-".join(platforms)
    zip_path = out_dir / f"flowbsdf-{version}{suffix}.zip"
    zip_path.unlink(missing_ok=True)
    run_tool(tool, "build", "--source-dir", str(staging), "--output-filepath", str(zip_path))
    run_tool(tool, "validate", str(zip_path))
    return zip_path


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(ROOT / "dist"), help="folder for the zip (default: dist/)")
    p.add_argument("--platform", action="append", help=f"Blender platform(s) for the OpenEXR wheel "
                   f"(default: this machine, {host_platform()}); one of {', '.join(PIP_PLATFORMS)}")
    p.add_argument("--no-wheels", action="store_true", help="leave the OpenEXR wheel out (platform-independent zip)")
    p.add_argument("--build-dir", default=str(ROOT / "build"), help="staging and wheel cache (default: build/)")
    args = p.parse_args(argv)
    try:
        path = build(args.out, args.platform, wheels=not args.no_wheels, build_dir=Path(args.build_dir))
    except BuildError as e:
        print(f"build_extension: error: {e}", file=sys.stderr)
        return 1
    print(f"[wrote] {path} (validated by Blender's extension tool)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
