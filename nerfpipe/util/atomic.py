"""Atomic writes: nothing already written is lost and nothing is half-written.

Every output and checkpoint of nerfpipe goes through :func:`atomic_path`: the content is written
to a temporary next to the target (same folder, so the rename is atomic) and moved into place
with ``os.replace`` only when complete. A killed writer leaves only a ``.tmp-*`` temporary,
which :func:`sweep_temporaries` removes on the next run.

A folder cannot replace a non-empty folder in one rename, so the old one is first moved aside
(``.tmp-old-*``) and then the new one moved in. A writer killed between the two renames leaves the
target missing and its previous content aside: the sweep puts that back instead of removing it, so
a kill -9 at any instant leaves the old or the new content in place, never neither.

The content is flushed to the disk (``fsync`` of every file written, then of the folder that holds the
renamed entry) before and after the rename, so a power cut, not only a killed process, leaves the old or
the new content: a rename can otherwise reach the disk before the data it names.
"""

import contextlib
import dataclasses
import json
import os
import re
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

TMP_PREFIX = ".tmp-"
_ASIDE = re.compile(re.escape(TMP_PREFIX) + r"old-[0-9a-f]{8}-(?P<name>.+)")
"""A target moved aside by :func:`_replace` (its name after the prefix)."""


@contextlib.contextmanager
def atomic_path(target: "str | Path") -> Iterator[Path]:
    """Yield a temporary path next to ``target``; on success move it into place with ``os.replace``.

    Works for a file or a folder. The temporary keeps the target's suffix (writers that pick a
    format from it keep working). On any exception (KeyboardInterrupt included) the temporary
    is removed and ``target`` is left as it was.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> with atomic_path(d / "a.txt") as tmp:
        ...     _ = tmp.write_text("hi")
        >>> (d / "a.txt").read_text()
        'hi'
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f"{TMP_PREFIX}{uuid.uuid4().hex[:8]}-{target.name}")
    try:
        yield tmp
        _replace(tmp, target)
    finally:
        _remove(tmp)


def atomic_write(path: "str | Path", write: "Callable[[Path], object]") -> Path:
    """Call ``write(tmp_path)`` and move the finished file onto ``path``; returns ``path``."""
    with atomic_path(path) as tmp:
        write(tmp)
    return Path(path)


def write_json(target: "str | Path", obj: object) -> Path:
    """Write JSON atomically (dataclasses and paths are converted); returns the path."""
    return atomic_write(target, lambda p: p.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n"))


def write_text(target: "str | Path", text: str) -> Path:
    return atomic_write(target, lambda p: p.write_text(text))


def write_bytes(target: "str | Path", data: bytes) -> Path:
    return atomic_write(target, lambda p: p.write_bytes(data))


def sweep_temporaries(run_dir: "str | Path") -> None:
    """Remove the temporaries of writes that were killed before they finished (symlinks not followed);
    a folder moved aside whose replacement never arrived is put back first (see the module docstring)."""
    for p in sorted(Path(run_dir).rglob(f"{TMP_PREFIX}old-*"), key=lambda p: len(p.parts)):
        aside = _ASIDE.fullmatch(p.name)
        target = p.with_name(aside["name"]) if aside else None
        if target is not None and not target.exists() and not target.is_symlink():
            os.replace(p, target)
    found = Path(run_dir).rglob(f"{TMP_PREFIX}*")
    for p in sorted(set(found), key=lambda p: -len(p.parts)):
        _remove(p)


def _replace(tmp: Path, target: Path) -> None:
    _flush(tmp)
    if tmp.is_dir() and target.exists():  # os.replace cannot overwrite a non-empty folder
        old = target.with_name(f"{TMP_PREFIX}old-{uuid.uuid4().hex[:8]}-{target.name}")
        os.replace(target, old)
        os.replace(tmp, target)
        _flush_folder(target.parent)
        _remove(old)
    else:
        os.replace(tmp, target)
        _flush_folder(target.parent)


def _flush(path: Path) -> None:
    """``fsync`` a written file, or every file and folder of a written folder (symlinks not followed)."""
    if path.is_symlink() or not path.exists():
        return
    if path.is_dir():
        for root, _, files in os.walk(path):
            for name in files:
                if not os.path.islink(os.path.join(root, name)):
                    _fsync(os.path.join(root, name), os.O_RDONLY)
            _flush_folder(Path(root))
    else:
        _fsync(str(path), os.O_RDONLY)


def _flush_folder(folder: Path) -> None:
    """``fsync`` a folder, so that the entries renamed into it are on the disk (not possible everywhere)."""
    if os.name != "nt":  # Windows cannot open a folder
        _fsync(str(folder), os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))


def _fsync(path: str, flags: int) -> None:
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    except OSError:  # some file systems refuse fsync on a folder; the data files were flushed
        pass
    finally:
        os.close(fd)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        p.unlink()


def _json_default(o: object) -> object:
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
