"""Where a steady ``fast`` training step's time goes on its device: milliseconds per step at each batch size and
marching mode, peak memory, and on CUDA the GPU's busy time, kernel launches and top kernels per step (torch's
profiler), so that a host-bound step (the GPU idle between tiny kernels) shows as such.

Run: ``python -m benchmarks.step_profile LEGO --rays 4096 16384 --warm 600 --steps 50`` (``--device cuda`` where there
is one; ``--modes graph fixed rounds`` compares the step replayed as a CUDA graph, CUDA's default, with the same step
launched eagerly and with the rounds of early termination, the CPU's). Prints one JSON line per configuration (and, on
CUDA with ``--tables``, the profiler's tables) and appends them to ``--log`` when given. Session 23's H200 figures in
the README come from it (``benchmarks/cuda_checks.sh`` runs it with the other device checks).
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import itertools
import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

from benchmarks.steps import append_log, model_config
from nerfpipe.training.opcount import gpu_profile


@dataclass
class StepProfileConfig:
    data: tyro.conf.Positional[Path]
    """Dataset (any supported format)."""
    preset: str = "small"
    """Capacity preset of the fast model."""
    options: "tuple[str, ...]" = ()
    """Model options ``NAME=VALUE`` (as ``benchmarks.steps``)."""
    rays: "tuple[int, ...]" = (4096,)
    """Rays per step to profile, each from a fresh model."""
    modes: "tuple[str, ...]" = ("fixed",)
    """Steps: ``graph`` (shapes known on the host, the step a replayed CUDA graph: CUDA's default), ``fixed`` (the same
    steps launched eagerly) and/or ``rounds`` (early termination in rounds, eager: the CPU's default)."""
    warm: int = 600
    """Steps trained before timing (past the warm-up, the tightening and the switch to fine samples)."""
    steps: int = 50
    """Steps timed."""
    profiled_steps: int = 10
    """Steps under the profiler (CUDA only; 0: none)."""
    cache_rays: "tuple[bool, ...]" = ()
    """Each value of ``TrainerConfig.cache_rays`` to profile (default: the trainer's own choice only)."""
    device: str = "auto"
    threads: int = 2
    seed: int = 0
    tables: bool = False
    """Print the profiler's tables of the top kernels and host ops (CUDA)."""
    log: "Path | None" = None
    """Append the JSON lines to this file."""


def main(cfg: StepProfileConfig) -> "list[dict]":
    from nerfpipe.data_adapters import load
    from nerfpipe.training.trainer import Trainer, TrainerConfig
    from nerfpipe.util.devices import announce

    device = announce(cfg.device)
    cuda = torch.device(device).type == "cuda"
    sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
    torch.set_num_threads(cfg.threads)
    scene = load(cfg.data)
    rows = []
    for mode, cache, rays in itertools.product(cfg.modes, cfg.cache_rays or (None,), cfg.rays):
        model = model_config(cfg.preset, cfg.options + (f"fixed_shapes={mode != 'rounds'}",))
        tcfg = TrainerConfig(iters=10**9, rays_per_step=rays, eval_every=0, checkpoint_every=0, video_frames=0,
                             write_outputs=False, device=device, seed=cfg.seed, cuda_graph=mode == "graph",
                             cache_rays=cache)
        trainer = Trainer(tcfg, scene, "fast", model, Path(tempfile.mkdtemp()))
        trainer.model.train()
        if cuda:
            torch.cuda.reset_peak_memory_stats(device)
        w0 = time.perf_counter()
        while trainer.step < cfg.warm:
            trainer.train_step()
        sync()
        w1 = time.perf_counter()
        for _ in range(cfg.steps):
            trainer.train_step()
        sync()
        row = {"mode": mode, "cache_rays": trainer.sampler.cached is not None, "rays": rays, "device": device, "warm_steps": cfg.warm, "warm_s": w1 - w0,
               "ms_per_step": 1000 * (time.perf_counter() - w1) / max(cfg.steps, 1),
               "samples_per_ray": float(trainer.model.stats().get("samples_per_ray", 0.0)), "load": os.getloadavg()[0]}
        if trainer.graph is not None:
            row.update(trainer.graph.stats(), graph_failed=trainer.graph.failed)
        if cuda:
            row["peak_gpu_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
            if cfg.profiled_steps:
                row.update(gpu_profile(trainer.train_step, cfg.profiled_steps, device, cfg.tables))
        print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        rows.append(row)
        del trainer
        if cuda:
            torch.cuda.empty_cache()
    append_log(cfg.log, rows)
    return rows


if __name__ == "__main__":
    main(tyro.cli(StepProfileConfig))
