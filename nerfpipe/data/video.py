"""A video of a capture as photographs: the sharpest frame of each stretch, for structure from motion.

A phone video walked around an object is a common capture: nerfpipe takes its frames the way instant-ngp's
``colmap2nerf --video_in`` and nerfstudio's ``ns-process-data video`` do, spread evenly over the video, but from
each stretch of ``duration / count`` the frame whose pixels vary most under a Laplacian (the least motion blur;
the "variance of the Laplacian" focus measure), which a walking capture needs: its frames blur with every step.

Frames are decoded once, in order, by ffmpeg (imageio-ffmpeg, which turns a phone's portrait video upright as
its display matrix says); only the best frame so far of each stretch is held. A file ffmpeg cannot decode
is one :class:`~nerfpipe.util.errors.NerfpipeError` naming it.

Glossary:
    stretch   consecutive frames of which one is kept (the video's frames split into ``count`` equal stretches)
    sharpness variance of the 4-neighbour Laplacian of the frame's grey levels, at most :data:`SHARPNESS_SIZE` pixels
              on the longer side
"""

import contextlib
import logging
import math
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from nerfpipe.data.image_file import _first_line
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.typing import UInt8

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
"""Files taken as a video of a capture."""

SHARPNESS_SIZE = 480
"""Longer side the frames are reduced to (by striding) before their sharpness is measured."""


def is_video(path: "str | Path | None") -> bool:
    """Whether ``path`` is a file with a video suffix (:data:`VIDEO_SUFFIXES`)."""
    return path is not None and Path(path).is_file() and Path(path).suffix.lower() in VIDEO_SUFFIXES


def sharpness(frame: UInt8[np.ndarray, "H W 3"]) -> float:
    """Variance of the 4-neighbour Laplacian of the grey levels (higher: sharper), on the frame strided down to
    about :data:`SHARPNESS_SIZE` pixels on its longer side."""
    step = max(1, math.ceil(max(frame.shape[:2]) / SHARPNESS_SIZE))
    grey = frame[::step, ::step, :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    lap = 4 * grey[1:-1, 1:-1] - grey[:-2, 1:-1] - grey[2:, 1:-1] - grey[1:-1, :-2] - grey[1:-1, 2:]
    return float(lap.var()) if lap.size else 0.0


@contextlib.contextmanager
def _quiet_reader() -> Iterator[None]:
    """What imageio-ffmpeg says that a user need not read, held back while it reads: the warning it logs for every
    rotated video (its frames' size differs from the stream's, as they are turned upright: a phone's portrait video
    is the common case), and the ``ResourceWarning`` for the pipes of an ffmpeg that ended by itself (it closes them
    only when it stops ffmpeg)."""
    logger = logging.getLogger("imageio_ffmpeg")
    note = lambda record: "different from the source frame size" not in record.getMessage()  # noqa: E731
    logger.addFilter(note)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ResourceWarning)
            yield
    finally:
        logger.removeFilter(note)


def _scale_filter(max_size: int) -> "list[str] | None":
    """ffmpeg's output options that scale frames down (area averaging) to at most ``max_size`` pixels on the
    longer side, keeping the aspect ratio (an even other side); None for 0."""
    if max_size <= 0:
        return None
    m = int(max_size)
    return ["-vf", f"scale='if(gt(iw,ih),min(iw,{m}),-2)':'if(gt(iw,ih),-2,min(ih,{m}))':flags=area"]


def frame_count(meta: dict) -> int:
    """The video's frame count from ffmpeg's duration and frame rate (at least 1)."""
    return max(1, round(float(meta.get("duration") or 0.0) * float(meta.get("fps") or 0.0)))


def stretch_of(index: int, total: int, count: int) -> int:
    """The stretch (``0 .. count - 1``) that frame ``index`` of ``total`` falls in (frames past ``total``, where
    the metadata undercounted, fall in the last)."""
    return min(count - 1, index * count // max(total, 1))


def sharpest_frames(path: "str | Path", count: int, max_size: int = 0) -> "list[tuple[int, float, UInt8[np.ndarray, 'H W 3']]]":
    """From each of ``count`` equal stretches of the video, the sharpest frame: ``(index, sharpness, pixels)`` in
    order (fewer where the video has fewer frames than ``count``). ``max_size`` > 0: ffmpeg scales the frames down to
    at most that many pixels on the longer side as it decodes them (90 frames of a 2160 x 3840 video read in 1.04 s
    at 1,024 px against 1.72 s whole: a phone's 4K frames are 25 MB each through the pipe).

    Raises:
        NerfpipeError: naming ``path`` when it is not a video ffmpeg can decode, or holds no frame.
    """
    import imageio_ffmpeg

    path = Path(path)
    if count < 1:
        raise NerfpipeError(f"the number of frames to take must be at least 1, got {count}", path)
    kept: "dict[int, tuple[int, float, np.ndarray]]" = {}
    failure = None
    with _quiet_reader():  # the error is raised after it, once ffmpeg's pipes are let go
        frames = imageio_ffmpeg.read_frames(str(path), output_params=_scale_filter(max_size))
        try:
            meta = next(frames)
            (width, height), total = meta["size"], frame_count(meta)
            for index, raw in enumerate(frames):
                frame = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3)
                stretch, score = stretch_of(index, total, count), sharpness(frame)
                if stretch not in kept or score > kept[stretch][1]:
                    kept[stretch] = (index, score, frame.copy())
        except Exception as exc:  # imageio-ffmpeg raises OSError / RuntimeError / StopIteration on broken files
            failure = f"{type(exc).__name__}: {_first_line(exc)}"
        finally:
            frames.close()
    if failure is not None:
        raise NerfpipeError(f"not a video ffmpeg can decode ({failure})", path)
    if not kept:
        raise NerfpipeError("the video holds no frame", path)
    return [kept[s] for s in sorted(kept)]


def write_frames(path: "str | Path", out: "str | Path", count: int, max_size: int = 0, quality: int = 95) -> "list[Path]":
    """The sharpest frame of each of ``count`` stretches of the video ``path`` as JPEG files in the folder ``out``
    (``frame_NNNNN.jpg`` by frame index; the folder is made), at most ``max_size`` pixels on the longer side
    (:func:`sharpest_frames`; 0: as decoded). Returns their paths in order."""
    from PIL import Image

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for index, _, pixels in sharpest_frames(path, count, max_size):
        file = out / f"frame_{index:05d}.jpg"
        Image.fromarray(pixels).save(file, quality=quality)
        paths.append(file)
    return paths

