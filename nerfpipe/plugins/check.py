"""Stage ``check``: the kornia consistency check of the scene's camera conventions; fails fast.

Runs :func:`nerfpipe.data.consistency.check_scene` and writes its figures to ``check.json``. When a
convention is broken (``failures`` not empty) the stage raises, so the pipeline stops before
training on a wrongly converted scene; ``fail = false`` records the failures and goes on.
"""

import json
from dataclasses import dataclass

from nerfpipe.pipeline.report_items import Shown
from nerfpipe.pipeline.stages import StageContext, StageSpec, write_json
from nerfpipe.util.errors import NerfpipeError

CHECK_JSON = "check.json"


@dataclass
class CheckConfig:
    """Options of the ``check`` stage."""

    samples: int = 16
    """Probe pixels per camera."""
    seed: int = 0
    """Seed of the probe pixels."""
    fail: bool = True
    """Stop the pipeline when a convention is broken (otherwise only record it)."""


def run(config: CheckConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe.data.consistency import check_scene

    report = check_scene(ctx.get("scene"), samples=config.samples, seed=config.seed)
    figures = report.as_dict()
    if report.failures and config.fail:
        write_json(ctx.path("check.failed.json"), figures)
        raise NerfpipeError("camera conventions are broken: " + "; ".join(report.failures), ctx.path("check.failed.json"))
    write_json(ctx.path(CHECK_JSON), figures)
    ctx.path("check.failed.json").unlink(missing_ok=True)
    return {"check": figures}


def restore(config: CheckConfig, ctx: StageContext) -> "dict[str, object]":
    return {"check": json.loads(ctx.path(CHECK_JSON).read_text())}


STAGE = StageSpec(
    name="check",
    description="kornia consistency check of the camera conventions (stops the pipeline when broken)",
    config=CheckConfig,
    run=run,
    requires=("scene",),
    produces=(CHECK_JSON,),
    shows=(Shown("check", "table", (CHECK_JSON, "check.failed.json"), "convention check"),),
    provides=("check",),
    restore=restore,
    dependencies=(("kornia", "kornia"),),
)
