#!/usr/bin/env bash
# Create or refresh .venv at the repo root with everything the project needs.
# Idempotent: reinstalls only when pyproject.toml, setup.py or the C source changed.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
py=${FLOWBSDF_PYTHON:-python3.11}
if ! command -v "$py" >/dev/null; then
  echo "flowbsdf: needs Python 3.11 (set FLOWBSDF_PYTHON to its path)" >&2
  exit 2
fi
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($py --version)"
  "$py" -m venv .venv
fi
stamp=.venv/.flowbsdf-installed
want=$(cat pyproject.toml setup.py bake/maths/_tables_c.c | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[setup] installing flowbsdf and its dependencies into .venv"
  .venv/bin/python -m pip install --quiet --upgrade pip
  # torch first and pinned: an unpinned torch would pull a multi-GB CUDA build.
  .venv/bin/python -m pip install --quiet "torch==2.13.0"
  .venv/bin/python -m pip install --quiet -e ".[train,report,test]"
  echo "$want" > "$stamp"
fi
# Mitsuba's vectorized (LLVM) variant, the benchmark peer, needs libLLVM 19; best effort:
# without it the peer falls back to the slow scalar variant and its heavy tests skip.
if [ "${FLOWBSDF_NO_APT:-}" = "" ] && ! ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19' \
   && command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
  echo "[setup] installing libllvm19 for Mitsuba's LLVM variant (best effort)"
  (apt-get install -y -qq libllvm19 >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libllvm19 >/dev/null 2>&1; }) \
    || echo "[setup] libllvm19 not installed: Mitsuba peer uses scalar_rgb"
fi
# Debian's Blender 3.4 gives the add-on's batch test a real `blender --background`; best
# effort (apt install measured at ~45 s here): without it tests/test_blender_batch.py skips.
if [ "${FLOWBSDF_NO_APT:-}" = "" ] && ! command -v blender >/dev/null && command -v apt-get >/dev/null \
   && [ "$(id -u)" = 0 ]; then
  echo "[setup] installing Debian's blender for the add-on's batch test (best effort, ~1 min)"
  (apt-get install -y -qq blender >/dev/null 2>&1 || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq blender >/dev/null 2>&1; }) \
    || echo "[setup] blender not installed: tests/test_blender_batch.py skips"
fi
