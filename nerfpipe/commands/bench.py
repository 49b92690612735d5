"""``nerfpipe bench``: speed against error of the NeRF presets on one dataset."""

from pathlib import Path

from tyro.conf import Positional


def bench(
    path: Positional[Path],
    out: Path = Path("bench_out"),
    budgets: "tuple[float, ...]" = (20.0, 60.0, 600.0),
    presets: "tuple[str, ...]" = ("vanilla", "fast-small", "fast-medium", "fast-large"),
    eval_views: int = 0,
    eval_scale: float = 1.0,
    rays_per_step: "int | None" = None,
    cuda_graph: "bool | None" = None,
    cache_rays: "bool | None" = None,
    threads: int = 2,
    clock: str = "wall",
    seed: int = 0,
    device: str = "auto",
) -> int:
    """Train each preset once and score it at every time budget: table.md, table.json, psnr_vs_seconds.png.

    Args:
        path: dataset file or folder (any format data_adapters.load reads).
        out: output folder.
        budgets: training seconds at which each preset is scored (render time excluded).
        presets: vanilla, fast (capacity from the scene), fast-small, fast-medium, fast-large; model options may follow a colon, e.g. ``fast-small:distortion_weight=0.001,tv_weight=1e-5``.
        eval_views: validation views scored at each budget (0: all).
        eval_scale: resolution factor of the validation renders.
        rays_per_step: override every preset's rays per iteration.
        cuda_graph: replay each training step as a CUDA graph (default: on CUDA; False: launch its kernels one by one).
        cache_rays: keep every training pixel's ray on the device (default: on CUDA where they fit; False: generated per batch).
        threads: torch CPU threads.
        clock: wall (seconds) or cpu (process CPU seconds / threads, fairer on a busy machine).
        seed: random seed.
        device: torch device (auto: CUDA when present, else CPU; printed at start).
    """
    from nerfpipe.training.bench import BenchConfig, run
    from nerfpipe.util.devices import announce

    cfg = BenchConfig(budgets=tuple(budgets), presets=tuple(presets), eval_views=eval_views, eval_scale=eval_scale,
                      threads=threads, clock=clock, seed=seed, device=announce(device), rays_per_step=rays_per_step,
                      cuda_graph=cuda_graph, cache_rays=cache_rays)
    run(path, out, cfg)
    return 0
