"""Paths named by files, and the folders nerfpipe writes to: checked before anything is read or written.

Datasets and run folders are passed around, so a name inside one (a ``file_path`` in
``transforms.json``, a COLMAP image name, an image name handed to the load stage, a figure a
report embeds) must not reach outside it. :func:`resolve_inside` is the one check: the name is
resolved with ``os.path.realpath`` (``..``, absolute paths and symlinks alike), and the result
must lie in the resolved root. A symlink *to* the root is fine (the root is resolved too); a
symlink inside it that leads elsewhere is not.

:func:`check_output_folder` refuses an ``--out`` that cannot become a folder (it, or a folder
above it, is a file) before any work starts, instead of a ``NotADirectoryError`` at the end.
"""

import os
from pathlib import Path

from nerfpipe.util.errors import NerfpipeError


def resolve_inside(root: "str | Path", name: "str | Path", listed_in: "str | Path | None" = None) -> Path:
    """``root / name``, refusing a name that leads outside ``root`` once resolved.

    The returned path is ``root / name`` as written (normalised), so file names stay the ones
    the dataset uses; only the check follows symlinks.

    Args:
        root: the folder the name is relative to (a dataset, an image folder, a run folder).
        name: the name as found in a file or a folder listing.
        listed_in: the file that holds the name, named in the error (default: ``root``).

    Raises:
        NerfpipeError: ``"<listed_in>: '<name>' points outside the folder <root> ..."`` for ``..`` or an
            absolute path, ``"<root>/<name>: a symlink to <target>, outside the folder <root> ..."`` for a link.

    Example:
        >>> resolve_inside("/data/set", "images/a.png").as_posix()
        '/data/set/images/a.png'
    """
    text = str(name)
    if "\0" in text or len(os.fsencode(text)) > 4096 or any(len(os.fsencode(p)) > 255 for p in Path(text).parts):
        raise NerfpipeError(f"{text[:80]!r} is not a usable file name (a NUL character, or too long)", listed_in or root)
    root = Path(os.path.normpath(Path(root).absolute()))
    full = Path(os.path.normpath(root / name))
    real_root, real = Path(os.path.realpath(root)), Path(os.path.realpath(full))
    if real.is_relative_to(real_root):
        return full
    if full.is_relative_to(root):  # the name stays inside, a symlink on the way leads out: name the link
        where = f" (listed in {listed_in})" if listed_in is not None else ""
        raise NerfpipeError(f"a symlink to {real}, outside the folder {root}{where}; files must lie inside it", full)
    raise NerfpipeError(f"'{name}' points outside the folder {root} ('..' or an absolute path); files must lie inside it", listed_in or root)


def check_output_folder(out: "str | Path", flag: str = "--out") -> Path:
    """Fail now, naming ``flag``, when ``out`` cannot be (or become) a writable folder.

    Raises:
        NerfpipeError: ``out`` or one of the folders above it is a file, or the nearest
            existing folder is not writable.
    """
    out = Path(out)
    for folder in (out, *out.absolute().parents):
        if folder.exists():
            if not folder.is_dir():
                what = "is a file" if folder == out else f"lies under {folder}, which is a file"
                raise NerfpipeError(f"{flag} {what}, not a folder", out)
            if not os.access(folder, os.W_OK | os.X_OK):
                raise NerfpipeError(f"{flag}: no permission to write in {folder}", out)
            return out
    return out
