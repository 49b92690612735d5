"""Quality and seconds per training step of the ``fast`` model for model-option overrides: the A/B tool
behind the default choices (PSNR at equal step counts is deterministic on CPU; seconds are not).

Run: ``python -m benchmarks.steps LEGO --options coarse_to_fine_every=32 mlp_lr=0.01 --marks 100 200 300``.
Prints one JSON line per mark (step, cumulative training seconds, wall and CPU/threads, val PSNR over
``--eval-views`` views, mean samples per ray, ATen ops and host syncs per step over the steps before the mark, load) and appends them to ``--log`` when given.
``occupancy.NAME=VALUE`` sets an option of the occupancy grid, ``behind.NAME=VALUE`` one of the field behind the box.
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import ast
import contextlib
import dataclasses
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro


@dataclass
class StepsConfig:
    data: tyro.conf.Positional[Path]
    """Dataset (any supported format)."""
    options: "tuple[str, ...]" = ()
    """Model options ``NAME=VALUE`` (Python literals), e.g. ``step_ratio=1.0`` or ``occupancy.update_every=32``."""
    preset: str = "small"
    """Capacity preset of the fast model."""
    marks: "tuple[int, ...]" = (100, 200, 300)
    """Steps at which to validate."""
    eval_views: int = 10
    eval_max_size: "int | None" = 400
    """Longer side of validation renders at most (as ``nerfpipe run``'s train stage)."""
    eval_supersample: int = 2
    """Rays per pixel side at most in validation renders smaller than their photographs (``TrainerConfig.eval_supersample``;
    1: one ray per pixel, as the figures before session 15)."""
    track_rays: int = 512
    """Rays per step through sparse points (scenes with tracks)."""
    threads: int = 2
    rays_per_step: int = 4096
    seed: int = 0
    counted_steps: int = 16
    """Steps before each mark whose ATen ops and host syncs are counted (:mod:`nerfpipe.training.opcount`; timed with the rest)."""
    name: str = ""
    """Label of the JSON lines (default: the options)."""
    log: "Path | None" = None
    """Append the JSON lines to this file."""


def model_config(preset: str, options: "tuple[str, ...]"):
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.util.configs import from_dict

    values: dict = {"preset": preset}
    for key, value in (o.split("=", 1) for o in options):  # a nested config's option as ``behind.levels=(8,)``
        *tables, name = key.split(".")
        table = values
        for t in tables:
            table = table.setdefault(t, {})
        table[name] = ast.literal_eval(value)
    return from_dict(FastConfig, values, "the variant's options")


def main(cfg: StepsConfig) -> "list[dict]":
    from nerfpipe.data_adapters import load

    from nerfpipe.training import evaluation

    from nerfpipe.training.opcount import DispatchCounter
    from nerfpipe.training.trainer import Trainer
    from nerfpipe.util import runtime

    torch.set_num_threads(cfg.threads)
    scene = load(cfg.data)
    tcfg = trainer_config(cfg)
    rows, wall, cpu = [], 0.0, 0.0
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(tcfg, scene, "fast", model_config(cfg.preset, cfg.options), Path(tmp))
        trainer.model.train()
        for mark in cfg.marks:
            counter, counted = DispatchCounter(), 0
            while trainer.step < mark:
                counting = trainer.step >= mark - cfg.counted_steps
                counted += counting
                w0, c0 = time.perf_counter(), time.process_time()
                with counter if counting else contextlib.nullcontext():
                    trainer.train_step()
                wall, cpu = wall + time.perf_counter() - w0, cpu + time.process_time() - c0
            psnr, _ = evaluation.validate(trainer, cfg.eval_views)
            counted = max(counted, 1)
            rows.append(dict(name=cfg.name or " ".join(cfg.options) or "default", step=mark, wall=round(wall, 3),
                             cpu=round(cpu / cfg.threads, 3), psnr=round(psnr, 3), samples_per_ray=round(trainer.model.stats()["samples_per_ray"], 2),
                             aten_ops_per_step=round(counter.ops / counted, 1), host_syncs_per_step=round(counter.syncs / counted, 2),
                             load=round(os.getloadavg()[0], 2), omp_wait=runtime.OMP_WAIT))
            print(json.dumps(rows[-1]), flush=True)
    append_log(cfg.log, rows)
    return rows


def trainer_config(cfg):
    """The trainer of an A/B run: no validation, video or checkpoint of its own (``cfg``: ``StepsConfig``-like)."""
    from nerfpipe.training.trainer import TrainerConfig

    return TrainerConfig(iters=10**9, eval_every=0, video_frames=0, checkpoint_every=0, rays_per_step=cfg.rays_per_step, seed=cfg.seed,
                         eval_max_size=cfg.eval_max_size, track_rays=cfg.track_rays, eval_supersample=cfg.eval_supersample)


def append_log(path: "Path | None", rows: "list[dict]") -> None:
    """Append the JSON lines of ``rows`` to ``path`` (None: nothing)."""
    if path is not None:
        with open(path, "a") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)


if __name__ == "__main__":
    main(tyro.cli(StepsConfig))
