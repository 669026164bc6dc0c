#!/usr/bin/env bash
# The add-on in the Blender versions users have: for each Blender LTS (default 4.2 and 4.5; the
# main .venv holds 5.0), a venv .venv-compat/<version> with Python 3.11 and that version's bpy
# wheel (+ numpy<2, OpenEXR, pytest), then the add-on's tests in it: register, scan, bake
# through the operators (never training: no torch there), bind, render the OSL and SVM back
# ends small, validate, build the extension zip with that Blender's own tool and install it.
#
#   bash scripts/compat_check.sh [VERSION...]        e.g. bash scripts/compat_check.sh 4.2
#
# Separate from the default test suite (each venv is a ~350 MB download, each run ~2-4 min).
# Extra pytest arguments: COMPAT_PYTEST_ARGS="-k bake". Exit code: 0 when every version passes.
set -uo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
py=${FLOWBSDF_PYTHON311:-python3.11}
if ! command -v "$py" >/dev/null; then
  echo "compat_check: needs Python 3.11 (bpy 4.2-5.0 wheels are cp311; set FLOWBSDF_PYTHON311)" >&2
  exit 2
fi
versions=("$@")
[ ${#versions[@]} -eq 0 ] && versions=(4.2 4.5)
failed=()
for ver in "${versions[@]}"; do
  venv=.venv-compat/$ver
  if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import bpy, numpy, OpenEXR, pytest" 2>/dev/null; then
    echo "[compat] creating $venv (bpy==$ver.*)"
    "$py" -m venv "$venv" && "$venv/bin/python" -m pip install --quiet "bpy==$ver.*" "numpy<2" OpenEXR pytest \
      || { echo "[compat] $ver: could not set up $venv" >&2; failed+=("$ver (setup)"); continue; }
  fi
  echo "[compat] $("$venv/bin/python" -c 'import bpy; print("Blender", bpy.app.version_string)')"
  # pytest through os._exit: the bpy 4.5 wheel deadlocks in a static destructor at exit
  # shellcheck disable=SC2086
  if ! "$venv/bin/python" -c 'import os, sys, pytest; code = pytest.main(sys.argv[1:]); sys.stdout.flush(); os._exit(int(code))' \
       -q -p no:cacheprovider -m "not slow" tests/test_addon.py ${COMPAT_PYTEST_ARGS:-}; then
    failed+=("$ver")
  fi
done
if [ ${#failed[@]} -gt 0 ]; then
  echo "[compat] failed: ${failed[*]}" >&2
  exit 1
fi
echo "[compat] passed: ${versions[*]}"
