"""``nerfpipe fit2d``: fit a neural field to one 2D image (course recipe or fast grid), or sweep L × lr."""

from pathlib import Path
from typing import Literal, Optional

import tyro

from nerfpipe.util.errors import NerfpipeError


def fit2d(
    image: tyro.conf.Positional[Optional[Path]] = None,
    out: Path = Path("fit2d_out"),
    preset: Literal["course", "fast"] = "course",
    iterations: Optional[int] = None,
    lr: Optional[float] = None,
    lr_final_factor: Optional[float] = None,
    batch_size: Optional[int] = None,
    num_frequencies: Optional[int] = None,
    hidden_width: Optional[int] = None,
    num_layers: Optional[int] = None,
    grid_levels: Optional[int] = None,
    grid_features: Optional[int] = None,
    grid_max_resolution: Optional[int] = None,
    grid_log2_hashmap_size: Optional[int] = None,
    max_seconds: Optional[float] = None,
    num_evals: Optional[int] = None,
    seed: int = 0,
    sweep: bool = False,
    sweep_l: "list[int]" = [4, 10, 20, 35],
    sweep_lr: "list[float]" = [1e-3, 1e-2],
    max_pixels: int = 2048 * 2048,
    threads: int = 2,
) -> int:
    """Fit a coordinate network (x, y) -> RGB to an image and write plots and metrics to OUT.

    Args:
        image: image file; default: scikit-image's astronaut photograph.
        out: output folder (psnr.png, progress.png, final.png, metrics.json; sweep.* with --sweep).
        preset: ``course`` (positional encoding L=10, 4×256 MLP, 10k pixels/step) or ``fast``
            (multiresolution grid + tiny MLP, 8k pixels/step). Flags below override the preset.
        iterations: Adam steps.
        lr: Adam learning rate.
        lr_final_factor: decay the learning rate exponentially to lr × this by the end.
        batch_size: random pixels per step; 0 = every pixel.
        num_frequencies: L of the positional encoding (phases are exact at any L).
        hidden_width: MLP hidden width.
        num_layers: number of linear layers.
        grid_levels: grid encoder levels.
        grid_features: grid features per level.
        grid_max_resolution: finest grid resolution (default: the image's larger side).
        grid_log2_hashmap_size: levels above 2^this vertices are hashed.
        max_seconds: stop after this much training time.
        num_evals: full-image PSNR evaluations over the run.
        seed: random seed.
        sweep: fit every (L, lr) of --sweep-l × --sweep-lr with the positional encoding.
        sweep_l: values of L for --sweep.
        sweep_lr: learning rates for --sweep.
        max_pixels: larger images are downscaled (with a warning) to at most this many pixels.
        threads: torch CPU threads.
    """
    from nerfpipe.image_field import fit2d_run
    from nerfpipe.image_field.images import load_target

    from nerfpipe.outputs.plots import PLOT_DEPENDENCIES
    from nerfpipe.util.errors import refuse_unless, require_all
    from nerfpipe.util.paths import check_output_folder
    from nerfpipe.util.scoped import torch_threads

    refuse_unless((
        ("iterations", iterations is None or iterations >= 1, "at least 1", iterations),
        ("lr", lr is None or lr > 0, "positive", lr), ("lr_final_factor", lr_final_factor is None or lr_final_factor > 0, "positive", lr_final_factor),
        ("batch_size", batch_size is None or batch_size >= 0, "0 (every pixel) or more", batch_size),
        ("max_seconds", max_seconds is None or max_seconds > 0, "positive", max_seconds),
        ("num_evals", num_evals is None or num_evals >= 1, "at least 1", num_evals),
        ("max_pixels", max_pixels >= 4, "at least 4", max_pixels), ("threads", threads >= 1, "at least 1", threads),
        ("sweep_l", not sweep or (sweep_l and all(v >= 0 for v in sweep_l)), "frequencies 0 or more", sweep_l),
        ("sweep_lr", not sweep or (sweep_lr and all(v > 0 for v in sweep_lr)), "positive rates", sweep_lr),
        ("num_frequencies", num_frequencies is None or 0 <= num_frequencies <= 64, "between 0 and 64", num_frequencies),
        ("hidden_width", hidden_width is None or 1 <= hidden_width <= 4096, "between 1 and 4096", hidden_width),
        ("num_layers", num_layers is None or 1 <= num_layers <= 64, "between 1 and 64", num_layers),
        ("grid_levels", grid_levels is None or 1 <= grid_levels <= 32, "between 1 and 32", grid_levels),
        ("grid_features", grid_features is None or 1 <= grid_features <= 64, "between 1 and 64", grid_features),
        ("grid_max_resolution", grid_max_resolution is None or grid_max_resolution >= 2, "at least 2", grid_max_resolution),
        ("grid_log2_hashmap_size", grid_log2_hashmap_size is None or 4 <= grid_log2_hashmap_size <= 30, "between 4 and 30", grid_log2_hashmap_size),
    ))  # fmt: skip
    check_output_folder(out)
    require_all(PLOT_DEPENDENCIES)  # the figures are written after the fit
    with torch_threads(threads):  # handed back after (a caller's own count stays)
        target = load_target(image, max_pixels)
        for note in target.notes:
            fit2d_run.console().print(f"[yellow]nerfpipe: warning:[/] {target.source}: {note}")
        overrides = {k: v for k, v in locals().items() if k in fit2d_run.OVERRIDES and v is not None}
        cfg = fit2d_run.configure(preset, overrides, target.pixels.shape)
        if sweep:
            if preset != "course":
                raise NerfpipeError("--sweep varies L of the positional encoding: use it with --preset course")
            fit2d_run.run_sweep(target, cfg, sweep_l, sweep_lr, out)
        else:
            fit2d_run.run_single(target, cfg, preset, out)
    return 0


__all__ = ["fit2d"]
