#!/usr/bin/env bash
# The tests: set up .venv, then run the default (fast) test suite.
# Extra arguments go to pytest (e.g. -m slow for the long training/benchmark tests; -n 0 runs
# them in this one process). Two workers by default, a test file each at a time (pytest-xdist,
# --dist loadfile: a file's module fixtures and its bpy scene stay in one process, as in a
# serial run), longest files first (tests/conftest.py: LONGEST_FIRST; xdist's own order, by
# test count, left the longest file for last); FLOWBSDF_TEST_WORKERS sets how many.
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/venv.sh
exec .venv/bin/python -m pytest -n "${FLOWBSDF_TEST_WORKERS:-2}" --dist loadfile --no-loadscope-reorder "$@"
