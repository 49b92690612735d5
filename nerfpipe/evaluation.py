"""Validation and end-of-run outputs of a :class:`~nerfpipe.trainer.Trainer`.

Validation renders the first views of the val split (the test split, then train, when the
scene has no val images) with :func:`~nerfpipe.render.render_cameras`, scaled by ``eval_scale``,
and scores PSNR and SSIM (kornia.metrics, 11-px Gaussian window) against the ground truth
composited on the evaluation background.
"""

from pathlib import Path

import torch
import torch.nn.functional as F

from nerfpipe.checkpoint import CHECKPOINT
from nerfpipe.errors import require
from nerfpipe.functional.metrics import psnr_from_mse
from nerfpipe.pixel_sampler import background_colors, composite_pixels
from nerfpipe.render import capped_size, render_cameras, resize_cameras, to_uint8
from nerfpipe.runs import write_json


def dependencies(cfg) -> "tuple[tuple[str, str], ...]":
    """The optional modules validation and :func:`finish` will need under the trainer config ``cfg``
    (scores always; figures and videos when written), checked before training starts."""
    from nerfpipe.artifacts import SEQUENCE_DEPENDENCIES
    from nerfpipe.plots import PLOT_DEPENDENCIES

    deps = [("kornia", "kornia")]
    if cfg.write_outputs:
        deps += PLOT_DEPENDENCIES
        deps += SEQUENCE_DEPENDENCIES if cfg.video_frames else ()
    return tuple(deps)


def eval_split(scene) -> str:
    for split in ("val", "test", "train"):
        idx = scene.splits.get(split)
        if idx is not None and len(idx) and all(scene.images.has(int(i)) for i in idx):
            return split
    raise ValueError("scene has no images to validate on")


def ground_truth(scene, index: int, background, size: "tuple[int, int]") -> torch.Tensor:
    """Image ``index`` as float ``[H, W, 3]`` on ``background``, area-resized to ``size`` (w, h)."""
    img = composite_pixels(torch.from_numpy(scene.images.load(index)), background)
    if (img.shape[1], img.shape[0]) != tuple(size):
        img = F.interpolate(img.permute(2, 0, 1)[None], size=(size[1], size[0]), mode="area")[0].permute(1, 2, 0)
    return img


def score(pred: torch.Tensor, gt: torch.Tensor) -> "tuple[float, float]":
    """(PSNR, SSIM) of two ``[H, W, 3]`` images in [0, 1]."""
    kornia = require("kornia", "kornia")
    a, b = pred.permute(2, 0, 1)[None].float(), gt.permute(2, 0, 1)[None].float().to(pred.device)
    return float(kornia.metrics.psnr(a, b, 1.0)), float(kornia.metrics.ssim(a, b, 11).mean())


def fitted_colour_psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """PSNR on the right half of an image after an affine colour map (3x3 + offset) fitted by least squares
    on its left half: how well a held-out view is predicted up to its own exposure and white balance
    (the NeRF-W / nerfbaselines protocol for per-image appearance; the map is fitted on pixels not scored)."""
    w = pred.shape[1] // 2
    x = pred.reshape(pred.shape[0], -1, 3)[:, :w].reshape(-1, 3).double()
    y = gt.to(pred.device).reshape(gt.shape[0], -1, 3)[:, :w].reshape(-1, 3).double()
    a = torch.cat([x, torch.ones_like(x[:, :1])], dim=-1)
    m = torch.linalg.lstsq(a, y).solution  # [4, 3]
    right = pred[:, w:].reshape(-1, 3).double()
    mapped = (torch.cat([right, torch.ones_like(right[:, :1])], dim=-1) @ m).clamp(0, 1)
    return psnr_from_mse(float(((mapped - gt[:, w:].reshape(-1, 3).double().to(mapped.device)) ** 2).mean()))


VAL_COLUMNS = ("step", "train_seconds", "val_psnr", "val_ssim", "views")
"""Fields of one validation in ``history.json`` (the trainer's ``history["val"]`` rows)."""


def validate(trainer, num_views: int) -> "tuple[float, float]":
    """Mean (PSNR, SSIM) over ``num_views`` val views (0: all); logs it and keeps a snapshot of view 0."""
    scene, cfg = trainer.scene, trainer.cfg
    split = eval_split(scene)
    idx = [int(i) for i in scene.splits[split]]
    idx = idx[: num_views] if num_views else idx
    cams = scene.cameras[torch.tensor(idx)]
    sizes = [capped_size(int(w), int(h), cfg.eval_scale, cfg.eval_max_size) for w, h in zip(cams.width, cams.height)]
    bg = background_colors(trainer.eval_bg, 1)[0]
    scores, fitted = [], []
    for i, (w, h) in zip(range(len(idx)), sizes):
        view = render_cameras(trainer.model, resize_cameras(cams[i : i + 1], w, h).to(cfg.device), cfg.chunk, bg)[0]
        gt = ground_truth(scene, idx[i], bg, (w, h))
        scores.append(score(view.rgb, gt))
        fitted.append(fitted_colour_psnr(view.rgb, gt))
        if i == 0:
            save_snapshot(trainer.out / "progress" / f"step_{trainer.step:07d}.png", to_uint8(view.rgb))
    psnr = sum(s[0] for s in scores) / len(scores)
    ssim = sum(s[1] for s in scores) / len(scores)
    trainer.history["val"].append([trainer.step, trainer.train_seconds, psnr, ssim, len(idx)])
    trainer.last_fitted_psnr = sum(fitted) / len(fitted)
    return psnr, ssim


def save_snapshot(path: Path, image) -> None:
    import imageio.v3 as iio

    from nerfpipe.atomic import atomic_write

    atomic_write(path, lambda p: iio.imwrite(p, image, extension=".png"))


def finish(trainer) -> dict:
    """Final validation, metrics.json, plots and videos; returns the metrics."""
    from nerfpipe import plots
    from nerfpipe.artifacts import write_sequence
    from nerfpipe.orbit import path_cameras

    cfg, out = trainer.cfg, trainer.out
    psnr, ssim = validate(trainer, cfg.final_eval_views)
    stats = trainer.model.stats()
    metrics = {
        "val_psnr": psnr,
        "val_ssim": ssim,
        "val_psnr_colour_fitted": trainer.last_fitted_psnr,
        "val_views": cfg.final_eval_views or len(trainer.scene.splits[eval_split(trainer.scene)]),
        "eval_scale": cfg.eval_scale,
        "eval_max_size": cfg.eval_max_size,
        "train_seconds": trainer.train_seconds,
        "iterations": trainer.step,
        "seconds_per_iteration": trainer.train_seconds / max(trainer.step, 1),
        "rays_per_step": cfg.rays_per_step,
        "processes": trainer.world.size,
        "resumed_at": trainer.history.get("resumed_at", []),
        "model": trainer.model_name,
        **stats,
    }
    checkpoint = out / CHECKPOINT
    if checkpoint.is_file():  # model, optimizer moments and random streams, as stored
        metrics["checkpoint_mb"] = checkpoint.stat().st_size / 2**20
    if cfg.write_outputs:
        plots.plot_psnr(trainer.history, out / "psnr.png")
        plots.plot_progress(sorted((out / "progress").glob("step_*.png")), out / "progress.png")
        spr = trainer.model.stats().get("samples_per_ray", 64)
        plots.plot_cameras(trainer.scene, trainer.sampler, out / "cameras.png", num_samples=int(spr))
    if cfg.video_frames and cfg.write_outputs:
        cams = path_cameras(trainer.scene, "test", cfg.video_frames)
        w, h = (max(1, round(int(v) * cfg.video_scale)) for v in (cams.width[0], cams.height[0]))
        bg = background_colors(trainer.eval_bg, 1)[0]
        views = render_cameras(trainer.model, resize_cameras(cams, w, h).to(cfg.device), cfg.chunk, bg)
        metrics["video"] = write_sequence(views, out, "orbit", depth=True)
        metrics["depth_colormap"] = metrics["video"]["depth_mapping"]
    write_json(out / "metrics.json", metrics)
    write_json(out / "history.json", {"val": [dict(zip(VAL_COLUMNS, row)) for row in trainer.history["val"]]})
    return metrics
