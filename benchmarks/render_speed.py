"""Render and training-step speed of a trained ``fast`` run, with and without early ray termination
and two-level empty-space skipping.

Run: ``python -m benchmarks.render_speed RUN_DIR`` (e.g. ``/work/runs/lego300/train``).
For each mode (``reference``: the full density pass over every marched sample; ``early-noskip``: the
density pass in rounds that stop at opaque rays; ``early``: rounds, and each ray marched only over the
span a coarser occupancy grid allows) it measures

* seconds per frame of :func:`~nerfpipe.outputs.render.render_cameras` on the first val views, at each thread count,
* samples the density-only pass evaluated per ray, and samples kept (shaded) per ray,
* PSNR of the val views (all of them by default),
* seconds per training step (the trainer's ``train_step`` on ``rays_per_step`` rays, from the checkpoint),
  at each thread count (the model keeps training: consecutive steps, not the same step repeated).

The machine may be shared: the 1-minute load average is recorded next to every timing, with the
process CPU seconds. Prints a table and writes ``render_speed.json`` to ``--out`` when given.
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import dataclasses
import json
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro


@dataclass
class RenderSpeedConfig:
    """What to measure."""

    run_dir: tyro.conf.Positional[Path]
    """A run folder of the ``fast`` model (config.json + checkpoint.safetensors)."""
    modes: "tuple[str, ...]" = ("reference", "early-noskip", "early")
    """``reference`` (the full density pass, one-level marching), ``early-noskip`` (rounds with early
    termination, one-level marching) and/or ``early`` (rounds, two-level empty-space skipping)."""
    threads: "tuple[int, ...]" = (1, 2)
    """torch thread counts for the frame timings."""
    frames: int = 2
    """Val views timed per thread count (the mean is reported)."""
    psnr_views: int = 0
    """Val views scored for PSNR (0: all)."""
    train_steps: int = 6
    """Training steps timed (the median is reported; the first is a warm-up)."""
    rays_per_step: int = 4096
    """Rays per training step."""
    out: "Path | None" = None
    """Folder for render_speed.json (none: print only)."""


class _Counter:
    """Counts the points a density function is called on."""

    def __init__(self, fn) -> None:
        self.fn, self.points = fn, 0

    def __call__(self, points):
        self.points += points.shape[0]
        return self.fn(points)


MODES = {"reference": (False, 0), "early-noskip": (True, 0), "early": (True, None)}
"""mode: (early ray termination, occupancy ``skip_factor``: 0 = one-level marching, None = the run's own)."""


def set_mode(model, mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}: choose from {', '.join(MODES)}")
    early, skip = MODES[mode]
    occ = model.grid.cfg
    if not hasattr(model, "_run_skip_factor"):
        model._run_skip_factor = getattr(occ, "skip_factor", 0)
    if hasattr(model.cfg, "early_termination"):
        model.cfg.early_termination = early
    elif early:
        raise ValueError("this nerfpipe has no early termination: use --modes reference")
    if hasattr(occ, "skip_factor"):
        occ.skip_factor = model._run_skip_factor if skip is None else skip


def val_cameras(scene, n: int):
    from nerfpipe.training.evaluation import eval_split

    idx = [int(i) for i in scene.splits[eval_split(scene)]]
    idx = idx[:n] if n else idx
    return idx, scene.cameras[torch.tensor(idx)]


def timed(fn):
    load = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu, load


def frame_times(model, scene, cfg: RenderSpeedConfig) -> dict:
    from nerfpipe.outputs.render import render_cameras

    _, cams = val_cameras(scene, cfg.frames)
    rows = {}
    for threads in cfg.threads:
        torch.set_num_threads(threads)
        render_cameras(model, cams[:1])  # warm-up
        _, wall, cpu, load = timed(lambda: render_cameras(model, cams))
        rows[str(threads)] = dict(seconds_per_frame=wall / len(cams), cpu_seconds_per_frame=cpu / len(cams), load=load)
    return rows


def quality_and_samples(model, scene, run_cfg: dict, cfg: RenderSpeedConfig) -> "tuple[dict, list]":
    from nerfpipe.outputs.novel_views import RenderConfig, background
    from nerfpipe.outputs.render import render_cameras
    from nerfpipe.training.evaluation import ground_truth, score

    idx, cams = val_cameras(scene, cfg.psnr_views)
    bg = background(RenderConfig(), run_cfg, scene)  # the run's evaluation background
    counter = _Counter(model.field.density)
    model.field.density = counter
    kept = []
    original = model.get_outputs

    def counting(rays, background):
        out = original(rays, background)
        kept.append(out.num_samples)
        return out

    model.get_outputs = counting
    try:
        views = render_cameras(model, cams, 4096, bg)
    finally:
        del model.field.density, model.get_outputs
    rays = sum(int(w) * int(h) for w, h in zip(cams.width, cams.height))
    psnrs = [score(v.rgb, ground_truth(scene, i, bg, (v.rgb.shape[1], v.rgb.shape[0])))[0] for v, i in zip(views, idx)]
    return dict(psnr=sum(psnrs) / len(psnrs), views=len(idx), density_samples_per_ray=counter.points / rays,
                kept_samples_per_ray=sum(kept) / rays), views


def train_step_time(run_dir: Path, run_cfg: dict, mode: str, cfg: RenderSpeedConfig) -> dict:
    from nerfpipe.data_adapters import load

    from nerfpipe.models.registry import get_model
    from nerfpipe.training.checkpoint import CHECKPOINT, load_checkpoint
    from nerfpipe.training.runs import from_dict
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    scene = load(Path(run_cfg["data"]))
    model_cfg = from_dict(get_model(run_cfg["model"]).config, run_cfg["model_config"])
    trainer_cfg = dataclasses.replace(from_dict(TrainerConfig, run_cfg["trainer"]), rays_per_step=cfg.rays_per_step, num_threads=None)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(trainer_cfg, scene, run_cfg["model"], model_cfg, Path(tmp))
    trainer.load_state(load_checkpoint(run_dir / CHECKPOINT))
    set_mode(trainer.model, mode)
    trainer.model.train()
    out = {}
    for threads in cfg.threads:
        torch.set_num_threads(threads)
        rows = [timed(trainer.train_step)[1:] for _ in range(cfg.train_steps)]
        rows = rows[1:] or rows
        out[str(threads)] = dict(seconds_per_step=statistics.median(r[0] for r in rows),
                                 cpu_seconds_per_step=statistics.median(r[1] for r in rows), load=max(r[2] for r in rows), steps=len(rows))
    return out


def measure(cfg: RenderSpeedConfig) -> dict:
    from nerfpipe.training.runs import load_run, read_config

    run_cfg = read_config(cfg.run_dir)
    scene, model, _ = load_run(cfg.run_dir)
    results, images = {}, {}
    for mode in cfg.modes:
        set_mode(model, mode)
        res = {"frames": frame_times(model, scene, cfg)}
        torch.set_num_threads(max(cfg.threads))
        res["quality"], images[mode] = quality_and_samples(model, scene, run_cfg, cfg)
        res["train_step"] = train_step_time(cfg.run_dir, run_cfg, mode, cfg)
        results[mode] = res
    if len(images) >= 2:
        first, *others = images.values()
        results["max_abs_rgb_difference"] = max(float((x.rgb - y.rgb).abs().max()) for b in others for x, y in zip(first, b))
    return results


def main(cfg: RenderSpeedConfig) -> dict:
    results = measure(cfg)
    print(json.dumps(results, indent=1))
    if cfg.out is not None:
        from nerfpipe.training.runs import write_json

        cfg.out.mkdir(parents=True, exist_ok=True)
        write_json(cfg.out / "render_speed.json", {"run_dir": str(cfg.run_dir), **results})
    return results


if __name__ == "__main__":
    main(tyro.cli(RenderSpeedConfig))
