#!/usr/bin/env bash
# The main job: set up .venv, then run FlowBSDF end to end on the default manifest.
# Extra arguments go to `flowbsdf run` (e.g. --material NAME, --out DIR).
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/venv.sh
exec .venv/bin/flowbsdf run manifest.toml --out out "$@"
