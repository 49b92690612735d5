"""Stage ``train``: fit a registered model (``nerfpipe.models`` group) with :class:`nerfpipe.training.trainer.Trainer`.

The trainer's run folder is ``RUN_DIR/train`` (``config.json``, ``checkpoint.safetensors``, ``metrics.json``,
``psnr.png``, ``progress.png``, ``cameras.png``, ``held_out.png``: the final evaluation's views, photograph, render and
error map). Videos are the ``render`` stage's job, so the
trainer writes none here.

Resume: when the stage runs again (interrupted, or with more ``iters`` or a new time budget) and
``train/checkpoint.safetensors`` holds the same model, model options and training options (``iters``
and the budgets aside), training continues from that checkpoint; otherwise it starts afresh.

Under torchrun every process runs this stage (it is *collective*, :mod:`nerfpipe.training.distributed`): rank 0
decides resume and budget and sends them, and alone clears or writes ``train/``.

Time budget: the trainer's ``train_budget`` (training seconds, validation excluded) is the smaller
of ``trainer.train_budget`` and ``budget_share`` of what is left of the pipeline's budget.
"""

import json
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

from nerfpipe.outputs.colormap import ERROR_MAX
from nerfpipe.pipeline.report_items import Shown
from nerfpipe.pipeline.stages import StageContext, StageSpec
from nerfpipe.training import checkpoint, evaluation
from nerfpipe.training.trainer import RESOLVED_DEFAULTS, TrainerConfig
from nerfpipe.util.configs import JsonTable
from nerfpipe.util.errors import NerfpipeError, refuse_unless

TRAIN_DIR = "train"
CHECKPOINT = f"{TRAIN_DIR}/{checkpoint.CHECKPOINT}"
METRICS = f"{TRAIN_DIR}/metrics.json"
_RESUMABLE_CHANGES = ("iters", "train_budget", "time_budget", "resume", "device", "video_frames")
"""Trainer options that may differ between a checkpoint and the run that continues it."""


@dataclass
class TrainStageConfig:
    """Options of the ``train`` stage."""

    model: str = "fast"
    """Registered model name (``nerfpipe.models`` entry points); ``fast`` in pipelines, ``vanilla`` for reference."""
    model_options: JsonTable = field(default_factory=dict)
    """Overrides of the model's config, nested as the config is (e.g. ``{"field": {"width": 64}}``; JSON on the
    command line)."""
    trainer: TrainerConfig = field(default_factory=lambda: TrainerConfig(rays_per_step=None, video_frames=0, eval_max_size=400))
    """Training options (``device`` comes from the pipeline; videos are the render stage's). Defaults as
    ``nerfpipe train`` and the bench: rays per step by the device (4,096 on the CPU, 16,384 on CUDA); validation renders at most 400 pixels on the
    longer side, so a budgeted run is not spent scoring phone photos."""
    budget_share: float = 0.6
    """Share of the pipeline's remaining time budget given to training (the rest: evaluation, later stages)."""
    view: bool = False
    """Watch the training in the browser (:mod:`nerfpipe.viewer.training`; needs ``nerfpipe[viewer]``)."""
    view_port: int = 7007
    """Port of that viewer (0: any free one)."""

    def __post_init__(self) -> None:
        """The model name and options are checked when the pipeline is built, not after the stages before this one ran."""
        model_config(self.model, self.model_options)
        refuse_unless([("budget_share", 0 < self.budget_share <= 1, "in (0, 1]", self.budget_share)])


def model_config(name: str, options: dict):
    """The registered model's config with ``options`` merged in (unknown keys are errors)."""
    from nerfpipe.models.registry import get_model
    from nerfpipe.util.configs import from_dict

    spec = get_model(name)
    if not isinstance(options, dict):
        raise NerfpipeError(f"model_options must be a table of the '{name}' model's options, not {type(options).__name__}")
    return from_dict(spec.config, options, f"model_options of the '{name}' model")


def _trainer_config(config: TrainStageConfig, ctx: StageContext) -> TrainerConfig:
    """The trainer's options under the pipeline's budget: ``budget_share`` of the time left for training, and an
    end-to-end ``time_budget`` that leaves the validations their share of it and sizes the final evaluation to
    what follows (a fog box renders slowly: unbounded, its final scoring ran 33 s past a 180 s budget)."""
    from nerfpipe.training.evaluation import FINAL_SHARE, VALIDATION_SHARE

    budget, end, left = config.trainer.train_budget, config.trainer.time_budget, ctx.time_left()
    if left is not None:
        share = config.budget_share * left
        budget = share if budget is None else min(budget, share)
        whole = share * (1 + VALIDATION_SHARE) / (1 - FINAL_SHARE)
        end = whole if end is None else min(end, whole)
    return replace(config.trainer, train_budget=budget, time_budget=end, device=ctx.device, video_frames=0)


def _resumable(out: Path, model: str, model_cfg, trainer_cfg: TrainerConfig) -> bool:
    """Whether ``out`` holds a checkpoint of this very training (up to the resumable options)."""
    from nerfpipe.util.configs import to_dict

    if not (out / checkpoint.CHECKPOINT).is_file() or not (out / "config.json").is_file():
        return False
    old = json.loads((out / "config.json").read_text())
    new = to_dict(trainer_cfg)
    old_trainer = {**old.get("trainer", {}), **{k: None for k in RESOLVED_DEFAULTS if new.get(k) is None}}  # resolved at run time
    strip = lambda d: {k: v for k, v in d.items() if k not in _RESUMABLE_CHANGES}  # noqa: E731
    same_trainer = strip(old_trainer) == strip(new)
    return old.get("model") == model and old.get("model_config") == to_dict(model_cfg) and same_trainer


def run(config: TrainStageConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe.training import distributed
    from nerfpipe.training.trainer import Trainer

    world = distributed.world(ctx.device)
    scene = ctx.get("scene")
    model_cfg = model_config(config.model, config.model_options)
    trainer_cfg = _trainer_config(config, ctx)
    out = ctx.path(TRAIN_DIR)
    resume = _resumable(out, config.model, model_cfg, trainer_cfg) if world.writer else None
    if world.active:  # rank 0's choices (its clock gives the budget): every rank must stop at the same step
        trainer_cfg, resume = distributed.broadcast_object((trainer_cfg, resume))
    if not resume and out.exists() and world.writer:
        shutil.rmtree(out)
    ctx.log.info("train: %s, %s", config.model, "resuming from the checkpoint" if resume else "from scratch")
    trainer = Trainer(replace(trainer_cfg, resume=resume), scene, config.model, model_cfg, out)
    spread = getattr(trainer.model, "exposure_spread", 0.0)
    if spread:
        ctx.log.info("train: the photos' exposure spreads %.2f (log gain std); per-image colour corrections %s", spread,
                     "on" if getattr(trainer.model, "appearance", None) is not None else "off")
    from nerfpipe.viewer.training import train_watched

    metrics = train_watched(trainer, config.view, config.view_port)
    if metrics.get("held_out_fall_db", 0.0) >= evaluation.HELD_OUT_FALL_DB:
        ctx.log.warning("train: the held-out view's PSNR fell %.1f dB from its best while training: the photographs' poses "
                        "probably disagree (a fold in the reconstruction; see sfm/sfm.json and mesh/mesh_views.png)",
                        metrics["held_out_fall_db"])
    return {"model": trainer.model.eval(), "metrics": metrics}


def restore(config: TrainStageConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe.training.runs import load_run

    _, model, _ = load_run(ctx.path(TRAIN_DIR), ctx.device)
    return {"model": model, "metrics": json.loads(ctx.path(METRICS).read_text())}


STAGE = StageSpec(
    name="train",
    description="train a registered NeRF model (vanilla, fast...) with checkpoints and resume",
    config=TrainStageConfig,
    run=run,
    requires=("scene",),
    produces=(CHECKPOINT, METRICS),
    provides=("model", "metrics"),
    restore=restore,
    dependencies=evaluation.dependencies(TrainStageConfig().trainer),
    collective=True,
    shows=tuple(Shown(role, kind, (f"{TRAIN_DIR}/{name}",), title) for role, kind, name, title in (
        ("metrics", "table", "metrics.json", "training metrics"), ("history", "table", "history.json", "validation history"),
        ("psnr_curves", "image", "psnr.png", "PSNR curves"), ("progress", "image", "progress.png", "validation view during training"),
        ("cameras", "image", "cameras.png", "training cameras, rays and samples"),
        ("held_out", "image", "held_out.png", f"held-out views: photograph, render, error (turbo, 0 to {ERROR_MAX} RMS)"), ("train_colour", "image", "orbit.gif", "orbit (colour)"),
        ("train_depth", "image", "depth_orbit.gif", "orbit (depth)"), ("train_video", "video", "orbit.mp4", "orbit video (MP4)"))),
)
