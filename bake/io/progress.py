"""Progress of a long job: one line per stage with an estimate of the time left, and never a
silent minute.

A job is a plan of stages, each of a kind ("train", "bake", ...; a prior estimate of seconds
per kind) and either to run or current (nothing to do: it costs no time). `stage(kind, label)`
opens the next one and prints

    [3/12 bake paper_white] · job: ~4m10s left

`update(fraction, note)` reports progress inside it, and a heartbeat thread prints a status
line whenever nothing was printed for `heartbeat` seconds. Estimates: a stage under way, from
its own rate once it reports a fraction, else its kind's estimate minus its elapsed time; the
stages still to run, from the mean duration of the finished stages of their kind, else their
prior times the ratio actual / prior of every stage finished so far (a busy machine scales
them all). A stage's closing line gives its wall time and the CPU time of this process and its
children (on a shared machine the two differ).
"""
import dataclasses
import os
import threading
import time
from dataclasses import dataclass


def fmt_seconds(s):
    s = max(0.0, float(s))
    if s < 60:
        return f"{s:.0f}s"
    if s < 3600:
        return f"{int(s // 60)}m{int(s % 60):02d}s"
    return f"{int(s // 3600)}h{int(s % 3600 // 60):02d}m"


def cpu_seconds():
    """User + system CPU time of this process and its finished children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


@dataclass(frozen=True)
class _Stage:
    kind: str
    label: str
    todo: bool
    start: float
    cpu: float
    fraction: float = None
    note: str = ""


class Progress:
    def __init__(self, plan, priors, out=None, heartbeat=20.0, clock=time.monotonic, cpu=cpu_seconds):
        """plan: (kind, to run?) of every stage, in order; priors: {kind: seconds}."""
        self.plan = list(plan)
        self.priors = dict(priors)
        self.out = out or (lambda line: print(line, flush=True))
        self.clock, self.cpu = clock, cpu
        self.t0 = clock()
        self.finished = []          # (kind, seconds, prior) of the stages that ran
        self.index = 0              # stages opened so far
        self.current = None         # the open _Stage (replaced whole, so the heartbeat reads it safely)
        self.last_print = clock()
        self.lock = threading.Lock()
        self.stopped = threading.Event()
        self.thread = None
        if heartbeat:
            self.thread = threading.Thread(target=self._beat, args=(heartbeat,), daemon=True)
            self.thread.start()

    # ---------------------------------------------------------------- estimates

    def estimate(self, kind):
        """Seconds a stage of this kind is expected to take."""
        mine = [s for k, s, _ in self.finished if k == kind]
        if mine:
            return sum(mine) / len(mine)
        scored = [(s, p) for _, s, p in self.finished if p > 0]
        factor = sum(s for s, _ in scored) / sum(p for _, p in scored) if scored else 1.0
        return self.priors.get(kind, 0.0) * factor

    def stage_left(self, stage, now):
        if stage is None or not stage.todo:
            return 0.0
        elapsed = now - stage.start
        if stage.fraction is not None and stage.fraction >= 0.02:
            return elapsed * (1.0 - stage.fraction) / stage.fraction
        return max(self.estimate(stage.kind) - elapsed, 0.0)

    def job_left(self, stage, now):
        return self.stage_left(stage, now) + sum(self.estimate(k) for k, todo in self.plan[self.index:] if todo)

    # ---------------------------------------------------------------- printing

    def say(self, line):
        with self.lock:
            self.out(line)
            self.last_print = self.clock()

    def _status(self, stage, now):
        done = "" if stage.fraction is None else f" {100 * stage.fraction:.0f}%"
        left = self.stage_left(stage, now)
        elapsed = now - stage.start
        left_text = f"~{fmt_seconds(left)} left" if left > 0 or stage.fraction is not None else \
            f"longer than the ~{fmt_seconds(self.estimate(stage.kind))} estimated"
        return (f"[{stage.kind} {stage.label}]{done}{' ' + stage.note if stage.note else ''} · "
                f"{fmt_seconds(elapsed)} so far, {left_text} · job: ~{fmt_seconds(self.job_left(stage, now))} left")

    def stage(self, kind, label):
        """Open the next stage of the plan (closing the one before, if still open)."""
        self.end()
        if self.index >= len(self.plan) or self.plan[self.index][0] != kind:
            raise ValueError(f"stage {kind!r} is not next in the plan (stage {self.index})")
        todo = self.plan[self.index][1]
        self.index += 1
        now = self.clock()
        self.current = stage = _Stage(kind, label, todo, now, self.cpu())
        self.say(f"[{self.index}/{len(self.plan)} {kind} {label}] · job: ~{fmt_seconds(self.job_left(stage, now))} left")

    def update(self, fraction=None, note="", every=10.0):
        """Progress inside the current stage (fraction done, or None); printed at most every `every` s."""
        if self.current is None:
            return
        self.current = stage = dataclasses.replace(self.current, fraction=fraction, note=note)
        now = self.clock()
        if now - self.last_print >= every:
            self.say(self._status(stage, now))

    def end(self, skipped=False, note=""):
        """Close the current stage: skipped = its product was current (it did no work)."""
        stage, self.current = self.current, None
        if stage is None:
            return
        seconds = self.clock() - stage.start
        if not skipped:
            self.finished.append((stage.kind, seconds, self.priors.get(stage.kind, 0.0)))
        if note:
            cpu = "" if skipped else f", CPU {fmt_seconds(self.cpu() - stage.cpu)}"
            self.say(f"[{stage.kind} {stage.label}] {note} ({fmt_seconds(seconds)}{cpu})")

    def _beat(self, every):
        while not self.stopped.wait(min(every, 5.0)):
            now, stage = self.clock(), self.current
            if stage is not None and now - self.last_print >= every:
                self.say(self._status(stage, now))

    def close(self):
        """Stop the heartbeat; returns the seconds since the job began."""
        self.end()
        self.stopped.set()
        if self.thread is not None:
            self.thread.join()
        return self.clock() - self.t0
