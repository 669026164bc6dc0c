#!/usr/bin/env bash
# The tests: set up .venv, then run the default (fast) test suite.
# Extra arguments go to pytest (e.g. -m slow for the long training/benchmark tests).
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/venv.sh
exec .venv/bin/python -m pytest "$@"
