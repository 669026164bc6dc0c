"""Files: content hashes (what decides whether a cached product is current), atomic writes, and a
folder's job.json (its stamp: what inputs made the files in it)."""
import hashlib
import json
import os
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path


def file_hash(path):
    """sha256 hex digest of the file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path):
    """A temporary path next to `path`, renamed onto it when the block succeeds and removed when
    it fails: a crash never leaves a half-written file under the real name. The file gets the
    usual permissions (mkstemp's are private)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_stale_temps(path, older_than=600.0):
    """Delete temporaries of `path` that a killed writer left behind (a live writer's temporary
    exists only for the seconds its write takes)."""
    path = Path(path)
    now = time.time()
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            if now - tmp.stat().st_mtime > older_than:
                tmp.unlink()
        except OSError:
            pass


def read_stamp(folder):
    """The job.json of a report or render folder, or None."""
    try:
        return json.loads((Path(folder) / "job.json").read_text())
    except (OSError, ValueError):
        return None


def write_stamp(folder, inputs_hash, **data):
    with atomic_path(Path(folder) / "job.json") as tmp:
        Path(tmp).write_text(json.dumps({"inputs_hash": inputs_hash, **data}, indent=1, default=str))
