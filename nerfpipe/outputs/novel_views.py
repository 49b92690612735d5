"""The one renderer of camera paths of a trained model, used by ``nerfpipe render`` and the ``render`` stage.

A :class:`RenderConfig` names the path (``orbit``, ``test`` or a ``camera_path.json`` file), the frame
count, the size, the background and whether depth is written. :func:`render_sequence` renders it
(under a time budget: fewer frames, then smaller ones, :func:`nerfpipe.outputs.render.plan_frames`) and
:func:`write_render` writes it into the run's ``render/`` folder, atomically: ``<name>.gif``,
``<name>.mp4``, ``depth_<name>.gif``, ``<name>.json`` (frame count, size, depth colour mapping, plan)
and with ``pngs`` the frames losslessly in ``<name>_frames/``. ``<name>`` is the path (``orbit``,
``test``) or the file's stem. The command and the stage differ only in where the model comes from.
"""

import json
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from nerfpipe.util.atomic import TMP_PREFIX, _remove, _replace
from nerfpipe.util.errors import NerfpipeError, refuse_unless

RENDER_DIR = "render"
"""The folder of a run (the pipeline run, or a ``nerfpipe train`` folder) that holds the renders."""
PATHS = ("orbit", "test")


@dataclass
class RenderConfig:
    """What to render: camera path, frames, size, background, depth (``nerfpipe render`` and the ``render`` stage)."""

    path: str = "orbit"
    """``orbit`` around the scene centre (along the photographs' own viewpoints for a collection taken from near and far,
    :func:`nerfpipe.data.orbit.along_photographs`), ``test`` (the dataset's test poses; orbit when it has none) or a
    camera_path.json file (nerfstudio's format, as ``nerfpipe view`` saves it), played at the file's fps and size."""
    frames: int = 60
    """Number of frames (orbit and test; a file gives its own)."""
    depth: bool = True
    """Also write depth_<path>.gif (turbo colour map, mapping in the JSON)."""
    background: Literal["auto", "black", "white", "grey"] = "auto"
    """auto: the training run's evaluation background."""
    size: "str | None" = None
    """Frame size WxH, e.g. 800x800 (default: the cameras' own times ``scale``, capped at ``max_size``)."""
    scale: float = 1.0
    """Resolution factor of the frames relative to the cameras."""
    max_size: int = 400
    """Longer side of the frames in pixels at most (after ``scale``; not applied to ``size`` nor to a file's size)."""
    chunk: "int | None" = None
    """Rays per forward pass (bounds memory; None: the model's ``render_chunk``)."""
    supersample: int = 1
    """Rays per pixel side, each pixel the mean over its area (:func:`~nerfpipe.outputs.render.render_cameras`): 2
    smooths the speckle and stair-steps a field learnt from larger photographs shows in small frames, at 4x the time
    per frame (under a time budget, fewer or smaller frames)."""
    fps: float = 15.0
    """Frames per second of the GIFs and the video (a camera_path.json file gives its own)."""
    pngs: bool = False
    """Also write every colour frame losslessly, as render/<path>_frames/00000.png, ..."""
    min_frames: int = 12
    """Under a time budget, never fewer frames than this (the resolution drops instead)."""
    budget_share: float = 0.4
    """Share of the pipeline's remaining time budget the rendering may spend."""
    last_share: float = 0.6
    """That share where only light stages (export, report) follow in the pipeline: the render stage is then the last
    that computes, and 40 % left the rest of a budget unused (the fox's photos: 12 frames of 104x184 and the run ended
    16 s early). Well below 1: the first frame's time has underestimated the others' by 19-42 % (Sacre Coeur, 2 runs)."""

    def __post_init__(self) -> None:
        if not self.from_file and self.path not in PATHS:
            raise NerfpipeError(f"unknown --path '{self.path}' (test, orbit or a camera_path.json file)")
        refuse_unless((
            ("frames", 1 <= self.frames <= 10_000, "between 1 and 10000", self.frames), ("scale", 0 < self.scale <= 16, "a positive factor (at most 16)", self.scale),
            ("chunk", self.chunk is None or self.chunk >= 1, "at least 1", self.chunk), ("fps", 0 < self.fps <= 240, "in (0, 240]", self.fps),
            ("max_size", self.max_size >= 1, "at least 1", self.max_size), ("min_frames", self.min_frames >= 1, "at least 1", self.min_frames),
            ("budget_share", 0 < self.budget_share <= 1, "in (0, 1]", self.budget_share),
            ("last_share", 0 < self.last_share <= 1, "in (0, 1]", self.last_share),
            ("supersample", 1 <= self.supersample <= 8, "1 to 8", self.supersample),
        ))  # fmt: skip
        if self.size is not None:
            parse_size(self.size)

    @property
    def from_file(self) -> bool:
        return self.path.lower().endswith(".json")

    @property
    def name(self) -> str:
        """The file names' stem: the path, or the camera file's stem."""
        return Path(self.path).stem if self.from_file else self.path


def parse_size(text: str) -> "tuple[int, int]":
    """``"WxH"`` -> ``(W, H)``; anything else is one line naming ``--size``."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise NerfpipeError(f"--size must be WxH, e.g. 800x800 (got '{text}')") from exc
    if not (0 < w <= 8192 and 0 < h <= 8192):
        raise NerfpipeError(f"--size must be positive, at most 8192x8192 (got '{text}')")
    return w, h


def read_path_file(config: RenderConfig):
    """The camera_path.json of ``config`` (None for orbit/test); a bad file is one line naming it."""
    from nerfpipe.data.camera_path import read_camera_path

    return read_camera_path(Path(config.path)) if config.from_file else None


def path_cameras(scene, config: RenderConfig, frames: int, camera_file=None):
    """``frames`` cameras of the path (a file's cameras evenly subsampled), full size."""
    import torch

    from nerfpipe.data.orbit import path_cameras as generated

    if camera_file is None:
        return generated(scene, config.path, frames)
    cams = camera_file.cameras.to(dtype=torch.float32)
    return cams[torch.linspace(0, len(cams) - 1, min(frames, len(cams))).round().long()]


def frame_size(cams, config: RenderConfig, extra_scale: float = 1.0) -> "tuple[int, int]":
    """Width and height of the frames: ``size``, else ``scale`` capped at ``max_size``; times ``extra_scale``."""
    from nerfpipe.outputs.render import capped_size

    if config.size is not None:
        w, h = parse_size(config.size)
    elif config.from_file:  # the file gives its size
        w, h = (max(1, round(int(v) * config.scale)) for v in (cams.width[0], cams.height[0]))
    else:
        w, h = capped_size(int(cams.width[0]), int(cams.height[0]), config.scale, config.max_size)
    return max(1, round(w * extra_scale)), max(1, round(h * extra_scale))


def background(config: RenderConfig, train_config: "dict | None", scene):
    """The background colour ``[3]``: the configured one, or (auto) the training run's evaluation background."""
    from nerfpipe.data.background import background_colors, backgrounds

    if config.background != "auto":
        return background_colors(config.background, 1)[0]
    mode = (train_config or {}).get("trainer", {}).get("background", "auto")
    return background_colors(backgrounds(mode, scene.has_alpha, scene.shows_surroundings)[1], 1)[0]


def plan_frames(config: RenderConfig, seconds_per_frame: float, time_left: "float | None", frames: "int | None" = None):
    """Frames and scale that fit ``budget_share * time_left`` (:func:`nerfpipe.outputs.render.plan_frames`) of
    ``frames`` (default ``config.frames``)."""
    from nerfpipe.outputs.render import plan_frames as plan

    allowed = None if time_left is None else config.budget_share * time_left
    return plan(config.frames if frames is None else frames, config.min_frames, seconds_per_frame, allowed)


def render_sequence(model, scene, config: RenderConfig, bg, device: str, time_left: "float | None" = None, camera_file=None):
    """Render the path; ``(views, info)``. The first frame is timed; under ``time_left`` the rendering
    keeps to ``budget_share`` of it (fewer frames, never below ``min_frames``, then smaller ones)."""
    from nerfpipe.outputs.render import render_cameras, resize_cameras
    from nerfpipe.util.progress import track

    wanted = len(camera_file.cameras) if camera_file is not None else config.frames
    sized = lambda cams, s: resize_cameras(cams, *frame_size(cams, config, s)).to(device)  # noqa: E731
    start, bg = time.perf_counter(), bg.to(device)
    views = render_cameras(model, sized(path_cameras(scene, config, wanted, camera_file)[:1], 1.0), config.chunk, bg, config.supersample)
    plan = plan_frames(config, time.perf_counter() - start, time_left, wanted)
    cams = sized(path_cameras(scene, config, plan.frames, camera_file), plan.scale)
    if plan.scale != 1.0:  # every path starts at the same camera for any count: the first frame is kept at full size only
        views = []
    for i in track(range(len(views), len(cams)), "render", total=len(cams) - len(views)):
        views += render_cameras(model, cams[i : i + 1], config.chunk, bg, config.supersample)
    info = {"path": config.path, "frames": len(views), "width": int(cams.width[0]), "height": int(cams.height[0]), "supersample": config.supersample,
            "background": [float(v) for v in bg.cpu()], "budget_plan": {"frames": plan.frames, "scale": plan.scale,
            "estimated_seconds": plan.estimated_seconds, "seconds": time.perf_counter() - start}}  # fmt: skip
    if config.path == "orbit" and camera_file is None:
        from nerfpipe.data.orbit import along_photographs, orbit_reference

        info["along_photographs"] = along_photographs(*orbit_reference(scene))
    return views, info


def write_render(folder: Path, views, config: RenderConfig, info: dict, fps: "float | None" = None) -> dict:
    """Write the sequence into ``folder`` (``render/``) atomically; returns the JSON written.

    Everything is written into a temporary next to ``folder`` first. A new ``folder`` is then moved into
    place in one rename; into an existing one (other paths rendered before) each file is moved in by
    its own rename, so a reader never sees a half-written file and other paths' files stay.
    """
    from nerfpipe.outputs.artifacts import write_sequence

    folder, name = Path(folder), config.name
    tmp = folder.with_name(f"{TMP_PREFIX}{uuid.uuid4().hex[:8]}-{folder.name}")
    try:
        tmp.mkdir(parents=True)
        info = {**write_sequence(views, tmp, name, depth=config.depth, fps=fps or config.fps), **info}
        if config.pngs:
            info["pngs"] = str(_write_pngs(views, tmp / f"{name}_frames"))
        info = {k: v.replace(str(tmp), str(folder)) if isinstance(v, str) else v for k, v in info.items()}
        (tmp / f"{name}.json").write_text(json.dumps(info, indent=2) + "\n")
        if not folder.exists():
            os.replace(tmp, folder)
        else:
            for entry in sorted(tmp.iterdir()):
                _replace(entry, folder / entry.name)
    finally:
        _remove(tmp)
    return info


def _write_pngs(views, folder: Path) -> Path:
    import imageio.v3 as iio

    from nerfpipe.outputs.render import to_uint8

    folder.mkdir()
    for i, v in enumerate(views):
        iio.imwrite(folder / f"{i:05d}.png", to_uint8(v.rgb))
    return folder
