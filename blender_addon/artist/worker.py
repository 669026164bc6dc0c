"""Worker jobs: FlowBSDF's heavy work in a subprocess, so Blender never freezes.

A Job starts `worker_main.py` in its own process group, a reader thread collects its
output lines, and the UI polls (`poll()`) from a modal operator's timer; `cancel()` ends
the whole group (the worker and a trainer it started). In background mode (batch, tests)
`run()` follows the job to its end, echoing lines to stdout.
"""
import os
import queue
import re
import signal
import subprocess
import threading
import time

from .. import deps

PROGRESS_RE = re.compile(r"^\[progress (\d+)/(\d+)\]\s*(.*)$")
STEP_RE = re.compile(r"^\[step ([0-9.]+)\]\s*(.*)$")


class JobError(Exception):
    """A job that failed: str(e) is one line fit for Blender's report popup, `details` the rest
    (shown in the panel and printed to the console)."""

    def __init__(self, message, details=""):
        super().__init__(message)
        self.details = details


def short(text, limit=100):
    """The first line of a message, cut at a word boundary to at most `limit` characters."""
    line = text.strip().splitlines()[0] if text.strip() else ""
    if len(line) <= limit:
        return line
    cut = line[:limit - 1]
    at_word = cut.rsplit(" ", 1)[0].rstrip(",;:")
    return (at_word if len(at_word) > 0.7 * limit else cut) + "\u2026"


class Job:
    """`python worker_main.py ARGS`, or with script=None the program `python` itself with ARGS
    (a background Blender: the asset library's library.blend); its lines read the same way."""

    def __init__(self, python, args, extra_paths=(), label="FlowBSDF", script=deps.WORKER_SCRIPT):
        self.label = label
        self.cmd = [str(python), *([str(script)] if script else []), *map(str, args)]
        self.lines = []               # everything the worker printed
        self.fraction = 0.0
        self.message = "starting"
        self._step = (0, 1, False)       # (steps done, steps planned, words came from [step] lines)
        self.error = None
        self.cancelled = False
        self.returncode = None
        self._queue = queue.Queue()
        kwargs = {"start_new_session": True} if os.name == "posix" else {
            "creationflags": subprocess.CREATE_NEW_PROCESS_GROUP}
        try:
            self.proc = subprocess.Popen(self.cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, text=True, bufsize=1,
                                         env=deps.worker_env(python, extra_paths), **kwargs)
        except OSError as e:
            raise JobError(f"cannot start {python}: {e}") from None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.proc.stdout:
            self._queue.put(line.rstrip("\n"))
        self.proc.stdout.close()
        self._queue.put(None)

    def poll(self):
        """New output lines since the last call; sets returncode once the worker is done."""
        new = []
        while True:
            try:
                line = self._queue.get_nowait()
            except queue.Empty:
                break
            if line is None:
                self.returncode = self.proc.wait()
                self._finish()
                break
            new.append(line)
            self._take(line)
        return new

    @property
    def done(self):
        return self.returncode is not None

    def _take(self, line):
        """Progress: `[progress K/N]` starts step K of N, `[step F]` says how far it is (F of it)
        in an artist's words, which then stay the message; other lines are the log."""
        self.lines.append(line)
        m, step = PROGRESS_RE.match(line), STEP_RE.match(line)
        if m:
            k, n = int(m.group(1)), max(int(m.group(2)), 1)
            self.fraction = min((k - 1) / n if m.group(3) != "done" else 1.0, 1.0)
            self.message = m.group(3)
            self._step = (k - 1, n, False)
        elif step:
            done, n, _ = self._step
            self.fraction = max(self.fraction, min((done + float(step.group(1))) / n, 1.0))
            self.message = step.group(2)
            self._step = (done, n, True)
        elif line.startswith("[error] "):
            self.error = line[len("[error] "):]
        elif line.strip() and not line.startswith("  ") and not self._step[2]:
            self.message = line.strip()[:120]

    def _finish(self):
        if self.cancelled:
            self.error = "cancelled"
        elif self.returncode != 0 and not self.error:
            tail = [ln for ln in self.lines if ln.strip()][-1:] or ["no output"]
            self.error = f"the worker failed (exit code {self.returncode}): {tail[0]}"
        if self.returncode == 0:
            self.fraction = 1.0

    def cancel(self):
        """End the worker and everything it started; poll() then reports 'cancelled'."""
        if self.proc.poll() is not None:
            return
        self.cancelled = True
        try:
            if os.name == "posix":
                os.killpg(self.proc.pid, signal.SIGTERM)
            else:
                self.proc.terminate()
        except ProcessLookupError:
            return
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            if os.name == "posix":
                os.killpg(self.proc.pid, signal.SIGKILL)
            else:
                self.proc.kill()

    def run(self, echo=True):
        """Follow the job to its end (background mode); returns the lines; JobError on failure."""
        try:
            while not self.done:
                for line in self.poll():
                    if echo:
                        print(line, flush=True)
                if not self.done:
                    time.sleep(0.05)
        except KeyboardInterrupt:
            self.cancel()
            raise
        if self.error:
            raise JobError(self.error)
        return self.lines


# The one job the UI runs at a time (module state: survives panel redraws, not Blender).
current = None


def start(python, args, extra_paths=(), label="FlowBSDF"):
    global current
    if current is not None and not current.done:
        raise JobError(f"{current.label} is still running (cancel it first)")
    current = Job(python, args, extra_paths, label)
    return current


def clear():
    global current
    if current is not None and not current.done:
        current.cancel()
        current.poll()
    current = None


def python_for(prefs, need_train=False, where="ui"):
    """deps.choose_python with the add-on preferences; JobError (short line + details) when
    there is no Python for the job."""
    try:
        return deps.choose_python(prefs.python_path if prefs else "", need_train=need_train,
                                  extra_paths=extra_paths(prefs), where=where)
    except deps.PythonNotFound as e:
        raise JobError(str(e), e.details) from None


def extra_paths(prefs):
    paths = getattr(prefs, "module_path", "") if prefs else ""
    return tuple(p for p in (paths or "").split(os.pathsep) if p.strip())
