"""Stage ``render``: novel views of the trained model, an orbit in colour and depth.

Frames are at most ``max_size`` pixels on their longer side (phone photographs are not rendered at
full size). Under a pipeline time budget the first frame is timed and the stage keeps to
``budget_share`` of the time left: fewer frames (never below ``min_frames``), then smaller ones.
The plan actually used is in ``orbit.json`` (``frames``, ``width``, ``height``, ``budget_plan``).

Uses :func:`nerfpipe.orbit.path_cameras`, :func:`nerfpipe.render.render_cameras` and
:func:`nerfpipe.artifacts.write_sequence`, the same functions as ``nerfpipe render``, and writes the
folder ``render/``: ``orbit.gif``, ``orbit.mp4``, ``depth_orbit.gif`` and ``orbit.json`` (frame
count, size, depth colour mapping); ``test*`` instead of ``orbit*`` for the test path. The
rendered views are also returned in memory (``views``).
"""

import json
import time
from dataclasses import dataclass
from typing import Literal

from nerfpipe.artifacts import SEQUENCE_DEPENDENCIES
from nerfpipe.errors import refuse_unless
from nerfpipe.render import FramePlan, plan_frames as _plan
from nerfpipe.stages import StageContext, StageSpec, atomic_path

RENDER_DIR = "render"


@dataclass
class RenderConfig:
    """Options of the ``render`` stage."""

    path: Literal["orbit", "test"] = "orbit"
    """``orbit`` around the scene centre, or the dataset's test poses (orbit when it has none)."""
    frames: int = 60
    """Number of frames."""
    scale: float = 1.0
    """Resolution factor of the frames relative to the cameras."""
    chunk: int = 4096
    """Rays per forward pass (bounds memory)."""
    fps: float = 15.0
    """Frames per second of the GIFs and the video."""
    max_size: int = 400
    """Longer side of the frames in pixels at most (after ``scale``)."""
    min_frames: int = 12
    """Under a time budget, never fewer frames than this (the resolution drops instead)."""
    budget_share: float = 0.4
    """Share of the pipeline's remaining time budget this stage may spend."""

    def __post_init__(self) -> None:
        refuse_unless((
            ("frames", 1 <= self.frames <= 10_000, "between 1 and 10000", self.frames), ("scale", 0 < self.scale <= 16, "a positive factor (at most 16)", self.scale),
            ("chunk", self.chunk >= 1, "at least 1", self.chunk), ("fps", 0 < self.fps <= 240, "in (0, 240]", self.fps),
            ("max_size", self.max_size >= 1, "at least 1", self.max_size), ("min_frames", self.min_frames >= 1, "at least 1", self.min_frames),
            ("budget_share", 0 < self.budget_share <= 1, "in (0, 1]", self.budget_share),
        ))  # fmt: skip


def plan_frames(config: RenderConfig, seconds_per_frame: float, time_left: "float | None") -> FramePlan:
    """Frames and scale that fit ``budget_share * time_left`` (:func:`nerfpipe.render.plan_frames`)."""
    allowed = None if time_left is None else config.budget_share * time_left
    return _plan(config.frames, config.min_frames, seconds_per_frame, allowed)


def _background(ctx: StageContext, scene):
    """The evaluation background of the training run (``train/config.json``), else the default."""
    from nerfpipe.pixel_sampler import background_colors
    from nerfpipe.trainer import backgrounds

    config = ctx.path("train") / "config.json"
    mode = json.loads(config.read_text())["trainer"].get("background", "auto") if config.is_file() else "auto"
    return background_colors(backgrounds(mode, scene.has_alpha)[1], 1)[0]


def run(config: RenderConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe.artifacts import write_sequence
    from nerfpipe.orbit import path_cameras
    from nerfpipe.render import render_cameras, resize_cameras

    from nerfpipe.progress import track

    scene, model = ctx.get("scene"), ctx.get("model")
    background = _background(ctx, scene).to(ctx.device)
    start = time.perf_counter()
    sized = lambda cams, s: resize_cameras(cams, *frame_size(cams, config, s)).to(ctx.device)  # noqa: E731
    first = render_cameras(model, sized(path_cameras(scene, config.path, config.frames)[:1], 1.0), config.chunk, background)
    plan = plan_frames(config, time.perf_counter() - start, ctx.time_left())
    cams = sized(path_cameras(scene, config.path, plan.frames), plan.scale)
    reuse = plan.scale == 1.0 and config.path == "orbit"  # an orbit's first frame is the same for any count
    views = first if reuse else []
    for i in track(range(1 if reuse else 0, len(cams)), "render", total=len(cams) - (1 if reuse else 0)):
        views += render_cameras(model, cams[i : i + 1], config.chunk, background)
    w, h = int(cams.width[0]), int(cams.height[0])
    with atomic_path(ctx.path(RENDER_DIR)) as tmp:
        info = write_sequence(views, tmp, config.path, depth=True, fps=config.fps)
        info = {k: v.replace(str(tmp), str(ctx.path(RENDER_DIR))) if isinstance(v, str) else v for k, v in info.items()}
        info.update(frames=len(views), width=w, height=h, budget_plan={"frames": plan.frames, "scale": plan.scale,
                    "estimated_seconds": plan.estimated_seconds, "seconds": time.perf_counter() - start})
        (tmp / f"{config.path}.json").write_text(json.dumps(info, indent=2) + "\n")
    ctx.log.info("render: %d frames of %dx%d -> %s/", len(views), w, h, RENDER_DIR)
    return {"views": views}


def frame_size(cams, config: RenderConfig, extra_scale: float) -> "tuple[int, int]":
    """Width and height of the frames: ``scale``, capped at ``max_size`` on the longer side, times ``extra_scale``."""
    from nerfpipe.render import capped_size

    w, h = capped_size(int(cams.width[0]), int(cams.height[0]), config.scale, config.max_size)
    return max(1, round(w * extra_scale)), max(1, round(h * extra_scale))


STAGE = StageSpec(
    name="render",
    description="orbit (or test-path) video of the trained model, in colour and depth",
    config=RenderConfig,
    run=run,
    requires=("scene", "model"),
    produces=(RENDER_DIR,),
    provides=("views",),
    dependencies=SEQUENCE_DEPENDENCIES,
)
