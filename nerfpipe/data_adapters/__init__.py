"""Format readers: each module converts one input format into nerfpipe's :class:`SceneData`.

Adapters are found through the entry-point group ``nerfpipe.data_adapters`` (the built-ins
register there too). :func:`load` picks the adapter whose ``detect`` scores a path highest.
"""

from pathlib import Path

from nerfpipe.data.image_file import photo_folder, unread_photos
from nerfpipe.data.scene import SceneData
from nerfpipe.data.video import is_video
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.registry import ADAPTER_GROUP, AdapterSpec, discover

__all__ = ["adapters", "detect", "load"]


def adapters() -> "dict[str, AdapterSpec]":
    """All installed adapters by name."""
    return discover(ADAPTER_GROUP, AdapterSpec)


def detect(path: "str | Path") -> AdapterSpec:
    """The adapter that recognises ``path`` best, or a :class:`NerfpipeError`."""
    path = Path(path)
    if not path.exists():
        raise NerfpipeError("no such file or folder", path)
    scored = sorted(((spec.detect(path), name, spec) for name, spec in adapters().items()), key=lambda s: -s[0])
    if not scored or scored[0][0] <= 0:
        unread = unread_photos(path)
        if unread:
            kinds = ", ".join(sorted({p.suffix for p in unread}))
            raise NerfpipeError(f"holds {len(unread)} photos in a format nerfpipe does not read ({kinds}): convert them to JPEG "
                                f"or PNG (e.g. ImageMagick's `mogrify -format jpg *{unread[0].suffix}`)", path)
        if is_video(path) or photo_folder(path) is not None:
            raise NerfpipeError(f"{'a video' if is_video(path) else 'photos'} without camera poses: `nerfpipe run {path}` "
                                "reconstructs them first (its sfm stage), then reads the result in RUN/sfm", path)
        known = ", ".join(sorted(adapters()))
        raise NerfpipeError(f"not a dataset nerfpipe can read (known formats: {known})", path)
    return scored[0][2]


def load(path: "str | Path", format: "str | None" = None) -> SceneData:
    """Read a dataset from a file or folder, detecting its format unless ``format`` is given."""
    if format is not None:
        table = adapters()
        if format not in table:
            raise NerfpipeError(f"unknown format '{format}' (known: {', '.join(sorted(table))})", path)
        return table[format].read(Path(path))
    return detect(path).read(Path(path))
