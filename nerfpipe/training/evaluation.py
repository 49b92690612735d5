"""Validation and end-of-run outputs of a :class:`~nerfpipe.training.trainer.Trainer`.

Validation renders the first views of the val split (the test split, then train, when the
scene has no val images) with :func:`~nerfpipe.outputs.render.render_cameras`, scaled by ``eval_scale``,
and scores PSNR and SSIM (kornia.metrics, 11-px Gaussian window) against the ground truth
composited on the evaluation background.
"""

import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch
import torch.nn.functional as F

from nerfpipe.data.background import background_colors, composite_pixels
from nerfpipe.data.rays import camera_rays
from nerfpipe.functional.metrics import psnr_from_mse
from nerfpipe.outputs.colormap import error_strip, stack_rows
from nerfpipe.outputs.render import FramePlan, RenderedView, capped_size, plan_frames, render_cameras, render_rays, resize_cameras, shrink, supersample_factor, to_uint8
from nerfpipe.training.checkpoint import CHECKPOINT
from nerfpipe.training.runs import write_json
from nerfpipe.util.errors import require
from nerfpipe.util.typing import Float, Tensor


def dependencies(cfg) -> "tuple[tuple[str, str], ...]":
    """The optional modules validation and :func:`finish` will need under the trainer config ``cfg``
    (scores always; figures and videos when written), checked before training starts."""
    from nerfpipe.outputs.artifacts import SEQUENCE_DEPENDENCIES
    from nerfpipe.outputs.plots import PLOT_DEPENDENCIES

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


SSIM_WINDOW = 11
"""Side of SSIM's Gaussian window in pixels (scored views are never made smaller than this)."""


def score(pred: torch.Tensor, gt: torch.Tensor) -> "tuple[float, float]":
    """(PSNR, SSIM) of two ``[H, W, 3]`` images in [0, 1]."""
    kornia = require("kornia", "kornia")
    a, b = pred.permute(2, 0, 1)[None].float(), gt.permute(2, 0, 1)[None].float().to(pred.device)
    return float(kornia.metrics.psnr(a, b, 1.0)), float(kornia.metrics.ssim(a, b, SSIM_WINDOW).mean())


def fitted_colour_psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """PSNR on the right half of an image after an affine colour map (3x3 + offset) fitted by least squares
    on its left half: how well a held-out view is predicted up to its own exposure and white balance
    (the NeRF-W / nerfbaselines protocol for per-image appearance; the map is fitted on pixels not scored)."""
    w = pred.shape[1] // 2
    mapped = colour_fitted(pred, gt)[:, w:].reshape(-1, 3)
    return psnr_from_mse(float(((mapped - gt[:, w:].reshape(-1, 3).double().to(mapped.device)) ** 2).mean()))


def fitted_figure_note(metrics: dict) -> str:
    """For a summary line after ``val PSNR X dB``: the figure that sees through each held-out photo's own exposure, where
    the model has per-image colour corrections (the appearance fitted with image codes, else the affine colour map); ""
    without them."""
    if metrics.get("val_psnr_appearance_fitted") is not None:
        return f" ({metrics['val_psnr_appearance_fitted']:.2f} dB on right halves, appearance fitted on left halves)"
    if metrics.get("appearance") and metrics.get("val_psnr_colour_fitted") is not None:
        return f" ({metrics['val_psnr_colour_fitted']:.2f} dB on right halves, an affine colour map fitted on left halves)"
    return ""


def colour_fitted(pred: Float[Tensor, "h w 3"], gt: Float[Tensor, "h w 3"]) -> Float[Tensor, "h w 3"]:
    """The whole image ``pred`` through the affine colour map fitted by least squares on its left half (float64,
    clamped to [0, 1]): what :func:`fitted_colour_psnr` scores on the right half."""
    w = pred.shape[1] // 2
    x = pred.reshape(pred.shape[0], -1, 3)[:, :w].reshape(-1, 3)
    y = gt.to(pred.device).reshape(gt.shape[0], -1, 3)[:, :w].reshape(-1, 3)
    return affine_colour(pred.reshape(-1, 3), fit_affine_colour(x, y)).clamp(0, 1).view(*pred.shape[:2], 3)


def fit_affine_colour(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The affine colour map (3x3 and an offset, ``[4, 3]`` on homogeneous colours, float64) that takes colours ``x``
    ``[N, 3]`` closest to ``y`` in least squares (:func:`affine_colour` applies it)."""
    return torch.linalg.lstsq(_homogeneous(x), y.double().to(x.device)).solution


def affine_colour(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """Colours ``x`` ``[N, 3]`` through the map ``m`` of :func:`fit_affine_colour` (float64)."""
    return _homogeneous(x) @ m


def _homogeneous(x: torch.Tensor) -> torch.Tensor:
    return torch.cat([x.double(), torch.ones_like(x[:, :1], dtype=torch.float64)], dim=-1)


VAL_COLUMNS = ("step", "train_seconds", "val_psnr", "val_ssim", "views")
"""Fields of one validation in ``history.json`` (the trainer's ``history["val"]`` rows)."""

FINAL_SHARE = 0.25
"""Under a wall-clock budget (:attr:`~nerfpipe.training.trainer.TrainerConfig.time_budget`), the share of it kept for
what follows training: the final evaluation, the figures and the videos."""
EVAL_SHARE = 0.5
"""Of the time left when training stops, the share the final evaluation may take (the figures come next,
then the videos get what is left)."""
MIN_FINAL_VIEWS = 4
"""Under a budget, the final evaluation scores at least this many views (smaller ones when they do not fit)."""
MIN_VIDEO_FRAMES = 12
"""Under a budget, the videos keep at least this many frames (smaller ones when they do not fit; none when even
that does not fit)."""
VALIDATION_SHARE = 0.05
"""Under a wall-clock budget, intermediate validations are skipped while they have taken more than this share
of the time so far (and there is none at step 0, where an untrained model renders slowest). 0.1 until session 69,
when the intermediate validations rendered 2 x 2 rays per pixel where the final one does: on colmap_mouse under
``nerfpipe run --time-budget 300`` four of them took about 18 s of the 183 s training window (157 s of steps);
at one ray per pixel and 0.05, ten took about 11 s of 185 (168 s of steps)."""
INTERMEDIATE_SUPERSAMPLE = 1
"""Rays per pixel side of the intermediate validations (the final one renders ``TrainerConfig.eval_supersample``):
they show progress, time a rendered ray for the final evaluation's plan and watch the held-out figure fall
(:func:`held_out_fall`, which compares them with each other only); 2 x 2 rays made each four times dearer."""
FINAL_MAX_SHARE = 0.4
"""Under a wall-clock budget, the share of it kept for what follows training at most: where the final evaluation of
every view (:func:`final_eval_need`) needs more than :data:`FINAL_SHARE` and at most this, training leaves it that;
where it needs more, no share would score every view, and :data:`FINAL_SHARE` is left (fewer or smaller views)."""
FINAL_MARGIN = 1.3
"""Safety factor on the final evaluation's estimated time (:func:`final_eval_need`)."""
AVERAGED_RENDER_FACTOR = 1.3
"""Where the parameters are averaged, the final evaluation renders their average, its occupancy grid refreshed in full,
whose rays may cost more than those of the latest validation during training: the final 2 x 2 rays took 1.52x what the
latest validation's time per ray predicted on colmap_mouse before the sparsity loss (65.8 s against 43.2; ``nerfpipe
run colmap_mouse --time-budget 300``), 0.84x with it (38.1 against 45.5), 0.94x and 1.12x on 23 of its photos (through
the sfm stage, and posed) at 180 s. :func:`final_eval_need` reserves for the supersampled final evaluation this many
times more, :data:`FINAL_MARGIN` over it. 1.2 (session 35) gave training the time: colmap_mouse 1,800 iterations and
**24.69 dB** against 905 and 24.78, its orbit 26 frames instead of 58; the posed 23 photos 979 iterations and 23.42 dB
against 861 and 23.57: past their plateaus, more steps bought nothing there, and the later stages lost the time. Since
then they pay (session 49, the parameter average scored at every mark, one ray per pixel, 400 px, 7 views: 24.58 / 24.79
/ 24.87 / 24.89 / 24.89 dB after 600 / 900 / 1,200 / 1,500 / 1,800 steps), and 2.0 left two runs in session 48 70 and 90
s of the train stage unused (final evaluations of 29.0 and 29.7 s where 31.0 and 37.2 were predicted, 0.93x and 0.80x):
at 1.3 (2.1x the prediction with :data:`FINAL_MARGIN` and the share of the time left) colmap_mouse trained 1,537
steps to **25.04 dB** (its orbit 47 frames of 60 instead of all)."""
PROBE = 2
"""Under a budget, the trained model's rendering speed is timed on the first view at this fraction of its side (the
latest validation's time per ray is no guide: photos_sacre_coeur's gave its final 2 x 2 rays 24.4 s, which took
84.8 s with the appearance fit, and the run ended 15 s past its budget). The probe's fixed per-call costs make its
time an overestimate: at a quarter of the side colmap_mouse's final 2 x 2 rays were estimated at 65.4 s (1.14 times
over), more than the 64 s allowed, though training had stopped early to leave them that time; one ray per pixel took
14 s and the rest went unused. At half the side the probe renders four times as many rays (about 0.4 s more there),
and with the planned supersampling (``k x k`` rays per pixel) as many as a view at one ray per pixel: rays cost less in
larger renders (a trained colmap_mouse model, 2 threads: 13.3 us per ray at half the side, 11.7 with 2 x 2 rays there,
12.6 for the whole view's 2 x 2). colmap_mouse's final 2 x 2 rays (``nerfpipe run --time-budget 300``): estimated at
55.4 s from one ray per pixel, they took 38.1 (1.45x over); from 2 x 2 rays after an untimed warm-up, 36.4 against 32.7
(1.11x; session 35). Its 23 posed photos at 180 s: 15.9 against 17.8 s before, 17.0 against 19.5 after."""
PROBE_WARMUP = 8
"""Side of the render before the probe, untimed: the first render after training pays one-time costs."""
ENCODE_SHARE = 0.2
"""Of the video's time, the share kept for encoding the GIFs and the MP4."""


def eval_views(scene, num_views: int = 0) -> "list[int]":
    """Indices of the first ``num_views`` views of the evaluation split (0: all)."""
    idx = [int(i) for i in scene.splits[eval_split(scene)]]
    return idx[:num_views] if num_views else idx


def appearance_fitted_view(model, rays, gt: torch.Tensor, background, chunk: "int | None", whole: bool = True) -> "tuple[float, torch.Tensor] | None":
    """A held-out view rendered with the appearance the model fits to its left half
    (:meth:`~nerfpipe.models.base.Model.fitted_appearance`: NeRF-W's protocol for held-out views of photo
    collections): the PSNR of its right half and the render, ``[H, W, 3]`` with ``whole`` (the left half included, for
    the pictures), else its right half alone; None for models without per-image appearance. ``rays``: the view's
    ``[H, W]`` rays."""
    height, width = rays.shape
    half = width // 2
    gt = gt.to(rays.origins)
    background = background.to(gt)
    shown = rays if whole else rays[:, half:]
    with model.fitted_appearance(rays[:, :half].reshape(-1), gt[:, :half].reshape(-1, 3), background) as fitted:
        if not fitted:
            return None
        with torch.no_grad():
            rgb = render_rays(model, shown.reshape(-1), background, chunk)[0].clamp(0, 1).view(*shown.shape, 3)
    return psnr_from_mse(float(((rgb[:, rgb.shape[1] - (width - half):] - gt[:, half:]) ** 2).mean())), rgb


def score_views(model, scene, idx: "list[int]", sizes: "list[tuple[int, int]]", background, device: str, chunk: "int | None", keep_first: bool = False,
                deadline: "float | None" = None, lpips=None, progress: bool = False, fit_appearance: bool = False, supersample: int = 1,
                on_view: "Callable[[int, RenderedView, torch.Tensor], None] | None" = None) -> dict:
    """Render views ``idx`` at ``sizes`` (w, h) and score them against the ground truth on ``background``;
    with a ``deadline`` (``time.monotonic()``), no view is begun after it but the first.

    Returns the per-view ``psnr``, ``ssim``, ``fitted_psnr`` lists, the render ``seconds`` and ``pixels``
    (the rays rendered, for the time one ray takes), with ``keep_first`` the first rendered view as ``first``, and with an
    ``lpips`` scorer (:func:`lpips_scorer`) the per-view ``lpips``; ``progress`` shows a bar on stderr. With
    ``fit_appearance``, models with per-image appearance also give ``appearance_fitted_psnr``
    (:func:`appearance_fitted_view`; its time is not in ``seconds``). ``supersample``: rays per pixel side at most
    for views smaller than their photographs (:func:`view_supersample`). ``on_view(view index, render, ground truth)``
    is called with each scored view (e.g. to write its error map).
    """
    out = {"psnr": [], "ssim": [], "fitted_psnr": [], "appearance_fitted_psnr": [], "lpips": [], "seconds": 0.0, "pixels": 0, "first": None}
    cams = scene.cameras[torch.tensor(idx, dtype=torch.long)]
    views = enumerate(sizes)
    if progress:
        from nerfpipe.util.progress import track

        views = track(views, "eval", total=len(sizes))
    for i, (w, h) in views:
        if i and deadline is not None and time.monotonic() > deadline:
            break
        start = time.perf_counter()
        cam = resize_cameras(cams[i : i + 1], w, h).to(device)
        k = view_supersample(cams, i, (w, h), supersample)
        view = render_cameras(model, cam, chunk, background, k)[0]
        out["seconds"] += time.perf_counter() - start
        out["pixels"] += w * h * k**2
        gt = ground_truth(scene, idx[i], background, (w, h))
        p, s = score(view.rgb, gt)
        out["psnr"].append(p)
        out["ssim"].append(s)
        out["fitted_psnr"].append(fitted_colour_psnr(view.rgb, gt))
        fitted = appearance_fitted_view(model, camera_rays(cam, 0), gt, background, chunk, whole=on_view is not None) if fit_appearance else None
        if fitted is not None:
            out["appearance_fitted_psnr"].append(fitted[0])
        if on_view is not None:  # what the view is scored on: for photo collections, with its fitted appearance;
            shown = view  # with colour corrections alone, through the affine map the colour-fitted figure scores
            if fitted is not None:
                shown = replace(view, rgb=fitted[1])
            elif getattr(model, "appearance", None) is not None:
                shown = replace(view, rgb=colour_fitted(view.rgb, gt).to(view.rgb))
            on_view(idx[i], shown, gt)
        if lpips is not None:
            with torch.no_grad():
                out["lpips"].append(lpips(view.rgb, gt))
        if keep_first and i == 0:
            out["first"] = view
    return out


def view_supersample(cams, i: int, size: "tuple[int, int]", limit: int) -> int:
    """Rays per pixel side for camera ``i`` of ``cams`` rendered at ``size`` (w, h) and scored against its photograph's
    area mean (:func:`~nerfpipe.outputs.render.supersample_factor`, at most ``limit``)."""
    return supersample_factor(max(size), max(int(cams.width[i]), int(cams.height[i])), limit)


def eval_sizes(scene, idx: "list[int]", scale: float, max_size: "int | None") -> "list[tuple[int, int]]":
    """(w, h) of views ``idx`` at ``scale``, the longer side capped at ``max_size``."""
    cams = scene.cameras[torch.tensor(idx, dtype=torch.long)]
    return [capped_size(int(w), int(h), scale, max_size) for w, h in zip(cams.width, cams.height)]


def _eval_sizes(scene, idx: "list[int]", cfg, scale: float = 1.0) -> "list[tuple[int, int]]":
    return eval_sizes(scene, idx, cfg.eval_scale * scale, cfg.eval_max_size)


def lpips_scorer(device: str):
    """``(scorer, None)`` with LPIPS (AlexNet) when the lpips package and torchvision's AlexNet weights are on
    this machine, else ``(None, why not)``: evaluation never downloads anything."""
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        return None, "the lpips package is not installed"
    weights = Path(torch.hub.get_dir()) / "checkpoints"
    if not any(weights.glob("alexnet-*.pth")):
        return None, f"AlexNet weights are not in {weights}"
    import lpips

    net = lpips.LPIPS(net="alex", verbose=False).to(device).eval()
    return lambda a, b: float(net(a.permute(2, 0, 1)[None] * 2 - 1, b.permute(2, 0, 1)[None].to(a) * 2 - 1)), None


HELD_OUT_PICTURE = "held_out.png"
"""The final evaluation's views, one per row: photograph | render | per-pixel error
(:func:`~nerfpipe.outputs.colormap.error_strip`, one scale for every view)."""
HELD_OUT_ROWS = 8
"""Views in :data:`HELD_OUT_PICTURE` at most (the first the final evaluation scores)."""
HELD_OUT_WIDTH = 1200
"""Width of a row of :data:`HELD_OUT_PICTURE` at most: larger views are shown averaged over square blocks of pixels
(the error map of the averaged render: a 13-view 800² evaluation would otherwise be a PNG of tens of MB)."""


def validate(trainer, num_views: int, scale: float = 1.0, deadline: "float | None" = None, final: bool = False,
             supersample: "int | None" = None) -> "tuple[float, float]":
    """Mean (PSNR, SSIM) over ``num_views`` val views (0: all) at ``scale`` of the configured size (those begun
    before ``deadline``), with ``supersample`` rays per pixel side at most (None: ``eval_supersample``); logs it, keeps
    a snapshot of view 0 and the time one rendered ray took (``trainer.seconds_per_pixel``). The ``final`` one also fits
    per-image appearance to the left halves (``trainer.last_appearance_fitted_psnr``, None without) and writes
    :data:`HELD_OUT_PICTURE`: each scored view's photograph, render and error map, one view per row."""
    scene, cfg = trainer.scene, trainer.cfg
    idx = eval_views(scene, num_views)
    bg = background_colors(trainer.eval_bg, 1)[0]
    strips: "list" = []

    def keep_strip(i, view, gt) -> None:  # a few views, each at most HELD_OUT_WIDTH wide: a picture, not the data
        if len(strips) < HELD_OUT_ROWS:
            k = max(1, -(-3 * view.rgb.shape[1] // HELD_OUT_WIDTH))
            small = [x if k == 1 else F.avg_pool2d(x.permute(2, 0, 1)[None].float(), k, ceil_mode=True)[0].permute(1, 2, 0)
                     for x in (view.rgb, gt.to(view.rgb.device))]
            strips.append(error_strip(*small))

    on_view = keep_strip if final and cfg.write_outputs else None
    scores = score_views(trainer.model, scene, idx, _eval_sizes(scene, idx, cfg, scale), bg, cfg.device, cfg.chunk, keep_first=True,
                         deadline=deadline, fit_appearance=final,
                         supersample=cfg.eval_supersample if supersample is None else supersample, on_view=on_view)
    if strips:
        save_snapshot(trainer.out / HELD_OUT_PICTURE, stack_rows(strips))
    fitted = scores["appearance_fitted_psnr"]
    trainer.last_appearance_fitted_psnr = _mean(fitted) if fitted else None
    idx = idx[: len(scores["psnr"])]
    save_snapshot(trainer.out / "progress" / f"step_{trainer.step:07d}.png", to_uint8(scores["first"].rgb))
    psnr, ssim = _mean(scores["psnr"]), _mean(scores["ssim"])
    trainer.history["val"].append([trainer.step, trainer.train_seconds, psnr, ssim, len(idx)])
    trainer.last_fitted_psnr = _mean(scores["fitted_psnr"])
    trainer.seconds_per_pixel = scores["seconds"] / max(scores["pixels"], 1)
    trainer.validation_seconds += scores["seconds"]
    if not final and trainer.cfg.time_budget is not None and trainer.appearance_fit_seconds is None:
        time_appearance_fit(trainer)
    return psnr, ssim


def time_appearance_fit(trainer) -> None:
    """Time the final evaluation's appearance fit of one held-out view (:func:`appearance_fit_seconds`, on the left half
    of the first one at the configured size) into ``trainer.appearance_fit_seconds`` (0 for models without per-image
    appearance), counted as validation time, so that the training window leaves each view its fit
    (:func:`final_eval_need`). The intermediate validations fit nothing: ``nerfpipe run photos_sacre_coeur
    --time-budget 300`` left its final evaluation the time of two renders, and it scored one of its 2 views (12.79 dB
    appearance fitted; both views 14.97)."""
    if not trainer.model.appearance_fit_steps:
        trainer.appearance_fit_seconds = 0.0
        return
    start = time.perf_counter()
    cfg, scene = trainer.cfg, trainer.scene
    idx = eval_views(scene, 1)
    (w, h), = _eval_sizes(scene, idx, cfg)
    cam = resize_cameras(scene.cameras[torch.tensor(idx, dtype=torch.long)], w, h).to(cfg.device)
    trainer.appearance_fit_seconds = _left_half_fit_seconds(trainer, cam, idx[0], background_colors(trainer.eval_bg, 1)[0])
    trainer.validation_seconds += time.perf_counter() - start


def _left_half_fit_seconds(trainer, cam, index: int, bg) -> float:
    """:func:`appearance_fit_seconds` on the left half of scene view ``index`` seen by the one camera ``cam`` (at its size)."""
    w, h = int(cam.width[0]), int(cam.height[0])
    half = max(1, w // 2)
    rays, gt = camera_rays(cam, 0)[:, :half], ground_truth(trainer.scene, index, bg, (w, h))[:, :half]
    return appearance_fit_seconds(trainer.model, rays.reshape(-1), gt.reshape(-1, 3), bg)


def validation_due(trainer) -> bool:
    """Whether an intermediate validation fits (always, without a wall-clock budget; see :data:`VALIDATION_SHARE`)."""
    if trainer.cfg.time_budget is None:
        return True
    return trainer.step > 0 and trainer.validation_seconds <= VALIDATION_SHARE * trainer.wall_elapsed()


def _mean(values: "list[float]") -> float:
    return sum(values) / len(values)


def save_snapshot(path: Path, image) -> None:
    import imageio.v3 as iio

    from nerfpipe.util.atomic import atomic_write

    atomic_write(path, lambda p: iio.imwrite(p, image, extension=".png"))


def _final_eval(trainer, plan: dict) -> "tuple[float, float, int]":
    """The final validation: every view (or ``final_eval_views``) at the configured size, or under a
    wall-clock budget what fits :data:`EVAL_SHARE` of the time left (recorded in ``plan``)."""
    cfg, scene = trainer.cfg, trainer.scene
    idx = eval_views(scene, cfg.final_eval_views)
    if trainer.wall_left() is None:
        return (*validate(trainer, cfg.final_eval_views, final=True), len(idx))
    start = time.perf_counter()
    allowed = _final_share(cfg) * trainer.wall_left()
    (w, h), = _eval_sizes(scene, idx[:1], cfg)
    pw, ph = max(1, w // PROBE), max(1, h // PROBE)  # the trained model's speed (per-view costs make it an overestimate)
    first = scene.cameras[torch.tensor(idx[:1], dtype=torch.long)]
    probe = resize_cameras(first, pw, ph).to(cfg.device)
    bg = background_colors(trainer.eval_bg, 1)[0]
    most = view_supersample(first, 0, (w, h), cfg.eval_supersample)
    render_cameras(trainer.model, resize_cameras(first, PROBE_WARMUP, PROBE_WARMUP).to(cfg.device), cfg.chunk, bg)  # first-call costs
    probe_start = time.perf_counter()
    render_cameras(trainer.model, probe, cfg.chunk, bg, supersample=most)  # the rays of the planned supersampling, as many as a view's
    render = (time.perf_counter() - probe_start) / (pw * ph * most**2) * w * h  # one ray per pixel
    fit_seconds = picture = 0.0  # each view's appearance fit, where the model fits one: its time is the view's too
    if trainer.model.appearance_fit_steps:
        fit_seconds = _left_half_fit_seconds(trainer, probe, idx[0], bg)
        picture = render if fit_seconds else 0.0  # and the view rendered with it (whole for the picture), one ray per pixel
    fixed = FINAL_MARGIN * fit_seconds  # the fit's steps on a fixed set of rays do not shrink with the view
    supersample, scaled = 1, render + picture  # the most rays per pixel with which every view fits at full size, else one
    for k in range(most, 1, -1):
        if len(idx) * (render * k**2 + picture + fixed) <= allowed - (time.perf_counter() - start):
            supersample, scaled = k, render * k**2 + picture
            break
    min_scale = min(1.0, max(0.25, SSIM_WINDOW / min(w, h)))
    fit = _fit(len(idx), min(MIN_FINAL_VIEWS, len(idx)), scaled, allowed - (time.perf_counter() - start), at_least=1, min_scale=min_scale,
               fixed=fixed)
    psnr, ssim = validate(trainer, fit.frames, fit.scale, deadline=time.monotonic() + allowed - (time.perf_counter() - start), final=True,
                          supersample=supersample)
    views = trainer.history["val"][-1][-1]
    (w, h), = _eval_sizes(scene, idx[:1], cfg, fit.scale)
    plan["final_eval"] = {"views": views, "planned": fit.frames, "of": len(idx), "scale": fit.scale, "size": [w, h], "supersample": supersample,
                          "appearance_fit_seconds": fit_seconds + picture, "estimated_seconds": fit.estimated_seconds, "seconds": time.perf_counter() - start}
    return psnr, ssim, views


FIT_PROBE_STEPS = (32, 160)
"""Steps of the two short appearance fits whose times give a whole fit's (:func:`appearance_fit_seconds`)."""
FIT_WARMUP_STEPS = 8
"""Steps of an untimed fit before them: without it, a Sacre Coeur checkpoint's fit on the probe (half the side) was
estimated at 2.4 s and took 9.7 s (its other view's 1.17x, full-size views' 0.92-0.98x)."""


def appearance_fit_seconds(model, rays, rgb, background, clock=time.perf_counter) -> float:
    """Seconds the final evaluation's appearance fit of one view takes (:meth:`~nerfpipe.models.base.Model.fitted_appearance`;
    0 for models without per-image appearance), from two short fits to ``rgb`` along ``rays``: their difference gives
    a step's time, the shorter one what a fit costs besides its steps (shorter fits are too noisy: on
    photos_sacre_coeur 8 and 24 steps gave 0.8 s for a fit that takes 9–14 s; 32 and 160 steps on the half-size probe
    10.6–11.6 s, in 4.2–4.6 s). Before it was planned for, photos_sacre_coeur's final evaluation (2 views, 1,024 steps
    each) was estimated at 11.3 s and took 46.9 s under ``nerfpipe run --time-budget 300``."""
    full = model.appearance_fit_steps
    if not full:
        return 0.0
    with model.fitted_appearance(rays, rgb, background, steps=FIT_WARMUP_STEPS):  # untimed: the first fit pays one-time costs
        pass
    times = []
    for steps in FIT_PROBE_STEPS:
        t0 = clock()
        with model.fitted_appearance(rays, rgb, background, steps=steps) as fitted:
            times.append(clock() - t0)
        if not fitted:
            return 0.0
    per_step = max(times[1] - times[0], 0.0) / (FIT_PROBE_STEPS[1] - FIT_PROBE_STEPS[0])
    return times[0] + per_step * (full - FIT_PROBE_STEPS[0])


def _final_share(cfg) -> float:
    """Of the time left when training stops, the share the final evaluation may take (the figures and videos come after)."""
    return EVAL_SHARE if cfg.video_frames and cfg.write_outputs else 1 - ENCODE_SHARE


def final_eval_need(trainer, supersample: bool = False, averaged_factor: float = AVERAGED_RENDER_FACTOR,
                    margin: float = FINAL_MARGIN) -> "float | None":
    """Seconds to leave when training stops for the final evaluation of every view at the configured size, one ray
    per pixel, or with ``supersample`` as many as the final evaluation would use (``eval_supersample`` at most, where
    views are scored smaller than their photographs), from the latest validation's time per ray, ``margin`` times over
    (the supersampled one ``averaged_factor`` times more where the parameters are averaged), with each view's appearance
    fit and its picture where the model fits one (``trainer.appearance_fit_seconds``); None before one.
    Supersampling is reserved for only after ``supersample_from`` steps (the trainer's window): on colmap_mouse under
    ``nerfpipe run --time-budget 300`` reserving for 2 x 2 rays from the start cut training from 878 to 600 steps."""
    if trainer.seconds_per_pixel is None:
        return None
    cfg, scene = trainer.cfg, trainer.scene
    if trainer.final_eval_rays is None:  # fixed by the scene and the configuration: counted once
        idx = eval_views(scene, cfg.final_eval_views)
        sizes = _eval_sizes(scene, idx, cfg)
        cams = scene.cameras[torch.tensor(idx, dtype=torch.long)]
        trainer.final_eval_rays = (sum(w * h for w, h in sizes),
                                   sum(w * h * view_supersample(cams, i, (w, h), cfg.eval_supersample) ** 2 for i, (w, h) in enumerate(sizes)), len(idx))
    factor = averaged_factor if supersample and trainer.average is not None else 1.0
    rays, views = trainer.final_eval_rays[int(supersample)], trainer.final_eval_rays[2]
    fits = 0.0  # each view's fit, and the view rendered whole with it at one ray per pixel (as _final_eval plans them)
    if trainer.appearance_fit_seconds:
        fits = views * trainer.appearance_fit_seconds + trainer.seconds_per_pixel * trainer.final_eval_rays[0]
    return margin * (factor * trainer.seconds_per_pixel * rays + fits) / _final_share(cfg)


def _fit(count: int, min_count: int, per: float, allowed: float, at_least: int, min_scale: float = 0.25, fixed: float = 0.0) -> FramePlan:
    """:func:`~nerfpipe.outputs.render.plan_frames` (``fixed``: each view's seconds that do not shrink with it), and when
    even ``min_count`` smallest views do not fit, as many of those as do (never fewer than ``at_least``), as large as
    they then fit."""
    fit = plan_frames(count, min_count, per, allowed, min_scale, fixed_per_frame=fixed)
    if fit.estimated_seconds > allowed:
        n = max(at_least, min(fit.frames, int(max(allowed, 0.0) // max(fixed + per * fit.scale**2, 1e-9))))
        scale = shrink(n, per, allowed, min_scale, fixed) if n else fit.scale
        fit = FramePlan(n, scale, n * (fixed + per * scale**2))
    return fit


def _video(trainer, metrics: dict, plan: dict) -> None:
    """Orbit/test-path videos: ``video_frames`` at ``video_scale``, or under a budget what fits the time left."""
    from nerfpipe.data.orbit import path_cameras
    from nerfpipe.outputs.artifacts import write_sequence
    from nerfpipe.outputs.novel_views import RenderConfig, render_sequence

    cfg = trainer.cfg
    cams = path_cameras(trainer.scene, "test", cfg.video_frames)
    w, h = (max(1, round(int(v) * cfg.video_scale)) for v in (cams.width[0], cams.height[0]))
    left = trainer.wall_left()
    if left is not None:
        per_frame = (trainer.seconds_per_pixel or 0.0) * w * h
        fit = _fit(cfg.video_frames, min(MIN_VIDEO_FRAMES, cfg.video_frames), per_frame, (1 - ENCODE_SHARE) * left, at_least=0)
        w, h = max(1, round(w * fit.scale)), max(1, round(h * fit.scale))
        plan["video"] = {"frames": fit.frames, "of": cfg.video_frames, "scale": fit.scale, "size": [w, h], "estimated_seconds": fit.estimated_seconds}
        if fit.frames < min(MIN_VIDEO_FRAMES, cfg.video_frames):  # a shorter orbit shows nothing: none at all
            plan["video"]["skipped"] = "no time left in the budget"
            return
    frames = len(cams) if left is None else fit.frames
    start = time.perf_counter()
    bg = background_colors(trainer.eval_bg, 1)[0]  # the one renderer of camera paths (nerfpipe render, the render stage)
    views, _ = render_sequence(trainer.model, trainer.scene, RenderConfig("test", frames, size=f"{w}x{h}", chunk=cfg.chunk), bg, cfg.device)
    metrics["video"] = write_sequence(views, trainer.out, "orbit", depth=True)
    if "video" in plan:
        plan["video"]["seconds"] = time.perf_counter() - start
    metrics["depth_colormap"] = metrics["video"]["depth_mapping"]


HELD_OUT_FALL_DB = 2.0
"""dB by which the intermediate validations may fall from their best to their last before the poses are suspect
(:func:`held_out_fall`). Where a capture's poses fold (photos registered in the wrong place), the held-out view's PSNR
falls while the field learns the photographs: two 23-photo folders of colmap_mouse 20.84 / 17.63 / 16.54 dB after 100 /
500 / 800 steps and 19.84 -> 14.63 over 1,100; right captures rise (colmap_mouse 22.54 -> 26.02, 17.28 -> 19.11 on a
right cut). Two other folds' views lay on their right part (22.04 -> 25.52, 21.66 -> 24.84 dB; their final 3-view
figures 19.97 and 21.42): not every fold shows (session 31)."""


def held_out_fall(rows: "list[list]") -> float:
    """dB by which the intermediate validations (``history["val"]`` rows, those of the first row's view count: the same
    views at the same size) fell from their best to their last; 0 for fewer than two."""
    views, value = VAL_COLUMNS.index("views"), VAL_COLUMNS.index("val_psnr")
    same = [r for r in rows if r[views] == rows[0][views]] if rows else []
    if len(same) < 2:
        return 0.0
    psnr = [float(r[value]) for r in same]
    return max(psnr) - psnr[-1]


def finish(trainer) -> dict:
    """Final validation, metrics.json, plots and videos; returns the metrics.

    Under a wall-clock budget the final validation and the videos are sized to what is left of it
    (``budget_plan`` in metrics.json says what was chosen); ``nerfpipe eval RUN`` scores the full protocol.
    """
    from nerfpipe.outputs import plots

    cfg, out = trainer.cfg, trainer.out
    plan: dict = {}
    fall = held_out_fall(trainer.history["val"])  # the intermediate ones, before the final evaluation's row
    psnr, ssim, views = _final_eval(trainer, plan)
    stats = trainer.model.stats()
    metrics = {
        "val_psnr": psnr,
        "val_ssim": ssim,
        "val_psnr_colour_fitted": trainer.last_fitted_psnr,
        **({} if trainer.last_appearance_fitted_psnr is None else {"val_psnr_appearance_fitted": trainer.last_appearance_fitted_psnr}),
        "val_views": views,
        "held_out_fall_db": round(fall, 2),
        "eval_scale": cfg.eval_scale * plan.get("final_eval", {}).get("scale", 1.0),
        "eval_max_size": cfg.eval_max_size,
        "train_seconds": trainer.train_seconds,
        "iterations": trainer.step,
        "seconds_per_iteration": trainer.train_seconds / max(trainer.step, 1),
        "rays_per_step": cfg.rays_per_step,
        "processes": trainer.world.size,
        "resumed_at": trainer.history.get("resumed_at", []),
        "model": trainer.model_name,
        **stats,
        **({} if trainer.graph is None else {"cuda_graph": {**trainer.graph.stats(), "failed": trainer.graph.failed}}),
    }
    checkpoint = out / CHECKPOINT
    if checkpoint.is_file():  # model, optimizer moments and random streams, as stored
        metrics["checkpoint_mb"] = checkpoint.stat().st_size / 2**20
    start = time.perf_counter()
    if cfg.write_outputs:
        fitted = trainer.last_appearance_fitted_psnr
        plots.plot_psnr(trainer.history, out / "psnr.png", None if fitted is None else (trainer.step, trainer.train_seconds, fitted, views))
        plots.plot_progress(sorted((out / "progress").glob("step_*.png")), out / "progress.png")
        spr = stats.get("samples_per_ray", 64)
        plots.plot_cameras(trainer.scene, trainer.sampler, out / "cameras.png", num_samples=int(spr))
    plan["figures_seconds"] = time.perf_counter() - start
    if cfg.video_frames and cfg.write_outputs:
        _video(trainer, metrics, plan)
    if cfg.time_budget is not None:
        metrics["budget_plan"] = {"time_budget": cfg.time_budget, "final_share": FINAL_SHARE if trainer.stopping_window is None or not cfg.time_budget else 1 - trainer.stopping_window / cfg.time_budget,
                                  "training_stopped_at": trainer.training_stopped_at,
                                  **({"supersample_plan": trainer.supersample_plan[0]} if trainer.supersample_plan else {}),
                                  **({"appearance_fit_timed": trainer.appearance_fit_seconds} if trainer.appearance_fit_seconds else {}),
                                  "final_started_at": trainer.final_started_at, **plan, "seconds": trainer.wall_elapsed()}
    write_json(out / "metrics.json", metrics)
    write_json(out / "history.json", {"val": [dict(zip(VAL_COLUMNS, row)) for row in trainer.history["val"]]})
    return metrics
