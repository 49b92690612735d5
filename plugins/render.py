"""Stage ``render``: novel views of the trained model, an orbit in colour and depth.

Uses :func:`nerfpipe.orbit.path_cameras`, :func:`nerfpipe.render.render_cameras` and
:func:`nerfpipe.artifacts.write_sequence`, the same functions as ``nerfpipe render``, and writes the
folder ``render/``: ``orbit.gif``, ``orbit.mp4``, ``depth_orbit.gif`` and ``orbit.json`` (frame
count, size, depth colour mapping); ``test*`` instead of ``orbit*`` for the test path. The
rendered views are also returned in memory (``views``).
"""

import json
from dataclasses import dataclass
from typing import Literal

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

    scene, model = ctx.get("scene"), ctx.get("model")
    cams = path_cameras(scene, config.path, config.frames)
    w, h = (max(1, round(int(v) * config.scale)) for v in (cams.width[0], cams.height[0]))
    cams = resize_cameras(cams, w, h).to(ctx.device)
    views = render_cameras(model, cams, config.chunk, _background(ctx, scene).to(ctx.device))
    with atomic_path(ctx.path(RENDER_DIR)) as tmp:
        info = write_sequence(views, tmp, config.path, depth=True, fps=config.fps)
        info = {k: v.replace(str(tmp), str(ctx.path(RENDER_DIR))) if isinstance(v, str) else v for k, v in info.items()}
        (tmp / f"{config.path}.json").write_text(json.dumps(info, indent=2) + "\n")
    ctx.log.info("render: %d frames of %dx%d -> %s/", len(views), w, h, RENDER_DIR)
    return {"views": views}


STAGE = StageSpec(
    name="render",
    description="orbit (or test-path) video of the trained model, in colour and depth",
    config=RenderConfig,
    run=run,
    requires=("scene", "model"),
    produces=(RENDER_DIR,),
    provides=("views",),
)
