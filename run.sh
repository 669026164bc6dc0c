#!/usr/bin/env bash
# The main job: set up .venv, then run FlowBSDF end to end and write one page of results.
#   ./run.sh          the demonstration, demo.toml: three materials, minutes -> out/demo/index.html
#   ./run.sh --all    every material of manifest.toml (about an hour)     -> out/index.html
# Other arguments go to `flowbsdf run` (e.g. --material NAME, --no-render, --preset balanced).
# A rerun skips what is current (models, tables, reports, renders) and resumes training.
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/venv.sh
if [ "${1:-}" = "--all" ]; then
  shift
  exec .venv/bin/flowbsdf run manifest.toml --out out "$@"
fi
exec .venv/bin/flowbsdf run demo.toml --out out/demo "$@"
