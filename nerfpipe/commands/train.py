"""``nerfpipe train``: fit a registered model to a dataset into a run folder.

The options are generated from the config dataclasses (tyro), so none is restated here: every field of
:class:`~nerfpipe.training.trainer.TrainerConfig` is ``--FIELD`` (``--iters``, ``--time-budget``, ...) and every field
of the chosen model's config is ``--model.FIELD``, nested as the config nests (``--model.occupancy.resolution``),
each with its attribute docstring as help. ``--model NAME`` picks a model or a named preset
(:func:`nerfpipe.models.registry.presets`: ``fast``, ``fast-small``, ..., ``vanilla``), whose values are the
defaults ``--help`` shows (``nerfpipe train --model vanilla --help``).
"""

import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro
from tyro.conf import OmitArgPrefixes, Positional

from nerfpipe.training.trainer import TrainerConfig

DEFAULT_MODEL = "fast"


@dataclass
class TrainCommand:
    """Train a radiance field on a dataset into a run folder: metrics.json, psnr.png, progress.png,
    cameras.png, orbit.gif/mp4, depth_orbit.gif. Under --time-budget the whole command keeps to it (training,
    the final evaluation and the videos, sized to fit: metrics.json budget_plan); nerfpipe eval RUN scores
    every view at full size afterwards. Data-parallel on N processes or GPUs: torchrun --nproc-per-node N -m
    nerfpipe train PATH ... (--rays-per-step is the total over the processes; add --max-restarts K to torchrun
    to resume from the last checkpoint after a process dies)."""

    path: Positional[Path]
    """Dataset file or folder (any format nerfpipe reads)."""
    model: str = DEFAULT_MODEL
    """Model or named preset: a registered model (fast, vanilla, ...) or fast-small / fast-medium / fast-large.
    Its values are the defaults of the --model.* options."""
    out: "Path | None" = None
    """Run folder (default: runs/<dataset>-<model>)."""
    trainer: OmitArgPrefixes[TrainerConfig] = field(default_factory=TrainerConfig)
    """How to train."""
    view: bool = False
    """Watch the training in the browser (nerfpipe view's viewer: live render and PSNR curves, at most 4 % of
    the training time; needs nerfpipe[viewer])."""
    view_port: int = 7007
    """Port of the viewer (0: any free one)."""


def command_type(model: str) -> type:
    """:class:`TrainCommand` with a ``--model.*`` group for ``model``'s config, at the preset's values."""
    from nerfpipe.models.registry import get_preset

    preset = get_preset(model)
    config = preset.config
    options = Annotated[type(config), tyro.conf.arg(name="model", help=f"Options of the {preset.model} model (preset {model}).")]
    trainer = OmitArgPrefixes[TrainerConfig]
    return dataclasses.make_dataclass(
        "TrainCommand",
        [("trainer", trainer, field(default_factory=lambda: dataclasses.replace(TrainerConfig(), **preset.trainer))),
         ("model_options", options, field(default_factory=lambda: config))],
        bases=(TrainCommand,),
    )


def model_name(argv: "list[str]") -> str:
    """The value of ``--model`` on a command line (the default without one)."""
    for i, arg in enumerate(argv):
        if arg == "--model" and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith("--model="):
            return arg.split("=", 1)[1]
    return DEFAULT_MODEL


def main(argv: "list[str]") -> int:
    """Parse ``nerfpipe train ARGV`` from the configs and train."""
    cmd = tyro.cli(command_type(model_name(argv)), args=argv, prog="nerfpipe train")
    return train(cmd)


def train(cmd: TrainCommand) -> int:
    """Train as ``cmd`` says; its ``time_budget`` counts from the process's start."""
    from nerfpipe.data_adapters import load
    from nerfpipe.models.registry import get_preset
    from nerfpipe.training import evaluation
    from nerfpipe.training.trainer import Trainer
    from nerfpipe.util.devices import announce
    from nerfpipe.util.errors import require_all
    from nerfpipe.util.paths import check_output_folder

    started = budget_start()
    name = get_preset(cmd.model).model
    cfg = dataclasses.replace(cmd.trainer, device=announce(cmd.trainer.device))
    out = check_output_folder(Path(cmd.out) if cmd.out is not None else Path("runs") / f"{Path(cmd.path).stem}-{cmd.model}")
    require_all(evaluation.dependencies(cfg) + ((("viser", "viewer"),) if cmd.view else ()))  # before the dataset is read
    scene = load(cmd.path)
    from nerfpipe.plugins.triangulate import wants_points

    if wants_points(scene):  # nerfpipe run's sfm stage would triangulate them; this command trains what it is given
        print(f"nerfpipe train: {cmd.path} holds real photographs with poses but no sparse points; without them the field has "
              "only the cameras' box and explains the surroundings with fog. `nerfpipe run` triangulates the points from the "
              "poses first (its sfm stage).", file=sys.stderr)  # fmt: skip
    trainer = Trainer(cfg, scene, name, cmd.model_options, out, started=started)
    from nerfpipe.viewer.training import train_watched

    metrics = train_watched(trainer, cmd.view, cmd.view_port)
    if not trainer.world.writer:  # ranks 1.. of a torchrun group: rank 0 reports
        return 0
    from nerfpipe.training.evaluation import fitted_figure_note

    print(f"{out}: val PSNR {metrics['val_psnr']:.2f} dB{fitted_figure_note(metrics)}, SSIM {metrics['val_ssim']:.3f} on {metrics['val_views']} views, "
          f"{metrics['iterations']} iterations in {metrics['train_seconds']:.0f} s")
    return 0


EXIT_SECONDS = 2.0
"""Kept of a command's time budget for the process's end after its work (printing, torch's shutdown): measured
1.5-2.5 s on this 2-core CPU after `nerfpipe run`."""


def budget_start() -> float:
    """The ``time.monotonic()`` value a command's time budget counts from: its process's start (imports included),
    less :data:`EXIT_SECONDS`, so that the budget holds from the command to its exit."""
    return time.monotonic() - process_age() - EXIT_SECONDS


def process_age() -> float:
    """Wall seconds since this process started (Linux ``/proc``; 0 where it cannot be read)."""
    import os

    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime (clock ticks after boot)
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
