"""Writing frame sequences as GIF or MP4, atomically (temporary file in the same folder, then rename)."""

from pathlib import Path

import numpy as np

from nerfpipe.util.atomic import atomic_write
from nerfpipe.util.errors import require

VIDEO_DEPENDENCIES = (("imageio_ffmpeg", "video"),)
"""What :func:`write_video` needs beyond the core (checked up front by whoever will write one)."""


def _frames(frames) -> "list[np.ndarray]":
    out = [np.asarray(f) for f in frames]
    if not out or any(f.dtype != np.uint8 or f.ndim != 3 for f in out):
        raise ValueError("frames must be a non-empty sequence of uint8 [H, W, C] arrays")
    return out


def write_gif(frames, path: "str | Path", fps: float = 15.0) -> Path:
    """Write uint8 frames ``[H, W, 3]`` as a looping GIF."""
    import imageio.v2 as imageio

    frames = _frames(frames)
    return atomic_write(Path(path), lambda p: imageio.mimsave(p, frames, format="GIF", duration=1000.0 / fps, loop=0))


def write_video(frames, path: "str | Path", fps: float = 15.0) -> Path:
    """Write uint8 frames as an H.264 MP4 (odd sizes are padded by one pixel to even)."""
    require(*VIDEO_DEPENDENCIES[0])
    import imageio.v2 as imageio

    frames = _frames(frames)
    h, w = frames[0].shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    frames = [np.pad(f[..., :3], pad, mode="edge") for f in frames]

    def write(p: Path) -> None:
        with imageio.get_writer(p, format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1, quality=8) as writer:
            for f in frames:
                writer.append_data(f)

    return atomic_write(Path(path), write)
