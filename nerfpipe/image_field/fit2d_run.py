"""Orchestration of ``nerfpipe fit2d``: configure from a preset, train with a progress bar, write outputs."""

import os
import platform
from dataclasses import asdict
from pathlib import Path

import torch

from nerfpipe.encoders import GridEncoderConfig, PositionalEncoderConfig
from nerfpipe.functional.encoding import nyquist_frequencies
from nerfpipe.image_field import report
from nerfpipe.image_field.images import TargetImage
from nerfpipe.image_field.presets import Fit2dConfig, preset as get_preset
from nerfpipe.image_field.train import FitResult, fit_image

# Command flag -> (config section, field name); "grid"/"pe" only apply to that encoder.
OVERRIDES = {
    "iterations": ("train", "iterations"),
    "lr": ("train", "lr"),
    "lr_final_factor": ("train", "lr_final_factor"),
    "batch_size": ("train", "batch_size"),
    "max_seconds": ("train", "max_seconds"),
    "num_evals": ("train", "num_evals"),
    "seed": ("train", "seed"),
    "hidden_width": ("field", "hidden_width"),
    "num_layers": ("field", "num_layers"),
    "num_frequencies": ("pe", "num_frequencies"),
    "grid_levels": ("grid", "num_levels"),
    "grid_features": ("grid", "features_per_level"),
    "grid_max_resolution": ("grid", "max_resolution"),
    "grid_log2_hashmap_size": ("grid", "log2_hashmap_size"),
}


def console():
    from rich.console import Console

    return Console(stderr=True)


PARAM_BUDGET = 0.5
"""Without an explicit hash size, a grid gets the largest table with params <= this × H·W·3."""


def configure(preset: str, overrides: dict, shape: "tuple[int, ...]") -> Fit2dConfig:
    """The preset with command-line overrides applied.

    A grid's finest level defaults to the image's larger side, and its hash size to the largest
    power of two that keeps the model within ``PARAM_BUDGET`` of the image's value count.
    """
    from nerfpipe.util.errors import NerfpipeError

    cfg = get_preset(preset)
    enc = cfg.field.encoder
    if isinstance(enc, GridEncoderConfig):
        enc.max_resolution = max(shape[:2])
        enc.base_resolution = min(enc.base_resolution, enc.max_resolution)
        _fit_hash_size(cfg, PARAM_BUDGET * shape[0] * shape[1] * 3)
    for flag, value in overrides.items():
        section, name = OVERRIDES[flag]
        kind = {"pe": PositionalEncoderConfig, "grid": GridEncoderConfig}.get(section)
        if kind is not None and not isinstance(enc, kind):
            raise NerfpipeError(f"--{flag.replace('_', '-')} does not apply to the {preset} preset's encoder")
        setattr({"train": cfg.train, "field": cfg.field}.get(section, enc), name, value)
    return cfg


def _fit_hash_size(cfg: Fit2dConfig, budget: float) -> None:
    enc = cfg.field.encoder
    for log2 in range(enc.log2_hashmap_size, 3, -1):
        enc.log2_hashmap_size = log2
        if cfg.field.setup().num_parameters() <= budget:
            return


def train_with_progress(target: TargetImage, cfg: Fit2dConfig, label: str) -> FitResult:
    """:func:`fit_image` with a rich progress bar showing loss and the latest full-image PSNR."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("{task.fields[info]}"))
    with Progress(*columns, console=console(), transient=False) as bar:
        task = bar.add_task(label, total=cfg.train.iterations, info="")

        def on_step(it: int, loss: float, psnr: float) -> None:
            bar.update(task, completed=it, info=f"loss {loss:.5f}  PSNR {psnr:.2f} dB")

        image = torch.from_numpy(target.pixels)
        return fit_image(image, cfg.field, cfg.train, on_step=on_step)


def encoding_note(cfg: Fit2dConfig, shape: "tuple[int, ...]") -> dict:
    """What the encoding did about high frequencies, for metrics.json."""
    enc = cfg.field.encoder
    if not isinstance(enc, PositionalEncoderConfig):
        return {"type": "grid", **asdict(enc), "resolutions": enc.resolutions()}
    nyq = nyquist_frequencies(max(shape[:2]))
    return {
        "type": "positional",
        "num_frequencies": enc.num_frequencies,
        "phases": "exact: (2^k*x) mod 2 reduced in float64, then times pi; L is not capped",
        "nyquist_num_frequencies": nyq,
        "aliased_frequencies": max(0, enc.num_frequencies - nyq),
    }


def metrics(result: FitResult, target: TargetImage, cfg: Fit2dConfig, preset: str) -> dict:
    h, w = target.pixels.shape[:2]
    return {
        "psnr": result.psnr,
        "seconds": result.train_seconds,
        "cpu_seconds": result.train_cpu_seconds,
        "eval_seconds": result.eval_seconds,
        "total_seconds": result.train_seconds + result.eval_seconds,
        "iterations": result.iterations,
        "params": result.params,
        "image_values": h * w * 3,
        "image": {"source": target.source, "height": h, "width": w, "notes": target.notes},
        "preset": preset,
        "encoding": encoding_note(cfg, target.pixels.shape),
        "config": asdict(cfg),
        "curve": {"iteration": result.curve_iterations, "seconds": result.curve_seconds, "psnr": result.curve_psnr},
        "machine": machine(),
    }


def machine() -> dict:
    return {"loadavg": os.getloadavg(), "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
            "torch": torch.__version__, "platform": platform.platform()}


def run_single(target: TargetImage, cfg: Fit2dConfig, preset: str, out: Path) -> FitResult:
    note = encoding_note(cfg, target.pixels.shape)
    if note.get("aliased_frequencies"):
        console().print(f"note: L={note['num_frequencies']} exceeds the {note['nyquist_num_frequencies']} frequencies "
                        f"this image's resolution carries; phases are exact, the extra frequencies alias")
    result = train_with_progress(target, cfg, f"fit2d {preset}")
    write_outputs(result, target, cfg, preset, out)
    console().print(f"PSNR {result.psnr:.2f} dB after {result.iterations} iterations, "
                    f"{result.train_seconds:.1f} s training (+{result.eval_seconds:.1f} s evaluation), "
                    f"{result.params} parameters -> {out}")
    return result


def write_outputs(result: FitResult, target: TargetImage, cfg: Fit2dConfig, preset: str, out: Path) -> None:
    out = Path(out)
    report.save_psnr_plot({preset: result}, out / "psnr.png", title=f"{target.source} ({preset})")
    report.save_progress(result, target.pixels, out / "progress.png")
    report.write_png(out / "final.png", result.final)
    report.write_json(out / "metrics.json", metrics(result, target, cfg, preset))


def run_sweep(target: TargetImage, cfg: Fit2dConfig, ls: "list[int]", lrs: "list[float]", out: Path) -> list:
    """Fit every (L, lr); write one plot of all PSNR curves and a markdown + JSON table."""
    import copy

    curves, rows = {}, []
    for num_frequencies in ls:
        for lr in lrs:
            run = copy.deepcopy(cfg)
            run.field.encoder.num_frequencies, run.train.lr = num_frequencies, lr
            label = f"L={num_frequencies} lr={lr:g}"
            res = train_with_progress(target, run, label)
            curves[label] = res
            rows.append({"L": num_frequencies, "lr": lr, "psnr": res.psnr, "seconds": res.train_seconds,
                         "eval_seconds": res.eval_seconds, "iterations": res.iterations, "params": res.params})
    out = Path(out)
    report.save_psnr_plot(curves, out / "sweep_psnr.png", title=f"{target.source}: sweep of L and lr")
    report.write_text(out / "sweep.md", report.sweep_markdown(rows))
    note = encoding_note(cfg, target.pixels.shape)
    report.write_json(out / "sweep.json", {"rows": rows, "image": target.source, "phases": note["phases"],
                                           "nyquist_num_frequencies": note["nyquist_num_frequencies"],
                                           "machine": machine()})
    console().print(report.sweep_markdown(rows))
    return rows
