"""Per-test CPU of a pytest run, for ranking the default suite's costs on a busy machine (wall
durations there mostly measure the other jobs).

As a pytest plugin (-p pytest_cpu, scripts/ on PYTHONPATH), each process (every xdist worker)
appends one line per test to <FLOWBSDF_TEST_CPU_DIR>/cpu_<worker>.tsv: the process's user+sys
CPU over the test's setup, call and teardown (module fixtures count in the first test that
needs them; Cycles' render threads count; subprocesses count once waited for), its wall
seconds, and its node id:

  FLOWBSDF_TEST_CPU_DIR=/tmp/cpu PYTHONPATH=scripts nice -n 10 \\
      .venv/bin/python -m pytest -p pytest_cpu -n 2 --dist loadfile --no-loadscope-reorder tests/

Run as a script, it sums such a folder per test file and lists the costliest tests:

  .venv/bin/python scripts/pytest_cpu.py /tmp/cpu [how many tests, 40]
"""
import os
import sys
import time

import pytest

_out = []


def _cpu():
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    if not _out:
        folder = os.environ.get("FLOWBSDF_TEST_CPU_DIR", ".")
        os.makedirs(folder, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        _out.append(open(os.path.join(folder, f"cpu_{worker}.tsv"), "a", buffering=1))
    cpu, wall = _cpu(), time.time()
    yield
    _out[0].write(f"{_cpu() - cpu:.2f}\t{time.time() - wall:.1f}\t{item.nodeid}\n")



def main(folder, top=40):
    rows = []
    for name in sorted(os.listdir(folder)):
        if name.startswith("cpu_") and name.endswith(".tsv"):
            with open(os.path.join(folder, name)) as fh:
                rows += [(float(cpu), float(wall), node) for cpu, wall, node in (ln.rstrip("\n").split("\t") for ln in fh)]
    files = {}
    for cpu, _, node in rows:
        files.setdefault(node.split("::")[0], []).append(cpu)
    total = sum(cpu for cpu, _, _ in rows)
    print(f"{len(rows)} tests, {total:.1f} s CPU (user+sys)")
    for path, cpus in sorted(files.items(), key=lambda kv: -sum(kv[1])):
        print(f"{sum(cpus):8.1f} s  {100 * sum(cpus) / total:5.1f} %  {len(cpus):4d} tests  {path}")
    print(f"\nthe {top} costliest tests (CPU s, wall s):")
    for cpu, wall, node in sorted(rows, reverse=True)[:top]:
        print(f"{cpu:8.2f} {wall:8.1f}  {node}")


if __name__ == "__main__":
    main(sys.argv[1], *(int(a) for a in sys.argv[2:3]))
