"""Issue-52 where a Final bake's wall goes on 2 cores: per stage of its log, the share of time one
thread works while the other core idles, and the functions that run then.

    .venv/bin/python scripts/bake_threads.py MATERIAL [--manifest manifest.toml] [--out DIR]
        [--every 0.005] [--top 25]

Bakes MATERIAL of the manifest as `flowbsdf bake` does (tables, SVM/OSL exports, closure fit)
with threads on every core whatever the load (io.threads.free_workers patched: on a shared
machine it would fall back to one thread), and samples every thread's state (Linux: /proc's
task state, R: running or waiting only for a core) and Python stack every `every` seconds; numpy
and the C evaluator run under the Python frame that called them. The count of working threads
is the bake's own concurrency, whatever other processes take of the cores. Per stage (the log line that last began one): wall seconds, process CPU seconds, CPU/wall,
the mean working threads, the share of the time exactly one worked, and the wall the stage
would take on 2 idle cores: its CPU seconds over the cores its working threads kept busy
(CPU x mean(n / min(n, 2)) / mean(n) over the samples where n >= 1 threads worked: a loaded
machine gives each working thread a like share of a core); then the innermost bake functions seen
while only one thread worked (where a core idles). Prints Markdown; asserts nothing.
"""
import argparse
import collections
import os
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bake.io import threads as pool  # noqa: E402
from bake.plumbing.manifest import load_manifest  # noqa: E402
from bake.plumbing.pipeline import bake_with_derived  # noqa: E402


def running(native_id):
    """Whether the thread is running or waits only for a core (Linux task state R): a thread
    that waits for a lock, a queue or another thread's result sleeps (S)."""
    try:
        with open(f"/proc/self/task/{native_id}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] == "R"
    except OSError:
        return False


def where(frame):
    """The innermost frame of bake/ on the stack (file:function)."""
    while frame is not None:
        name = frame.f_code.co_filename
        if f"{os.sep}bake{os.sep}" in name and "bake_threads" not in name:
            return f"{Path(name).parent.name}/{Path(name).name}:{frame.f_code.co_name}"
        frame = frame.f_back
    return "?"


def stage_of(line):
    if line.startswith("[") and not line.startswith("[bake]"):
        return line.split("]")[0].strip("[")
    text = line.split(": ", 1)[-1] if line.startswith("[bake]") else line
    for key in ("resolution", "phi bins", "bins", "coordinates", "between bins", "tables", "carried"):
        if key in text:
            pre = text.split(":")[0] if text.startswith(("wo:", "halfpolar:")) else ""
            return (pre + " " + key).strip() if key in ("resolution", "bins") else key
    return line.split("]")[0].strip("[") if line.startswith("[") else text[:20]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("material")
    p.add_argument("--manifest", default=str(ROOT / "manifest.toml"))
    p.add_argument("--out", default="/tmp/bake_threads_out")
    p.add_argument("--every", type=float, default=0.005)
    p.add_argument("--top", type=int, default=25)
    args = p.parse_args()
    pool.free_workers = lambda cores: cores
    manifest = load_manifest(args.manifest)
    entry, = [e for e in manifest.select(args.material, log=print)]
    stage = ["start"]
    marks = [(time.monotonic(), time.process_time(), "start")]

    def log(line):
        print(f"{time.monotonic() - marks[0][0]:7.1f} {line}", flush=True)
        s = stage_of(line)
        if s != stage[0]:
            stage[0] = s
            marks.append((time.monotonic(), time.process_time(), s))

    samples = collections.defaultdict(list)       # stage -> working thread counts
    serial = collections.defaultdict(collections.Counter)
    done = threading.Event()

    def sample():
        me = threading.get_ident()
        while not done.wait(args.every):
            frames = sys._current_frames()
            busy = [frames[t.ident] for t in threading.enumerate()
                    if t.ident != me and t.ident in frames and running(t.native_id)]
            samples[stage[0]].append(len(busy))
            if len(busy) == 1:
                serial[stage[0]][where(busy[0])] += 1
    th = threading.Thread(target=sample, daemon=True)
    th.start()
    t0 = time.monotonic()
    bake_with_derived(entry, args.out, manifest.path, force=True, log=log)
    done.set()
    th.join()
    marks.append((time.monotonic(), time.process_time(), "end"))
    print(f"\n{entry.name}: {time.monotonic() - t0:.1f} s wall, load {os.getloadavg()[0]:.1f}\n")
    print("| stage | wall s | CPU s | CPU/wall | mean working threads | share with one working | "
          "on 2 idle cores: est. wall s |")
    print("|---|---|---|---|---|---|---|")
    per = collections.defaultdict(lambda: [0.0, 0.0])
    for (w0, c0, s), (w1, c1, _) in zip(marks[:-1], marks[1:]):
        per[s][0] += w1 - w0
        per[s][1] += c1 - c0
    totals = [0.0, 0.0, 0.0]
    for s, (w, c) in per.items():
        n = samples.get(s, [])
        mean = sum(n) / len(n) if n else 0.0
        one = sum(1 for k in n if k == 1) / len(n) if n else 0.0
        busy = [k for k in n if k >= 1]
        idle_wall = c * (sum(k / min(k, 2) for k in busy) / sum(busy)) if busy else c
        totals = [totals[0] + w, totals[1] + c, totals[2] + idle_wall]
        print(f"| {s} | {w:.1f} | {c:.1f} | {c / max(w, 1e-9):.2f} | {mean:.2f} | {one:.2f} | {idle_wall:.1f} |")
    print(f"| all | {totals[0]:.1f} | {totals[1]:.1f} | {totals[1] / totals[0]:.2f} | | | {totals[2]:.1f} "
          f"(CPU / {totals[1] / totals[2]:.2f} cores) |")
    print("\nOne thread working, by stage and innermost bake/ function (seconds):\n")
    for s, counter in serial.items():
        for fn, k in counter.most_common(args.top):
            if k * args.every >= 0.2:
                print(f"  {s:24s} {k * args.every:6.1f}  {fn}")


if __name__ == "__main__":
    main()
