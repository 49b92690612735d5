"""``nerfpipe train``: fit a registered model to a dataset into a run folder."""

from pathlib import Path
from typing import Literal

from tyro.conf import Positional


def train(
    path: Positional[Path],
    model: str = "fast",
    out: "Path | None" = None,
    iters: int = 1000,
    time_budget: "float | None" = None,
    clock: Literal["wall", "cpu"] = "wall",
    rays_per_step: int = 4096,
    lr: float = 5e-4,
    num_samples: "int | None" = None,
    eval_every: int = 100,
    checkpoint_every: int = 500,
    eval_scale: float = 1.0,
    final_eval_views: int = 0,
    video_frames: int = 60,
    video_scale: float = 1.0,
    background: str = "auto",
    seed: int = 0,
    device: str = "cpu",
    threads: "int | None" = None,
    resume: bool = False,
    view: bool = False,
    view_port: int = 7007,
) -> int:
    """Train a NeRF on a dataset (any format data_adapters.load reads).

    Data-parallel on N processes or GPUs: ``torchrun --nproc-per-node N -m nerfpipe train PATH ...``
    (``--rays-per-step`` is the total over the processes; add ``--max-restarts K`` to torchrun to
    resume from the last checkpoint after a process dies).

    Args:
        path: dataset file or folder.
        model: registered model name (see the nerfpipe.models entry points): ``fast`` (the CPU
            default: grids + occupancy grid) or ``vanilla`` (the classic MLP; course recipe: 10k rays).
        out: run folder (default: runs/<dataset>-<model>).
        iters: training iterations.
        time_budget: wall-clock seconds for the whole command, final evaluation and videos included: training
            stops with a quarter of it left, and the final evaluation and videos are sized to fit (recorded in
            metrics.json ``budget_plan``; ``nerfpipe eval RUN`` scores every view at full size afterwards).
        clock: what the budget counts: wall seconds, or process CPU seconds / threads (steadier on a busy machine).
        rays_per_step: rays per iteration, drawn across all training images.
        lr: Adam learning rate.
        num_samples: samples per ray (default: the model's).
        eval_every: validate every this many iterations.
        checkpoint_every: write the checkpoint every this many iterations (and at the end).
        eval_scale: resolution factor of validation renders.
        final_eval_views: val views scored at the end (0: all).
        video_frames: frames of orbit.gif/mp4 and depth_orbit.gif (0: none).
        video_scale: resolution factor of the videos.
        background: black | white | random | auto (random for RGBA training, else black).
        seed: random seed (CPU runs are deterministic).
        device: torch device.
        threads: CPU threads for torch (default: torch's choice).
        resume: continue from the run folder's checkpoint.
        view: watch the training in the browser (nerfpipe view's viewer: live render and PSNR curves,
            at most 4 % of the training time; needs nerfpipe[viewer]).
        view_port: port of the viewer (0: any free one).
    """
    import dataclasses

    from nerfpipe.data_adapters import load

    from nerfpipe import evaluation
    from nerfpipe.errors import NerfpipeError, refuse_unless, require_all
    from nerfpipe.models.registry import get_model
    from nerfpipe.paths import check_output_folder
    from nerfpipe.trainer import Trainer, TrainerConfig

    spec = get_model(model)
    model_cfg = spec.config()
    refuse_unless([("num_samples", num_samples is None or num_samples >= 1, "at least 1", num_samples)])
    if num_samples is not None:
        if not any(f.name == "num_samples" for f in dataclasses.fields(model_cfg)):
            raise NerfpipeError(f"--num-samples does not apply to the '{model}' model (it places samples itself)")
        model_cfg = dataclasses.replace(model_cfg, num_samples=num_samples)
    cfg = TrainerConfig(
        iters=iters, wall_budget=time_budget, clock=clock, rays_per_step=rays_per_step, lr=lr, eval_every=eval_every, checkpoint_every=checkpoint_every,
        eval_scale=eval_scale, final_eval_views=final_eval_views, video_frames=video_frames,
        video_scale=video_scale, background=background, seed=seed, device=device, num_threads=threads, resume=resume,
    )
    out = check_output_folder(Path(out) if out is not None else Path("runs") / f"{Path(path).stem}-{model}")
    require_all(evaluation.dependencies(cfg) + ((("viser", "viewer"),) if view else ()))  # before the dataset is read
    scene = load(path)
    if time_budget is not None:  # the budget counts from the process's start: imports and reading the dataset are part of it
        cfg = dataclasses.replace(cfg, wall_budget=max(0.0, time_budget - process_age()))
    trainer = Trainer(cfg, scene, model, model_cfg, out)
    watcher = None
    if view and trainer.world.writer:  # rank 0 of a torchrun group shows it
        from nerfpipe.viewer.training import watch

        watcher = watch(trainer, port=view_port)
    try:
        metrics = trainer.train()
    finally:
        if watcher is not None:
            watcher.viewer.stop()  # the page closes with the training
    if not trainer.world.writer:  # ranks 1.. of a torchrun group: rank 0 reports
        return 0
    print(f"{out}: val PSNR {metrics['val_psnr']:.2f} dB, SSIM {metrics['val_ssim']:.3f}, "
          f"{metrics['iterations']} iterations in {metrics['train_seconds']:.0f} s")
    return 0


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
