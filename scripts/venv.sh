#!/usr/bin/env bash
# Create or refresh .venv at the repo root with everything the project needs.
# Idempotent: reinstalls only when pyproject.toml changed since the last run.
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
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[setup] installing flowbsdf and its dependencies into .venv"
  .venv/bin/python -m pip install --quiet --upgrade pip
  # torch first and pinned: an unpinned torch would pull a multi-GB CUDA build.
  .venv/bin/python -m pip install --quiet "torch==2.13.0"
  .venv/bin/python -m pip install --quiet -e ".[train,test]"
  echo "$want" > "$stamp"
fi
