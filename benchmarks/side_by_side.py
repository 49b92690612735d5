"""Several ``fast`` model variants trained side by side in one process, steps interleaved, so that the
machine's load (which varies 2-3x from hour to hour on shared machines) weighs on each alike: seconds
per step as ratios, val PSNR at equal steps (deterministic on CPU), model MB and the finest voxel.

Run: ``python -m benchmarks.side_by_side LEGO --variants "dense:preset='small'" "compact:preset='compact'" --marks 300 3000``.
A variant is ``NAME:OPTIONS`` with options ``KEY=VALUE`` separated by spaces (as ``benchmarks.steps``;
``preset=...`` sets the capacity preset, default ``auto``; ``train.KEY=VALUE`` a ``TrainerConfig`` field, e.g.
``train.train_max_size=480``). Prints one JSON line per variant and mark,
and appends them to ``--log`` when given.
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import ast
import json
import os
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import tyro

from benchmarks.steps import append_log, model_config, trainer_config
from nerfpipe.data.orbit import path_cameras


@dataclass
class SideBySideConfig:
    data: tyro.conf.Positional[Path]
    """Dataset (any supported format)."""
    variants: "tuple[str, ...]" = ("dense:preset='small'", "compact:preset='compact'")
    """``NAME:OPTIONS`` per variant (options ``KEY=VALUE`` separated by spaces)."""
    marks: "tuple[int, ...]" = (300,)
    """Steps at which to validate."""
    chunk: int = 25
    """Steps one variant trains before the next takes its turn."""
    eval_views: int = 10
    eval_max_size: "int | None" = None
    """Longer side of validation renders at most (None: full resolution)."""
    eval_supersample: int = 2
    """Rays per pixel side at most in validation renders smaller than their photographs (``TrainerConfig.eval_supersample``;
    1: one ray per pixel, as the figures before session 15)."""
    points: "Path | None" = None
    """Sparse points for an input that lacks them (a run's ``sfm/points``, as the pipeline's ``load`` stage adds them)."""
    track_rays: int = 512
    threads: int = 2
    rays_per_step: int = 4096
    seed: int = 0
    log: "Path | None" = None
    """Append the JSON lines to this file."""
    pictures: "Path | None" = None
    """After the last mark, write this PNG: two rows (colour, depth) per variant of four orbit views (around the scene box at the
    training cameras' distance and elevation), longer side ``eval_max_size``, to see fog that PSNR hides."""
    average_every_mark: bool = False
    """Also score the parameter average at every mark, not only after the last (on a copy of the model, its occupancy
    grid refreshed from the average as a run's end does: training goes on undisturbed), to see where more steps stop
    paying for a run that ends there."""


def parse_variant(text: str) -> "tuple[str, str, tuple[str, ...], dict]":
    """``"name:preset='small' levels=(8,16) train.rays_per_step=8192"`` -> ``("name", "small", ("levels=(8,16)",), {"rays_per_step": 8192})``."""
    name, _, rest = text.partition(":")
    options, preset, trainer = [], "auto", {}
    for item in rest.split():
        key, _, value = item.partition("=")
        if key == "preset":
            preset = ast.literal_eval(value)
        elif key.startswith("train."):
            trainer[key.split(".", 1)[1]] = ast.literal_eval(value)
        else:
            options.append(item)
    return name, preset, tuple(options), trainer


def main(cfg: SideBySideConfig) -> "list[dict]":
    from nerfpipe.data_adapters import load

    from nerfpipe.training import evaluation
    from nerfpipe.training.trainer import Trainer

    torch.set_num_threads(cfg.threads)
    scene = load(cfg.data)
    if cfg.points is not None:
        from nerfpipe.data_adapters.colmap import with_points

        scene = with_points(scene, cfg.points)
    tcfg = trainer_config(cfg)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        runs = []
        for i, text in enumerate(cfg.variants):
            name, preset, options, overrides = parse_variant(text)
            trainer = Trainer(replace(tcfg, **overrides), scene, "fast", model_config(preset, options), Path(tmp) / str(i))
            trainer.model.train()
            runs.append(dict(name=name, trainer=trainer, wall=0.0))
        for mark in cfg.marks:
            while any(r["trainer"].step < mark for r in runs):
                for run in runs:
                    trainer, stop = run["trainer"], min(mark, run["trainer"].step + cfg.chunk)
                    t0 = time.perf_counter()
                    while trainer.step < stop:
                        trainer.train_step()
                    run["wall"] += time.perf_counter() - t0
            for run in runs:
                trainer = run["trainer"]
                psnr, _ = evaluation.validate(trainer, cfg.eval_views, final=True)
                stats = trainer.model.stats()
                fitted = trainer.last_appearance_fitted_psnr
                rows.append(dict(name=run["name"], step=mark, wall=round(run["wall"], 2), s_per_step=round(run["wall"] / mark, 4),
                                 psnr=round(psnr, 3), colour_fitted=round(trainer.last_fitted_psnr, 3),
                                 appearance_fitted=None if fitted is None else round(fitted, 3), model_mb=round(stats["model_mb"], 2), finest_voxel=round(stats.get("finest_voxel", 0.0), 5),
                                 samples_per_ray=round(stats["samples_per_ray"], 2),
                                 occupied=round(stats.get("occupied_fraction", 0.0), 4), load=round(os.getloadavg()[0], 2)))
                if cfg.average_every_mark and mark != cfg.marks[-1] and trainer.average is not None:
                    averaged = averaged_psnr(trainer, cfg.eval_views)
                    if averaged is not None:
                        rows[-1]["psnr_averaged"] = round(averaged, 3)
                if mark == cfg.marks[-1] and trainer.average is not None and trainer.average.apply():
                    trainer.model.parameters_replaced()  # as the run ends: scored with the averaged parameters
                    rows[-1]["psnr_averaged"] = round(evaluation.validate(trainer, cfg.eval_views, final=True)[0], 3)
                print(json.dumps(rows[-1]), flush=True)
        if cfg.pictures is not None:
            write_orbit_strips(cfg.pictures, scene, [r["trainer"] for r in runs], cfg.eval_max_size)
    append_log(cfg.log, rows)
    return rows


def averaged_psnr(trainer, views: int) -> "float | None":
    """Validation PSNR of the parameter average so far, scored on a copy of the model (the run goes on unchanged);
    None before the average starts."""
    import copy

    from nerfpipe.training import evaluation

    average = trainer.average
    if average.values is None:
        return None
    model = trainer.model
    twin = copy.deepcopy(model)
    with torch.no_grad():
        params = dict(twin.named_parameters())
        for name, value in average.values.items():
            params[name].copy_(value)
    twin.parameters_replaced()
    trainer.model = twin
    try:
        return evaluation.validate(trainer, views, final=True)[0]
    finally:
        trainer.model = model
        model.train()


def write_orbit_strips(path: Path, scene, trainers: list, max_size: "int | None", views: int = 4) -> None:
    """Two rows per trainer of ``views`` orbit views (:func:`nerfpipe.data.orbit.path_cameras`) as a PNG: colour, then
    depth coloured as the render stage's depth orbit (one range for all variants: pits and fog compare across rows)."""
    import imageio.v3 as iio
    import numpy as np

    from nerfpipe.data.background import background_colors
    from nerfpipe.outputs.colormap import colorize_depth, depth_range
    from nerfpipe.outputs.render import render_cameras, to_uint8
    from nerfpipe.util.atomic import write_bytes

    cams = path_cameras(scene, "orbit", views)
    if max_size:
        cams = cams.capped(max_size)
    renders = []
    for trainer in trainers:
        device = next(trainer.model.parameters()).device
        renders.append(render_cameras(trainer.model, cams.to(device), background=background_colors(trainer.eval_bg, 1)[0]))
    lo, hi = depth_range([v.depth for r in renders for v in r], [v.acc for r in renders for v in r])
    rows = []
    for rendered in renders:
        rows.append(np.concatenate([to_uint8(v.rgb) for v in rendered], axis=1))
        rows.append(np.concatenate([colorize_depth(v.depth, v.acc, lo, hi) for v in rendered], axis=1))
    write_bytes(path, iio.imwrite("<bytes>", np.concatenate(rows, axis=0), extension=".png"))


if __name__ == "__main__":
    main(tyro.cli(SideBySideConfig))
