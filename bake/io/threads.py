"""Threads for the baker's independent pieces of work (bins, probes, reference points): `parallel`
runs them on the cores other processes leave free; `workers` is how many cores this process may use."""
import os
import threading
import time


def workers():
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:          # not Linux
        return max(1, os.cpu_count() or 1)


_pool = None
_pool_lock = threading.Lock()
_local = threading.local()


def _cpu_seconds():
    """(seconds of CPU all processes have used, of which this process, wall seconds), or None
    where /proc/stat is not there (not Linux)."""
    try:
        with open("/proc/stat") as fh:
            ticks = [int(x) for x in fh.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    busy = (sum(ticks) - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK")     # all but idle, iowait
    t = os.times()
    return busy, t.user + t.system, time.monotonic()


_usage = {"last": None, "workers": None}


def free_workers(cores):
    """Threads worth running: the cores that other processes leave idle, as measured since
    the last look (1 to 10 s ago; else all cores, and a new window). On a machine shared with
    other jobs, threads that wait for a core cost CPU time (measured: chm_mint capped at 13
    bins, 31 s of CPU in one thread, 38-39 s in two, at a load of 3.4 on 2 cores)."""
    now = _cpu_seconds()
    if now is None:
        return cores
    with _pool_lock:
        last = _usage["last"]
        if last is None or now[2] - last[2] > 10.0:      # no recent look: a new window
            _usage["last"], _usage["workers"] = now, cores
        elif now[2] - last[2] >= 1.0:
            others = ((now[0] - last[0]) - (now[1] - last[1])) / (now[2] - last[2])
            _usage["last"], _usage["workers"] = now, int(min(cores, max(1, round(cores - others))))
        return _usage["workers"]


def parallel(fn, items):
    """fn(x) for x in items, in order (an iterator), in threads, one per core that other
    processes leave free (free_workers). The work is numpy and the C evaluator, which let go
    of the GIL, and every item's result is computed as in a loop (same bytes). A call from
    inside one of these threads runs its items in a loop (no nested pools)."""
    items = list(items)
    if len(items) < 2 or getattr(_local, "busy", False) or min(free_workers(workers()), len(items)) < 2:
        return map(fn, items)
    global _pool
    with _pool_lock:
        if _pool is None:
            from concurrent.futures import ThreadPoolExecutor
            _pool = ThreadPoolExecutor(workers(), thread_name_prefix="flowbsdf-bake")

    def run(x):
        _local.busy = True
        try:
            return fn(x)
        finally:
            _local.busy = False
    return _pool.map(run, items)
