"""Stage ``render``: novel views of the trained model, an orbit in colour and depth.

The same renderer as ``nerfpipe render`` (:mod:`nerfpipe.outputs.novel_views`: same options, same defaults,
same files): frames at most ``max_size`` pixels on their longer side (phone photographs are not
rendered at full size); under a pipeline time budget the first frame is timed and the stage keeps to
``budget_share`` of the time left: fewer frames (never below ``min_frames``), then smaller ones.
Writes the folder ``render/`` (``orbit.gif``, ``orbit.mp4``, ``depth_orbit.gif``, ``orbit.json``
with the plan actually used; ``test*`` for the test path). The rendered views are also returned in
memory (``views``).
"""

import dataclasses
import json

from nerfpipe.outputs.artifacts import SEQUENCE_DEPENDENCIES
from nerfpipe.outputs.novel_views import PATHS, RENDER_DIR, RenderConfig, frame_size, plan_frames  # noqa: F401 (this stage's API)
from nerfpipe.pipeline.report_items import Shown
from nerfpipe.pipeline.stages import StageContext, StageSpec

SHOWS = (
    Shown("views_info", "table", tuple(f"{RENDER_DIR}/{p}.json" for p in PATHS), "novel views"),
    Shown("colour", "image", tuple(f"{RENDER_DIR}/{p}.gif" for p in PATHS), "orbit (colour)"),
    Shown("depth", "image", tuple(f"{RENDER_DIR}/depth_{p}.gif" for p in PATHS), "orbit (depth)"),
    Shown("video", "video", tuple(f"{RENDER_DIR}/{p}.mp4" for p in PATHS), "orbit video (MP4)"),
)
"""The report's novel-views section: the orbit (or test path) GIFs, its video and its JSON."""

MIN_SECONDS = 3.0
"""Seconds the stages before the render leave it under a time budget (:attr:`StageSpec.min_seconds`). The synthetic
demo's 128-pixel orbit frames take about 0.09 s each on 2 cores: with ``last_share``, 3 s give its orbit about 20 of
them. Before, under ``nerfpipe demo --time-budget 60`` the mesh stage began with 15.7 s left, took 15.5 and left the
orbit 12 frames of 35 pixels (session 70)."""


def run(config: RenderConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe.outputs.novel_views import background, read_path_file, render_sequence, write_render

    camera_file = read_path_file(config)
    scene, model = ctx.get("scene"), ctx.get("model")
    train_config = ctx.path("train") / "config.json"
    train_config = json.loads(train_config.read_text()) if train_config.is_file() else None
    bg = background(config, train_config, scene)
    if ctx.rest_is_light():  # the last stage that computes: most of what is left
        config = dataclasses.replace(config, budget_share=config.last_share)
    views, info = render_sequence(model, scene, config, bg, ctx.device, ctx.time_left(), camera_file)
    write_render(ctx.path(RENDER_DIR), views, config, info, camera_file.fps if camera_file is not None else None)
    ctx.log.info("render: %d frames of %dx%d -> %s/", len(views), info["width"], info["height"], RENDER_DIR)
    return {"views": views}


STAGE = StageSpec(
    name="render",
    description="orbit (or test-path) video of the trained model, in colour and depth",
    config=RenderConfig,
    run=run,
    requires=("scene", "model"),
    produces=(RENDER_DIR,),
    provides=("views",),
    shows=SHOWS,
    dependencies=SEQUENCE_DEPENDENCIES,
    min_seconds=MIN_SECONDS,
)
