"""One nerfpipe process at a time in a run folder.

Two runs writing into one folder would interleave their artifacts and checkpoints, and the second
one's sweep of temporaries (:func:`nerfpipe.util.atomic.sweep_temporaries`) would delete files the first
is still writing. So a pipeline run (:meth:`nerfpipe.pipeline.stages.Pipeline.run`), ``nerfpipe stage`` and a
training (:meth:`nerfpipe.training.trainer.Trainer.train`) each hold :func:`run_lock` on their folder while
they work, and a second one refuses at once with one line naming the holder.

The lock is ``flock`` on the file :data:`LOCK_FILE` in the folder. The kernel releases it when its
holder dies, however it dies (kill -9 included), so a lock left behind by a killed run is never
stale: the file stays, unlocked, and the next run takes it over. The file holds a small JSON record
(pid, host, start time, command line) only for the message of a refused run. A finished holder
removes the file; to avoid the race in which a second process locks a file that was just removed,
a lock counts only if the locked file is still the one at the path (same inode), else it is taken
again. ``flock`` locks belong to an open file, so a second lock from the same process (another
thread) is refused as well.

Platforms without ``fcntl`` (Windows) take no lock; nerfpipe's other process settings are Linux's
too (``/proc/stat``, glibc).
"""

import contextlib
import json
import os
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from nerfpipe.util.errors import NerfpipeError

try:
    import fcntl
except ImportError:  # pragma: no cover (Windows)
    fcntl = None

LOCK_FILE = ".nerfpipe.lock"
"""The lock's file in a run folder."""


@contextlib.contextmanager
def run_lock(run_dir: "str | Path") -> Iterator[Path]:
    """Hold the run folder's lock for the block (the folder is created); yields the lock file's path.

    Raises:
        NerfpipeError: naming the folder and the process that holds it, when another one does.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> with run_lock(d) as lock:
        ...     lock.is_file()
        True
        >>> lock.exists()  # removed when released
        False
    """
    path = Path(run_dir) / LOCK_FILE
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file in the way, no permission
        raise NerfpipeError(f"cannot create the run folder ({exc.strerror or exc})", path.parent) from exc
    fd = _acquire(path) if fcntl is not None else None
    try:
        yield path
    finally:
        if fd is not None:
            path.unlink(missing_ok=True)  # while still locked: whoever opened this file sees it gone
            os.close(fd)


def holder(run_dir: "str | Path") -> "dict | None":
    """The record of the process that last took the folder's lock (None: none, or unreadable)."""
    try:
        record = json.loads((Path(run_dir) / LOCK_FILE).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _acquire(path: Path) -> int:
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as exc:  # locked by a live process
            os.close(fd)
            raise NerfpipeError(_in_use(holder(path.parent)), path.parent) from exc
        except OSError as exc:  # a file system without locks
            os.close(fd)
            raise NerfpipeError(f"cannot lock the run folder ({exc.strerror})", path.parent) from exc
        if _is_current(fd, path):
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps(_record()).encode())
            return fd
        os.close(fd)  # its holder removed this file as we locked it: lock the one at the path now


def _is_current(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    return os.fstat(fd).st_ino == st.st_ino and os.fstat(fd).st_dev == st.st_dev


def _record() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) if sys.argv and sys.argv[0] else "python"}


def _in_use(record: "dict | None") -> str:
    who = "another nerfpipe process"
    if record is not None:
        who = f"nerfpipe process {record.get('pid')} on {record.get('host')} (since {record.get('started')}: {record.get('command')})"
    return f"run folder is in use by {who}; wait for it to finish, or use another output folder"
