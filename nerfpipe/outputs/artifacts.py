"""Novel-view sequences as files: colour GIF + MP4 and a colour-mapped depth GIF (one writer for
the trainer's end-of-run outputs and ``nerfpipe render``)."""

from pathlib import Path

from nerfpipe.outputs.colormap import colorize_depth, depth_range, mapping_text
from nerfpipe.outputs.render import RenderedView, to_uint8
from nerfpipe.outputs.video import VIDEO_DEPENDENCIES, write_gif, write_video

SEQUENCE_DEPENDENCIES = (*VIDEO_DEPENDENCIES, ("matplotlib", "plot"))
"""What :func:`write_sequence` needs: the MP4 encoder, and matplotlib's colour map for the depth GIF."""


def write_sequence(views: "list[RenderedView]", out_dir: Path, name: str = "orbit", depth: bool = True, fps: float = 15.0) -> dict:
    """Write ``{name}.gif``, ``{name}.mp4`` and (``depth``) ``depth_{name}.gif``; returns what was written
    and the depth mapping."""
    out_dir = Path(out_dir)
    frames = [to_uint8(v.rgb) for v in views]
    info = {"frames": len(frames), "size": [int(frames[0].shape[1]), int(frames[0].shape[0])]}
    info["gif"] = str(write_gif(frames, out_dir / f"{name}.gif", fps))
    info["mp4"] = str(write_video(frames, out_dir / f"{name}.mp4", fps))
    if depth:
        lo, hi = depth_range([v.depth for v in views], [v.acc for v in views])
        dframes = [colorize_depth(v.depth, v.acc, lo, hi) for v in views]
        info["depth_gif"] = str(write_gif(dframes, out_dir / f"depth_{name}.gif", fps))
        info["depth_mapping"] = mapping_text(lo, hi)
        info["depth_range"] = [lo, hi]
    return info
