"""The training loop shared by every model: random rays across all training images, Adam,
validation at intervals, named callbacks, atomic checkpoints, resume, and the run's outputs.

Usable from Python::

    trainer = Trainer(TrainerConfig(iters=200), scene, "vanilla", VanillaConfig(), Path("runs/lego"))
    metrics = trainer.train()

Training time (``train_seconds``, the ``train_budget``) counts sampling, forward, backward, the
optimiser step and callbacks; validation, checkpoints and plots are excluded.

A trainer leaves the process as it found it: the model is initialised from ``seed`` with torch's
global stream seeded only for that call (:func:`nerfpipe.util.scoped.seeded_init`), every later random
draw comes from the run's own generators (``sampler_rng`` for rays and backgrounds, the model's
``generator`` for jitter and refreshes; both saved in the checkpoint, so a resumed run draws what an
uninterrupted one would), and ``num_threads`` holds only while :meth:`Trainer.train` runs.

Under torchrun (``torchrun --nproc-per-node N -m nerfpipe train ...``) the N processes train one
model data-parallel (:mod:`nerfpipe.training.distributed`): ``rays_per_step`` is the step's total, each rank
draws its share from its own streams, gradients are summed over the ranks, the model's own state
(occupancy grid, box) is sent from rank 0, and rank 0 alone validates and writes. After torchrun
restarts a failed group the trainer resumes from the checkpoint, with the same or another N.
"""

import contextlib
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.background import BACKGROUNDS, backgrounds
from nerfpipe.data.cameras import Cameras
from nerfpipe.data.exposure import exposure_gains, exposure_spread
from nerfpipe.data.orbit import camera_arc
from nerfpipe.data.scene import SceneData, check_images
from nerfpipe.functional.gather import move_rows
from nerfpipe.functional.metrics import psnr_from_mse
from nerfpipe.models.base import Callback, Model, SceneInfo
from nerfpipe.training import distributed
from nerfpipe.training.averaging import ParameterAverage, moved_rows
from nerfpipe.training.checkpoint import CHECKPOINT, find_checkpoint, load_checkpoint, save_checkpoint
from nerfpipe.training.cuda_graph import GraphedStep
from nerfpipe.training.pixel_sampler import PixelBatch, PixelSampler
from nerfpipe.training.runs import CONFIG, load_model_state, to_dict, write_json
from nerfpipe.util.devices import check_device
from nerfpipe.util.errors import NerfpipeError, refuse_unless, require_all
from nerfpipe.util.paths import check_output_folder
from nerfpipe.util.runlock import run_lock
from nerfpipe.util.scoped import continued_generator, seeded_init, torch_threads
from nerfpipe.util.typing import Float, Tensor


LOG_SECONDS = 1.0
"""The training losses are read back from the device (a host sync) and logged at most this often, and before
every validation, checkpoint and the end."""

DEVICE_RAYS_PER_STEP = {"cpu": 4096, "cuda": 16384}
"""Rays per step where ``rays_per_step`` is None, by device type (others: the CPU's). A GPU runs a step's
kernels in parallel and is bound by their launches, so four times the rays cost it 1.5x the time per step (an H200,
session 22: 11.1 / 16.4 ms for the fast field on lego_200): on ``blender_lego`` 29.85 / 31.47 / 32.18 dB after
10 / 30 / 60 s against 28.87 / 30.56 / 31.00 with 4,096. On two CPU cores the time per step grows with the rays. The
``fast`` model's learning rates on bounded scenes follow the batch (:data:`nerfpipe.models.fast.LR_REFERENCE_RAYS`: twice
as large at 16,384 rays since session 45; the H200 figures here are from before)."""


def by_device(table: dict, device: str):
    """``table``'s entry for ``device``'s type (a resolved name such as ``cuda:1``), the CPU's for any other type.

    Example:
        >>> by_device(DEVICE_RAYS_PER_STEP, "cuda:1"), by_device(DEVICE_RAYS_PER_STEP, "cpu"), by_device(DEVICE_ERROR_SAMPLING, "mps")
        (16384, 4096, 0.3)
    """
    return table.get(torch.device(device).type, table["cpu"])


CPU_PIXELS_PER_RAY = 20
"""On the CPU, a model whose batch follows the scene (:attr:`Model.batch_follows_pixels`: the ``fast`` model) takes one ray
per step for about this many pixels of the training image of an object on a transparent background (:func:`default_rays_per_step`), between
:data:`DEVICE_RAYS_PER_STEP`'s 4,096 and :data:`CPU_MAX_RAYS_PER_STEP`. Part of a step's cost does not grow with its
rays (the optimiser's pass over every parameter, the tables' gradients, the occupancy refreshes), and the field's
capacity, so that part, grows with the pixels. ``nerfpipe bench DATA --presets fast --rays-per-step R`` at equal training
seconds (session 50, this CPU, each alone, load ~2), after 100 / 250 s on the 800² stand-in (``python -m
benchmarks.lego800``, 4 views at full size): 4,096 rays 25.98 / 27.50 dB (422 / 822 steps), 8,192 26.27 / 28.05, **16,384
26.75 / 28.49** (229 / 504 steps); ``blender_lego`` (400², 5 views) after 60 / 150 s: 4,096 27.50 / 29.20 (396 / 779
steps), **8,192 27.60 / 29.98** (249 / 599), 16,384 27.76 / 29.98; ``lego_200`` (200²) after 20 / 60 s: **4,096 27.22 /
30.15** (152 / 500 steps), 8,192 26.48 / 30.33, 16,384 25.10 / 30.05 (a small scene's first seconds need many steps);
the 800² stand-in at 32,768 rays 26.58 / 28.18 (:data:`CPU_MAX_RAYS_PER_STEP`). Not tuned on: ``nerfstudio_lego`` (800², COLMAP's
poses, 5 views) after 60 / 150 s 24.39 / 25.32 at 4,096, **25.38 / 26.24** at 16,384.
Scenes without alpha keep 4,096: the rays of a real capture cross its surroundings, so a step's cost is mostly its rays'
samples. ``ngp_fox`` read as a bounded scene (``nerfpipe train``, no sparse points; 4 views at a quarter size) after 60 /
150 s: **18.79 / 19.26** at 4,096 (36 samples per ray), 18.56 / 18.89 at 16,384; real captures with sparse points
(``nerfpipe run``) lose per step with larger batches too (colmap_mouse at 16,384 rays, 24.76 against 24.82 dB after
900 steps: :data:`nerfpipe.models.fast.LR_REFERENCE_RAYS`)."""

CPU_MAX_RAYS_PER_STEP = 16384
"""The largest batch :data:`CPU_PIXELS_PER_RAY` gives."""


def default_rays_per_step(device: str, info: SceneInfo, model: Model) -> int:
    """Rays per step where ``rays_per_step`` is None: :data:`DEVICE_RAYS_PER_STEP` for the device, and on the CPU, for a
    model whose batch follows the scene, one per :data:`CPU_PIXELS_PER_RAY` pixels of the training image of an object
    on a transparent background (``SceneInfo.has_alpha``, bounded), rounded to a power of two, at most
    :data:`CPU_MAX_RAYS_PER_STEP`.

    Example:
        >>> import torch
        >>> from nerfpipe.models.base import Model, SceneInfo
        >>> fast = type("Fast", (Model,), {"batch_follows_pixels": True})()
        >>> [default_rays_per_step("cpu", SceneInfo(torch.zeros(2, 3), 0.1, 6.0, 100, side * side, has_alpha=True), fast) for side in (200, 400, 800)]
        [4096, 8192, 16384]
        >>> default_rays_per_step("cpu", SceneInfo(torch.zeros(2, 3), 0.1, 6.0, 100, 800 * 800), fast)  # no alpha
        4096
        >>> default_rays_per_step("cuda", SceneInfo(torch.zeros(2, 3), 0.1, 6.0, 100, 800 * 800, has_alpha=True), fast)
        16384
    """
    rays = by_device(DEVICE_RAYS_PER_STEP, device)
    if torch.device(device).type == "cuda" or not model.batch_follows_pixels or not info.has_alpha or info.unbounded:
        return rays
    wanted = 2 ** round(math.log2(max(info.pixels_per_image / CPU_PIXELS_PER_RAY, 1.0)))
    return int(min(max(wanted, rays), CPU_MAX_RAYS_PER_STEP))


MAX_RAYS_PER_STEP = 1 << 22
"""More rays per step than this (4 M) would not fit in memory with any model's samples: a typo, refused."""

DEFAULT_ITERS = 1000
"""Training iterations of a run without a budget (``TrainerConfig.iters`` None)."""

PLATEAU_STEPS = 800
"""Steps after which the held-out views of a real capture stop improving (``TrainerConfig.supersample_from``'s
default where the parameters are averaged): colmap_mouse, 7 views at 400 px, the parameters averaged with decay
0.998, 24.56 / 24.53 dB after 800 / 1,000 steps and 24.55 after 1,149 (session 27), while scoring the same
views with 2 x 2 rays per pixel instead of one adds 0.15 dB."""

AVERAGE_FROM = {True: 256, False: 128}
"""``TrainerConfig.average_from``'s default, for real captures (``SceneInfo.unbounded``) and elsewhere."""

AVERAGE_POWER = {True: 3.0, False: 7.0}
"""``TrainerConfig.average_power``'s default, for real captures and elsewhere: a power-function average, spanning about
the last quarter / eighth of the steps so far. Real captures had the fixed decay of 0.998 (a window of about 500 steps,
uniform from step 256) until session 67: it lags a scene that still improves at the few hundred to a thousand steps a
time budget affords. Side by side at equal steps (session 67, one ray per pixel, 400 px, the average scored at every
mark: ``python -m benchmarks.side_by_side DATA --variants "base:" "p7:train.average_power=7" "p3:train.average_power=3"
--marks 600 900 1200 --average-every-mark``), the decay / power 7 / power 3 after 600 / 900 / 1,200 steps:
colmap_mouse (7 views) 24.619 / 24.910 / **24.844**, 24.914 / 25.000 / **25.040**, 25.037 / 24.961 / **25.015** dB; the
posed 23-photo cut (3 views) 24.449 / 24.860 / **24.733**, 24.738 / 24.730 / **24.823**, 24.809 / 24.656 / **24.734**; the
same reconstruction of colmap_mouse's 59 photos from the ``sfm`` stage (8 views) 24.975 / 25.265 / **25.147**, 25.133 /
25.414 / **25.372**, 25.246 / 25.493 / **25.452**; the synthetic room (``nerfpipe synth --scene room``, 7 views) 30.242 /
30.877 / **30.675**, 30.944 / 31.472 / **31.354**, 31.406 / 31.806 / **31.711**; photos_sceaux_castle (its sfm folder, 2
views) after 600 / 900 / 1,200 15.170 / 15.077 / **15.119**, 15.137 / 15.030 / **15.082**, 15.110 / 15.019 / **15.055**. Power 3: +0.1 to +0.4 dB where the
scene still improves, at most 0.08 dB less where it has stopped by 1,200 steps (a longer window smooths more there);
power 7 loses more there."""

DEVICE_ERROR_SAMPLING = {"cpu": 0.3, "cuda": 0.5}
"""``TrainerConfig.error_sampling``'s default on bounded scenes for a model that asks for it (``Model.error_sampled``),
by device type (others: the CPU's). Rays drawn where the field is wrong meet the object, so a step marches more
samples: on this CPU 0.5 of 16,384 rays took 1.14x the seconds per step of 0.3 on blender_lego (6.1 against 4.8
samples per ray), where a GPU bound by its kernel launches (fixed shapes, a CUDA graph) pays nothing for them, so
there its gain per step is the gain. Side by side at 16,384 rays (CUDA's :data:`DEVICE_RAYS_PER_STEP`; session 46, this
CPU, the average scored) 0.3 / 0.5: lego800 29.04 / **29.37 dB** after 600 steps, 29.88 / **30.24** after 1,000
(unaveraged), 31.82 / **31.93** after 3,000; blender_lego 29.65 / **29.88** after 300; lego_200 31.34 / **31.53**
after 300. At 4,096 rays lego_200 gained as much per step (session 42: 29.29 / 29.60 after 300, at 1.2x the time
per step), so the CPU keeps 0.3."""

RESOLVED_DEFAULTS = ("rays_per_step", "error_sampling")
"""Options whose None the trainer resolves (by the device, the scene and the model) into the config its run records:
a run given None continues one that recorded the resolved value."""

UNCAPPED_ITERS = 1 << 62
"""The iteration cap under a budget when ``iters`` is not set: none that a run reaches."""


@dataclass
class TrainerConfig:
    """How to train a model."""

    iters: "int | None" = None
    """Training iterations (optimiser steps) at most. None: :data:`DEFAULT_ITERS` without a budget; under a
    ``train_budget`` or ``time_budget`` no cap, the budget decides (``nerfpipe train lego_200 --time-budget 150`` on an
    H100 with the old cap of 1,000: training ended at 64 s and the command at 70 s, 30.75 dB; without: 1,809
    iterations, 118 s, 31.66 dB). :attr:`max_iters` is the cap in force."""
    train_budget: "float | None" = None
    """Stop after this many seconds of training (validation excluded), whichever of the two comes first;
    the iteration running when the budget runs out is finished."""
    time_budget: "float | None" = None
    """Wall-clock seconds for the whole run, end to end: from when the trainer is made (or the ``started`` it is
    given: ``nerfpipe train`` counts from the process's start), training, validations, the final evaluation,
    figures and videos. Training stops when :data:`~nerfpipe.training.evaluation.FINAL_SHARE` of it is
    left (more, up to ``FINAL_MAX_SHARE``, where the validations' time per ray says the final evaluation of every
    view needs it); the final evaluation's views, size and supersampling and the videos' frames and size are then chosen
    to fit (``budget_plan`` in metrics.json). ``nerfpipe eval RUN`` scores the full protocol afterwards."""
    clock: str = "wall"
    """What ``train_budget`` and the training seconds count: ``wall`` seconds, or ``cpu`` (process CPU
    seconds divided by the torch threads; steadier on a shared machine)."""
    rays_per_step: "int | None" = 10000
    """Rays per iteration, drawn uniformly from all pixels of all training images (None: by the device and the scene,
    :func:`default_rays_per_step`; the fast model's default). The run's ``config.json`` records the number used."""
    train_max_size: "int | None" = None
    """Longer side in pixels of the images training rays are drawn from, at most: larger photographs are
    area-downscaled once at load (their cameras with them), so each ray's colour is the mean over its pixel's
    footprint at that size (None: full resolution). The model's capacity follows these pixels."""
    error_sampling: "float | None" = None
    """Share of the pixel rays drawn where the field is still wrong (an error map after instant-ngp's:
    :class:`~nerfpipe.training.pixel_sampler.ErrorMap`); the rest are uniform. None: :data:`DEVICE_ERROR_SAMPLING` on
    bounded scenes for a model that asks for it (``Model.error_sampled``: the ``fast`` model), else 0; the run's
    ``config.json`` records the share used. On lego_200 after 300 steps (session 43, side by side, the average
    scored) 0 / 0.3 **28.75 / 29.45 dB** at 0.099 / 0.114 s per step (4.3 / 6.4 samples per ray: its rays hit the
    object); session 42, with a map that read its tiles back: 0.5 29.60 at 1.24x the time per step, 0.8 without the
    average 28.77 against 27.73 but 1.5-1.9x the time per step. Off on real captures: on colmap_mouse it loses at
    equal steps (-0.26 dB after 600 with 0.8: rays leave the object the field has learnt for surroundings it cannot
    explain). Where a step's time does not grow with its samples (a GPU bound by kernel launches), its gain per
    step is the gain."""
    average: "bool | None" = None
    """Evaluate and save the parameters averaged over the late steps (:mod:`nerfpipe.training.averaging`: an
    exponential moving average from step ``average_from`` on, warm-started uniform) instead of the last step's.
    Default: for real captures (``SceneInfo.unbounded``), whose held-out views stop improving while the training
    views rise (colmap_mouse after 600 / 800 / 1,000 steps: 24.53 / 24.54 / 24.49 dB against 24.41 / 24.39 /
    24.31), and for every scene with a model that asks for it (``Model.averaged``: the ``fast`` model, since session
    42: the average smooths Adam's last steps on synthetic scenes too); off for the classic NeRF MLP (the recipe)."""
    average_from: "int | None" = None
    """First step of the parameter average. None: 256 for real captures, 128 elsewhere (with :attr:`average_power` the
    early steps fade anyway: lego_200 after 300 steps from step 100 / 256, 28.75 / 28.69 dB)."""
    average_power: "float | None" = None
    """Where positive, each step's weight in the parameter average is ``(average_power + 1)`` over the step count
    instead of ``1 - average_decay`` (a power-function average, as EDM2's: about the last ``1 / (average_power + 1)``
    of the steps so far weigh most, however long the run goes; 0: the fixed ``average_decay``). Side by side at equal
    steps (session 42, ``python -m benchmarks.side_by_side``, the averaged parameters scored after the last mark):
    lego_200 (10 views, one ray per pixel) the last step's parameters 28.48 / 31.14 dB after 300 / 1,000 steps; a fixed
    decay 0.97 / 0.98 / 0.99 from step 200 28.76 / 28.73 / - and 31.43 / - / 31.52 (0.99 from step 100: 28.41 after 300,
    the window too long for it); power 5 / 7 / 10 from step 100 28.73 / **28.75** / 28.75 and 31.49 / **31.51** / 31.52.
    colmap_mouse (7 held-out views at 400 px) after 900 steps from step 256: 0.998 (the default until then) 24.78, power
    3 / 7 24.82 / 24.80 (the last step's 24.72); photos_sceaux_castle (its sfm folder, 2 views) after 600 steps power 7
    from step 128 14.19 against 14.39 with 0.998 from 256. None: 7 on bounded scenes, 3 on real captures
    (:data:`AVERAGE_POWER`; the fixed decay until session 67)."""
    average_decay: float = 0.998
    """Decay of the parameter average per step (the last ~``1 / (1 - decay)`` steps weigh most; uniform over the
    first that many). colmap_mouse after 800 / 1,000 steps, from step 256: 0.99 24.48 / 24.44 dB, 0.995 24.54 /
    24.49, 0.998 24.56 / 24.53 (the last step's parameters: 24.39 / 24.31)."""
    supersample_from: "int | None" = None
    """Under a wall-clock budget, from this step on training stops as soon as what is left is what the final
    evaluation needs with ``eval_supersample`` rays per pixel side (views scored smaller than their photographs:
    anti-aliased against their area mean), instead of training on at one ray per pixel. Default:
    :data:`PLATEAU_STEPS` where the parameters are averaged (real captures, whose held-out views stop improving
    after a few hundred steps), never elsewhere (0: never)."""
    error_tiles: int = 16384
    """About how many tiles the error map cuts the training images into (square tiles, at least 4 pixels wide)."""
    track_rays: int = 512
    """Rays per iteration (of ``rays_per_step``) through the sparse points' track observations, when the
    scene has them (COLMAP): their colour and the distance of the point along them, for models with a
    depth loss (0: uniform pixels only)."""
    lr: float = 5e-4
    """Adam learning rate (models may set their own per parameter group)."""
    eval_every: int = 100
    """Validate every this many iterations (0: only at the end)."""
    eval_views: int = 1
    """Validation views rendered at each intermediate validation (the first ones of the val split; one ray per pixel:
    ``evaluation.INTERMEDIATE_SUPERSAMPLE``)."""
    final_eval_views: int = 0
    """Validation views for the final metrics (0: all of the val split)."""
    eval_scale: float = 1.0
    """Resolution factor of validation renders (ground truth is area-resized to match)."""
    eval_max_size: "int | None" = 800
    """Longer side of validation renders in pixels at most, after ``eval_scale`` (phone photographs are
    scored at a reduced size; None: no cap)."""
    eval_supersample: int = 2
    """Rays per pixel side at most in validation renders smaller than the photographs they are scored against (whose
    ground truth is their area mean): each pixel is the mean of up to this many squared rays over its area
    (:func:`~nerfpipe.outputs.render.supersample_factor`; 1: one ray through its centre). Costs up to its square
    in render time; under a ``time_budget`` the final evaluation supersamples only where every view fits with it.
    colmap_mouse (7 held-out views at 400 px of 1,920 px photographs, ``nerfpipe run``'s checkpoint):
    24.23 dB with one ray, 24.38 with 2 x 2, 24.39 with 3 x 3."""
    seed: int = 0
    """Seed of model initialisation, ray sampling and jitter (CPU runs are deterministic)."""
    device: str = "auto"
    """Torch device: auto (CUDA when present, else CPU: :func:`nerfpipe.util.devices.check_device`), cpu, cuda, cuda:N, mps."""
    num_threads: "int | None" = None
    """CPU threads for torch while training (None: as the process has them; restored afterwards). On a
    loaded machine 1 can be much faster for small models."""
    background: str = "auto"
    """black | white | grey | random | auto (random in training and white at evaluation for RGBA data; grey for real
    captures, whose photographs show the surroundings; else black: :func:`nerfpipe.data.background.backgrounds`)."""
    checkpoint_every: int = 500
    """Write checkpoint.safetensors every this many iterations (and always at the end)."""
    chunk: "int | None" = None
    """Rays per forward pass when rendering whole images (None: the model's ``render_chunk``, 16,384 for ``fast``)."""
    video_frames: int = 60
    """Frames of the orbit/test-path videos written at the end (0: no videos)."""
    video_scale: float = 1.0
    """Resolution factor of the videos."""
    resume: bool = False
    """Continue from the run folder's checkpoint.safetensors."""
    cuda_graph: "bool | None" = None
    """Capture each training step's forward, losses and backward as a CUDA graph and replay it
    (:mod:`nerfpipe.training.cuda_graph`: the host launches one graph instead of hundreds of kernels; models whose
    step reads values back, e.g. the fast model's rounds of early termination, step eagerly anyway). Default: on
    CUDA; ignored elsewhere and under torchrun."""
    cache_rays: "bool | None" = None
    """Generate every training pixel's ray once and keep them on the device with the pixels, so that a batch is one
    upload of its pixel indices and a few gathers (:class:`~nerfpipe.training.pixel_sampler.PixelSampler`); default:
    on CUDA where they fit (40 bytes a pixel, at most 4 GiB and a quarter of the free memory)."""
    write_outputs: bool = True
    """Write psnr.png, progress.png, cameras.png and the videos at the end (metrics.json and the checkpoint always)."""

    @property
    def max_iters(self) -> int:
        """The iteration cap in force: ``iters`` when set, else :data:`DEFAULT_ITERS` without a budget and none
        (:data:`UNCAPPED_ITERS`) under one."""
        if self.iters is not None:
            return self.iters
        return DEFAULT_ITERS if self.train_budget is None and self.time_budget is None else UNCAPPED_ITERS

    def __post_init__(self) -> None:
        """Impossible values are one clear error before anything runs or is written (not a run that never ends)."""
        checks = (
            ("iters", self.iters is None or self.iters >= 0, "0 or more"), ("rays_per_step", self.rays_per_step is None or 1 <= self.rays_per_step <= MAX_RAYS_PER_STEP, f"None or between 1 and {MAX_RAYS_PER_STEP}"),
            ("track_rays", self.track_rays >= 0, "0 or more"), ("lr", self.lr > 0, "positive"),
            ("error_sampling", self.error_sampling is None or 0 <= self.error_sampling <= 1, "between 0 and 1"), ("error_tiles", self.error_tiles >= 1, "at least 1"),
            ("eval_every", self.eval_every >= 0, "0 or more"), ("chunk", self.chunk is None or self.chunk >= 1, "at least 1"),
            ("train_budget", self.train_budget is None or self.train_budget >= 0, "0 or more seconds"),
            ("time_budget", self.time_budget is None or self.time_budget >= 0, "0 or more seconds"),
            ("checkpoint_every", self.checkpoint_every >= 0, "0 or more"), ("video_frames", 0 <= self.video_frames <= 10_000, "between 0 and 10000"),
            ("eval_views", self.eval_views >= 1, "at least 1"), ("final_eval_views", self.final_eval_views >= 0, "0 or more"),
            ("eval_scale", 0 < self.eval_scale <= 16, "a positive factor (at most 16)"),
            ("video_scale", 0 < self.video_scale <= 16, "a positive factor (at most 16)"),
            ("eval_max_size", self.eval_max_size is None or self.eval_max_size >= 1, "at least 1"),
            ("eval_supersample", 1 <= self.eval_supersample <= 8, "1 to 8"),
            ("average_from", self.average_from is None or self.average_from >= 0, "0 or more"),
            ("average_decay", 0 <= self.average_decay < 1, "at least 0 and below 1"),
            ("average_power", self.average_power is None or self.average_power >= 0, "0 or more"),
            ("supersample_from", self.supersample_from is None or self.supersample_from >= 0, "0 or more"),
            ("train_max_size", self.train_max_size is None or self.train_max_size >= 1, "at least 1"),
            ("num_threads", self.num_threads is None or self.num_threads >= 1, "at least 1"),
            ("background", self.background in (*BACKGROUNDS, "random", "auto"), f"{', '.join(BACKGROUNDS)}, random or auto"),
            ("clock", self.clock in ("wall", "cpu"), "wall or cpu"),
        )
        refuse_unless((name, ok, what, getattr(self, name)) for name, ok, what in checks)
        check_device(self.device)


def scene_info(scene: SceneData, train_max_size: "int | None" = None, exposure: bool = False) -> SceneInfo:
    """What a model may know of ``scene`` when it is built, its training images at most ``train_max_size`` pixels on the longer side.
    ``exposure``: also measure the training photos' exposure spread on a real capture's tracks (:func:`exposure_spread_of`;
    reads the photos, about a second per 50); a model rebuilt from a checkpoint needs none (its tensors say what it has)."""
    cams = scene.split_cameras("train").capped(train_max_size)
    pixels = int((cams.width * cams.height).max()) if len(cams) else 0
    rel = (cams.fx.double() / (cams.width.double() ** 2 + cams.height.double() ** 2).sqrt()).reshape(-1)
    q = torch.quantile(rel, torch.tensor([0.25, 0.5, 0.75], dtype=rel.dtype)) if len(rel) > 1 else None
    spread = float((q[2] - q[0]) / q[1]) if q is not None else 0.0
    return SceneInfo(aabb=scene.aabb, near=scene.near, far=scene.far, num_images=len(cams), pixels_per_image=pixels, has_alpha=scene.has_alpha,
                     unbounded=scene.shows_surroundings, focal_spread=spread,
                     exposure_spread=exposure_spread_of(scene) if exposure else 0.0, arc=camera_arc(cams, scene.aabb.mean(0)),
                     pixel_footprint=pixel_footprint(cams, scene.aabb), support_plane=support_plane_of(scene),
                     points=_box_points(scene), cameras=cams)


EXPOSURE_MAX_PHOTOS = 100
"""The training photos :func:`exposure_spread_of` reads at most, spread evenly over them (each is decoded once more)."""


def exposure_spread_of(scene: SceneData) -> float:
    """The spread of the training photos' log exposure gains (:func:`nerfpipe.data.exposure.exposure_gains`) on a real
    capture with tracks, over at most :data:`EXPOSURE_MAX_PHOTOS` of them; 0 for any other scene."""
    train = np.asarray(scene.splits["train"])
    if not scene.shows_surroundings or not scene.points.has_tracks or len(train) < 2:
        return 0.0
    if len(train) > EXPOSURE_MAX_PHOTOS:
        train = train[np.linspace(0, len(train) - 1, EXPOSURE_MAX_PHOTOS).round().astype(np.int64)]
    return exposure_spread(exposure_gains(scene.points, scene.images, len(scene.cameras), train))


def _box_points(scene: SceneData) -> "Float[Tensor, 'num_points 3'] | None":
    """A real capture's sparse points in its scene box (float32, on the CPU), or None."""
    if not scene.shows_surroundings or scene.points is None or not len(scene.points.xyz):
        return None
    return scene.points.xyz.float().cpu()[_in_region(scene)]


def _in_region(scene: SceneData) -> "Tensor":
    """Which of the scene's sparse points lie in its scene box, the object region (bool, on the CPU)."""
    xyz, (lo, hi) = scene.points.xyz.double().cpu(), scene.aabb.double().cpu()
    return ((xyz >= lo) & (xyz <= hi)).all(-1)


SUPPORT_TOLERANCE = 0.02
"""Distance within which sparse points lie on the support plane, in robust diagonals of the points (the mesh stage's
``support_tolerance``)."""
SUPPORT_LOWEST = 0.1
"""The support plane is drawn through the lowest of the sparse points along the cameras' up direction, this share of them
(colmap_mouse's white table holds 1.5 % of its points)."""
SUPPORT_MIN_SHARE = 0.05
"""Share of those lowest points the support plane must hold (it must also hold 1 % of all of them)."""
SUPPORT_MIN_POINTS = 50
"""Sparse points below which no support plane is looked for."""
SUPPORT_MAX_POINTS = 5000
"""Sparse points the support plane's side tests read at most (a seeded sample of them): each scene load looks for the
plane, and its side tests compare every point with 4,000 hypotheses (in chunks: ``mesh.clean.SIDE_TEST_ELEMENTS``)."""
SUPPORT_MAX_TILT = 20.0
"""Degrees the support plane's normal may lie from the cameras' mean up direction: among the sparse points alone a slope
of the object can hold more of them than the table (colmap_mouse at 45: a plane 30 degrees off, through the mouse's back)."""


def support_plane_of(scene: SceneData) -> "tuple[float, float, float, float] | None":
    """The plane a real capture's object stands on, or None: :func:`nerfpipe.mesh.clean.support_plane` through the lowest
    :data:`SUPPORT_LOWEST` of its sparse points in the object region (``scene.aabb``; all of them where it holds fewer than
    :data:`SUPPORT_MIN_POINTS`: a table, not the floor a room's points reach down to), with 95 % of the training cameras above it, 98 % of the points above it or
    on it, at least 1 % of them on it, and its normal within :data:`SUPPORT_MAX_TILT` degrees of the cameras' up direction
    (seeded: the same plane each time the scene is loaded). colmap_mouse: within 3.1 degrees and a tenth of a box height of the
    plane the mesh stage finds on its mesh; the room scene's floor exactly; ngp_fox (no plane under its points): None."""
    if not scene.shows_surroundings or scene.points is None or len(scene.points.xyz) < SUPPORT_MIN_POINTS:
        return None
    from nerfpipe.data.normalize import upright_direction
    from nerfpipe.mesh.clean import support_plane
    from nerfpipe.mesh.metrics import robust_diagonal

    cams = scene.split_cameras("train")
    points = _support_points(scene)
    centers = cams.centers.double().reshape(-1, 3).cpu().numpy()
    up = upright_direction(cams.to("cpu")).numpy()
    height = points @ (up / np.linalg.norm(up))
    low = points[height <= np.quantile(height, SUPPORT_LOWEST)]  # hypotheses from the bottom: a white table holds few points
    tolerance = SUPPORT_TOLERANCE * robust_diagonal(points)
    if len(points) > SUPPORT_MAX_POINTS:  # the side tests hold [points, hypotheses] arrays: a seeded sample of them
        points = points[np.random.default_rng(0).choice(len(points), SUPPORT_MAX_POINTS, replace=False)]
    plane = support_plane(low, points, centers, tolerance, min_inliers=SUPPORT_MIN_SHARE, up=up, max_tilt_deg=SUPPORT_MAX_TILT)
    return None if plane is None else tuple(float(v) for v in plane)


def _support_points(scene: SceneData) -> "np.ndarray":
    """The sparse points the support plane is looked for in (float64): those in the object region, the plane under the
    object rather than a floor farther down, or all of them where the region holds fewer than :data:`SUPPORT_MIN_POINTS`."""
    points, inside = scene.points.xyz.double().cpu().numpy(), _in_region(scene).numpy()
    return points[inside] if inside.sum() >= SUPPORT_MIN_POINTS else points


def above_support(scene: SceneData) -> "np.ndarray | None":
    """Which of the scene's sparse points lie more than the support plane's tolerance (:data:`SUPPORT_TOLERANCE` of their
    robust diagonal) above it: not on the table and not under it. None where :func:`nerfpipe.models.fast.object_support`
    gives no plane (no plane in the points, or a facade or photo collection, whose ground the mesh stage looks for in the
    mesh, if at all). The mesh figures' points on the object (the mesh stage removes the table)."""
    from nerfpipe.models.fast import object_support

    plane = object_support(scene_info(scene))
    if plane is None:
        return None
    from nerfpipe.mesh.metrics import robust_diagonal

    xyz = scene.points.xyz.double().cpu().numpy()
    return xyz @ np.asarray(plane[:3]) + plane[3] > SUPPORT_TOLERANCE * robust_diagonal(_support_points(scene))


def pixel_footprint(cams: Cameras, aabb: Float[Tensor, "2 3"]) -> float:
    """Median over cameras of (distance to the box centre) / (focal length in pixels): one pixel's width there."""
    if not len(cams):
        return 0.0
    centre = aabb.double().mean(0)
    dist = (cams.world_from_cam[..., :3, 3].double().reshape(-1, 3) - centre).norm(dim=-1)
    focal = (0.5 * (cams.fx + cams.fy)).double().reshape(-1)
    return float((dist / focal).median())


def drop_stale_optimizer_state(optimizer: torch.optim.Optimizer) -> None:
    """Forget the optimiser state of parameters a model resized in a callback (e.g. grids
    resampled to a tightened box): Adam's moments no longer match their shape. A parameter whose rows were only
    re-laid out (marked ``row_source``: a sparse grid level whose blocks were added or dropped) keeps its rows' state,
    moved with them; new rows' state is zero (:func:`~nerfpipe.training.averaging.moved_rows`)."""
    for p, st in list(optimizer.state.items()):
        stale = [k for k, v in st.items() if isinstance(v, torch.Tensor) and v.ndim > 0 and v.shape != p.shape]
        sources = [moved_rows(p, st[k]) for k in stale]
        if stale and all(src is not None for src in sources):
            for k, src in zip(stale, sources):
                st[k] = move_rows(st[k], src)
        elif stale:
            optimizer.state[p] = {}


def share(total: int, world: distributed.World) -> int:
    """This rank's part of ``total`` (rays per step): equal parts, the remainder to the first ranks."""
    return total // world.size + (world.rank < total % world.size)


class Trainer:
    """Trains one model on one scene into a run folder."""

    def __init__(self, cfg: TrainerConfig, scene: SceneData, model_name: str, model_config, out_dir: Path, started: "float | None" = None) -> None:
        """Everything that can be refused is refused here, before training and before ``out_dir`` is made:
        the output folder, the optional modules the outputs need, and every image the run will read.
        ``started`` (a ``time.monotonic()`` value, default now) is when the ``time_budget`` began."""
        from nerfpipe.training import evaluation

        self.started = time.monotonic() if started is None else started
        cfg = replace(cfg, device=check_device(cfg.device))  # auto resolved once: the run's config records the device used
        self.world = distributed.world(cfg.device)
        if self.world.active:
            cfg = replace(cfg, device=distributed.device_for(cfg.device, self.world))
        self.cfg, self.scene, self.out = cfg, scene, check_output_folder(out_dir)
        require_all(evaluation.dependencies(cfg))
        self.model_name, self.model_config = model_name, model_config
        self.train_bg, self.eval_bg = backgrounds(cfg.background, scene.has_alpha, scene.shows_surroundings)
        info = scene_info(scene, cfg.train_max_size, exposure=True)
        model, init_rng = seeded_init(lambda: model_config.setup(info), cfg.seed)
        self.model: Model = model.to(cfg.device)
        if cfg.rays_per_step is None:  # likewise the batch chosen by the device and the scene
            cfg = self.cfg = replace(cfg, rays_per_step=default_rays_per_step(cfg.device, info, self.model))
        if self.world.active:
            refuse_unless([("rays_per_step", cfg.rays_per_step >= self.world.size, f"at least the {self.world.size} processes", cfg.rays_per_step)])
        self.model.generator = continued_generator(cfg.device, cfg.seed, init_rng)
        if self.world.rank:  # every rank jitters and refreshes with its own stream (rank 0: as one process)
            self.model.generator.manual_seed(distributed.rank_seed(cfg.seed, self.world.rank))
        # The fused kernel is ~10x faster than the per-tensor loop on large grids (CPU and CUDA).
        fused = torch.device(cfg.device).type in ("cpu", "cuda")
        self.optimizer = torch.optim.Adam(self.model.param_groups(cfg.rays_per_step), lr=cfg.lr, fused=fused)
        for group in self.optimizer.param_groups:  # the schedule scales these (saved with the optimiser)
            group.setdefault("initial_lr", group["lr"])
        self.generator = torch.Generator().manual_seed(distributed.rank_seed(cfg.seed, self.world.rank))
        self.rays = share(cfg.rays_per_step, self.world)
        """Rays this process draws per step (all of ``rays_per_step`` in one process)."""
        if cfg.error_sampling is None:  # recorded in config.json as used
            cfg = self.cfg = replace(cfg, error_sampling=by_device(DEVICE_ERROR_SAMPLING, cfg.device) if self.model.error_sampled and not info.unbounded else 0.0)
        self.sampler = PixelSampler(scene, "train", self.train_bg, cfg.device, track_rays=share(cfg.track_rays, self.world),
                                    max_side=cfg.train_max_size, error_share=cfg.error_sampling, error_tiles=cfg.error_tiles,
                                    cache_rays=cfg.cache_rays)
        self.sync: "distributed.BufferSync | None" = None
        use_graph = cfg.cuda_graph is not False and torch.device(cfg.device).type == "cuda" and not self.world.active
        self.graph = GraphedStep(self.model, self.optimizer, self.forward_backward) if use_graph else None
        """The training step as a replayed CUDA graph (:attr:`TrainerConfig.cuda_graph`), or None: eager steps."""
        split = evaluation.eval_split(scene)
        if split != "train":  # decoded now (the sampler decoded train's): a broken one is an error before out_dir exists
            check_images(scene, scene.splits[split])
        self.step, self.train_seconds = 0, 0.0
        self.history = {"train": [], "val": []}  # train rows: [step, seconds, psnr]; val: [.., psnr, ssim, views]
        self._losses: "list[tuple[int, float, Tensor]]" = []  # (step, seconds, MSE on the device) not yet in history
        self._logged_at = 0.0  # perf_counter of the latest flush_losses
        self.hooks = self.model.callbacks()
        averaged = info.unbounded or self.model.averaged if cfg.average is None else cfg.average
        start = AVERAGE_FROM[info.unbounded] if cfg.average_from is None else cfg.average_from
        power = AVERAGE_POWER[info.unbounded] if cfg.average_power is None else cfg.average_power
        self.average = ParameterAverage(self.model, start, cfg.average_decay, power) if averaged else None
        """The running average of the parameters that the run ends with (None: the last step's)."""
        self.supersample_from = (PLATEAU_STEPS if self.average is not None and info.unbounded else 0) if cfg.supersample_from is None else cfg.supersample_from
        """Step from which training leaves the final evaluation its supersampling (0: never; ``supersample_from``)."""
        self.seconds_per_pixel: "float | None" = None  # per ray of the latest validation render
        self.final_eval_rays: "tuple[int, int, int] | None" = None  # rays of the final evaluation of every view, one per pixel and supersampled, and its views (counted once)
        self.appearance_fit_seconds: "float | None" = None
        """Under a budget, one held-out view's appearance fit for the final evaluation, timed at the first validation
        (:func:`~nerfpipe.training.evaluation.time_appearance_fit`; 0 without per-image appearance, None before)."""
        self.stopping_window: "float | None" = None  # the training window when training stopped
        self.supersample_plan: "tuple[str, float] | None" = None
        """Past ``supersample_from``: what the window leaves the supersampled final evaluation and the wall seconds when
        that was decided (:meth:`_supersample_reserve`); None before."""
        self.validation_seconds = 0.0  # rendering for validations so far
        self.training_stopped_at: "float | None" = None  # wall seconds after start
        self.final_started_at: "float | None" = None  # after the final checkpoint

    # ------------------------------------------------------------------ state
    def state(self) -> dict:
        return {
            "step": self.step,
            "train_seconds": self.train_seconds,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "torch_rng": self.model.generator.get_state(),  # the model's stream (name kept: older checkpoints resume)
            "sampler_rng": self.generator.get_state(),
            "history": self.history,
            **({"error_map": self.sampler.errors.state()} if self.sampler.errors is not None else {}),
            **({"average": self.average.state()} if self.average is not None else {}),
        }

    def resume_from(self, path: Path) -> None:
        """Continue from the checkpoint at ``path``; one that does not fit this model and training is one line."""
        state = load_checkpoint(path)
        load_model_state(self.model, state["model"], path, self.model_name)
        try:
            self._load_training_state(state)
        except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as exc:
            raise NerfpipeError(f"checkpoint does not fit this training ({' '.join(str(exc).split())[:300]})", path) from exc

    def load_state(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self._load_training_state(state)

    def _load_training_state(self, state: dict) -> None:
        """Everything of a checkpoint but the model's tensors: optimiser, random streams, step and history."""
        initial = [group["initial_lr"] for group in self.optimizer.param_groups]
        self.optimizer.load_state_dict(state["optimizer"])  # replaces the group dicts
        for group, lr in zip(self.optimizer.param_groups, initial):
            group["initial_lr"] = lr
        ranks = state.get("ranks", {"sampler_rng": state["sampler_rng"][None], "torch_rng": state["torch_rng"][None]})
        if self.world.rank < len(ranks["sampler_rng"]):  # else a rank the saved run did not have: its fresh streams
            stream = ranks["torch_rng"][self.world.rank].clone()  # own storage: set_state reads from offset 0 (a row crashes it)
            if stream.numel() == self.model.generator.get_state().numel():  # else saved on another device type:
                self.model.generator.set_state(stream)  # that stream cannot go on here, this run's own does
            self.generator.set_state(ranks["sampler_rng"][self.world.rank].clone())
            if self.sampler.errors is not None and "error_map" in ranks:
                self.sampler.errors.load_state(ranks["error_map"][self.world.rank].clone().view(torch.float32))
        if self.sampler.errors is not None and "error_map" in state and "error_map" not in ranks:
            self.sampler.errors.load_state(state["error_map"])  # a checkpoint of one process
        if self.average is not None and "average" in state:  # (a checkpoint without: the average starts anew)
            self.average.load_state(state["average"])
        self.step, self.train_seconds, self.history = state["step"], state["train_seconds"], state["history"]
        self.history["resumed_at"] = [*self.history.get("resumed_at", []), self.step]

    def save(self) -> None:
        """Rank 0 writes the checkpoint, with every rank's random streams (a collective in a group)."""
        ranks = None
        if self.world.active:
            ranks = {"sampler_rng": distributed.gather_bytes(self.generator.get_state()),
                     "torch_rng": distributed.gather_bytes(self.model.generator.get_state())}
            if self.sampler.errors is not None:  # each rank's own map, as bytes
                ranks["error_map"] = distributed.gather_bytes(self.sampler.errors.state().view(torch.uint8))
        if self.world.writer:
            save_checkpoint(self.out / CHECKPOINT, self.state() if ranks is None else {**self.state(), "ranks": ranks})

    def write_config(self) -> None:
        from nerfpipe.data_adapters.colmap import POINTS_MODEL

        extra = {"points": self.scene.meta[POINTS_MODEL]} if POINTS_MODEL in self.scene.meta else {}
        write_json(
            self.out / CONFIG,
            {"data": str(Path(self.scene.source).resolve()), **extra, "model": self.model_name, "model_config": to_dict(self.model_config), "trainer": to_dict(self.cfg)},
        )

    # ------------------------------------------------------------------ loop
    def fire(self, place: Callback) -> None:
        for hook in self.hooks.get(place, []):
            hook(self.step)

    def train_step(self) -> Tensor:
        """One optimiser step; returns the colour MSE of the batch, a 0-dim tensor on the device (reading it
        is a host sync: the loop reads the steps' losses together when it logs them, :meth:`flush_losses`)."""
        self.fire(Callback.BEFORE_TRAIN_ITERATION)
        if self.sync is not None:
            self.sync()  # the hooks' changes (occupancy grid, box) as rank 0 made them
        self.apply_lr()
        batch = self.sampler.sample(self.rays, self.generator)
        sq = self.graph(batch) if self.graph is not None else None
        if sq is None:
            self.optimizer.zero_grad(set_to_none=True)
            sq = self.forward_backward(batch)
        self.sampler.update_errors(sq)
        mse = sq.mean()
        if self.world.active:  # the gradient (and the MSE) over the union of the ranks' rays
            weight = self.rays / self.cfg.rays_per_step
            params = [p for group in self.optimizer.param_groups for p in group["params"]]
            (total,) = distributed.all_reduce_gradients(params, weight, [weight * float(mse)])
            mse = torch.full((), total)
        drop_stale_optimizer_state(self.optimizer)
        self.optimizer.step()
        if self.sync is not None:
            self.sync.mark()
        self.step += 1
        if self.average is not None:
            self.average.update(self.step)
        self.fire(Callback.AFTER_TRAIN_ITERATION)
        return mse

    def forward_backward(self, batch: PixelBatch) -> Float[Tensor, "num_rays"]:
        """The model's outputs and losses for ``batch`` and their gradients, added into ``.grad``; the squared colour
        error of each ray (what a CUDA graph captures: :mod:`nerfpipe.training.cuda_graph`)."""
        outputs = self.model.get_outputs(batch.rays, batch.background)
        losses = self.model.get_losses(outputs, batch.rgb, batch.depth)
        sum(losses.values()).backward()
        return ((outputs.rgb.detach() - batch.rgb) ** 2).mean(-1)

    def clock(self) -> float:
        """Seconds on the configured clock (see :attr:`TrainerConfig.clock`)."""
        if self.cfg.clock == "cpu":
            return time.process_time() / max(torch.get_num_threads(), 1)
        return time.perf_counter()  # "wall": TrainerConfig refuses any other value

    def apply_lr(self) -> None:
        """Set every group's rate from the model's schedule (on the optimiser's own groups: loading a
        checkpoint replaces them, so a model must not keep references to the dicts it handed over)."""
        factor = self.model.lr_factor(self.step)
        for group in self.optimizer.param_groups:
            group["lr"] = group["initial_lr"] * factor

    def wall_elapsed(self) -> float:
        return time.monotonic() - self.started

    def wall_left(self) -> "float | None":
        """Seconds left of the ``time_budget`` (never negative); None without one."""
        return None if self.cfg.time_budget is None else max(0.0, self.cfg.time_budget - self.wall_elapsed())

    def training_window(self) -> "float | None":
        """Wall seconds after the start at which training stops under a ``time_budget`` (the rest is the final phase's:
        :data:`~nerfpipe.training.evaluation.FINAL_SHARE` of it, or what the final evaluation of every view is
        estimated to need (:func:`~nerfpipe.training.evaluation.final_eval_need`) where that is at most
        ``FINAL_MAX_SHARE`` of it; beyond, the final evaluation scores fewer or smaller views in the usual share)."""
        from nerfpipe.training.evaluation import FINAL_MAX_SHARE, FINAL_SHARE, final_eval_need

        budget = self.cfg.time_budget
        if budget is None:
            return None
        reserve = FINAL_SHARE * budget
        need = None if self.world.active else final_eval_need(self)  # torchrun's ranks must agree on the window: the fixed share there
        if need is not None and need <= FINAL_MAX_SHARE * budget:  # else no share fits every view
            reserve = max(reserve, need)
        if need is not None and 0 < self.supersample_from <= self.step:  # past the plateau: anti-aliased scores pay more than steps
            reserve = max(reserve, self._supersample_reserve(budget))
        return budget - reserve

    def _supersample_reserve(self, budget: float) -> float:
        """What the window leaves the supersampled final evaluation past ``supersample_from``, decided at the first
        window there (:attr:`supersample_plan`): ``generous``, :func:`~nerfpipe.training.evaluation.final_eval_need`'s
        reserve (:data:`~nerfpipe.training.evaluation.AVERAGED_RENDER_FACTOR` over) where the time left affords it;
        ``now`` (training stops at once) where it affords only the evaluation's measured cost (averaged parameters'
        rays as dear as the validations', no margin: the validations' time per ray is already 1.1x over the final
        evaluation's, and the final evaluation's probe picks one ray per pixel if 2 x 2 do not fit, so a stop that then
        finds too little time costs only steps past the plateau); ``none`` where not even that: training goes on to the
        window of one ray per pixel, and the final evaluation's probe decides. ``nerfpipe run colmap_mouse
        --time-budget 300`` on a slow hour reached the plateau at 182 s of its 254: the generous reserve (220 s; the 2 x 2
        rays took 43 s in another run) stopped training there, and the 72 s left then did not afford the 2 x 2 rays
        either."""
        from nerfpipe.training.evaluation import final_eval_need

        generous = final_eval_need(self, supersample=True)
        if self.supersample_plan is None:
            elapsed = self.wall_elapsed()
            least = final_eval_need(self, supersample=True, averaged_factor=1.0, margin=1.0)
            self.supersample_plan = ("generous" if elapsed + generous <= budget else "now" if elapsed + least <= budget else "none", elapsed)
        plan, decided_at = self.supersample_plan
        return generous if plan == "generous" else budget - decided_at if plan == "now" else 0.0

    def done(self) -> bool:
        budget, window = self.cfg.train_budget, self.training_window()
        if window is not None:  # under torchrun every rank must stop at the same step: the group's slowest clock
            wall = distributed.maximum(self.wall_elapsed()) if self.world.active else self.wall_elapsed()
        return (self.step >= self.cfg.max_iters or (budget is not None and self.train_seconds >= budget)
                or (window is not None and wall >= window))

    def train(self) -> dict:
        """Train until ``iters`` or ``train_budget``, then validate and write every output.

        Holds the run folder's lock (:func:`nerfpipe.util.runlock.run_lock`): a second training into the
        same folder refuses while this one runs. In a torchrun group every rank calls this; rank 0
        holds the lock and writes, and every rank returns rank 0's metrics."""
        lock = run_lock(self.out) if self.world.writer else contextlib.nullcontext()
        with lock, torch_threads(self.cfg.num_threads):
            metrics = self._train()
        return distributed.broadcast_object(metrics) if self.world.active else metrics

    def _train(self) -> dict:
        from nerfpipe.training import evaluation
        from nerfpipe.util.progress import TrainProgress

        writer = self.world.writer
        if writer:
            self.out.mkdir(parents=True, exist_ok=True)
        resume = self.cfg.resume or self.world.restarts > 0  # torchrun restarted the group: go on from the checkpoint
        checkpoint = find_checkpoint(self.out) if resume else None
        if checkpoint is not None:
            self.resume_from(checkpoint)
        if self.world.active:
            distributed.broadcast_module(self.model)  # identical ranks from the start, whatever each built or read
            self.sync = distributed.BufferSync(self.model)
        if writer:
            self.write_config()
        self.model.train()
        with TrainProgress(self.cfg, self.step, self.train_seconds, self.training_window()) if writer else _Quiet() as bar:
            if self.step == 0 and self.cfg.eval_every and writer and evaluation.validation_due(self):
                evaluation.validate(self, self.cfg.eval_views, supersample=evaluation.INTERMEDIATE_SUPERSAMPLE)  # the starting point of the curves
            while not self.done():
                t0 = self.clock()
                mse = self.train_step()
                self.train_seconds += self.clock() - t0
                if self.world.active:  # one clock for the group, so every rank stops at the same step
                    self.train_seconds = distributed.maximum(self.train_seconds)
                self._losses.append((self.step, self.train_seconds, mse))
                if time.perf_counter() - self._logged_at >= LOG_SECONDS:
                    self.flush_losses(bar)
                self.periodic(evaluation, bar)
                if writer:  # a validation may have changed what the final evaluation needs, and so the window
                    bar.window = self.training_window()
        self.flush_losses(bar)
        self.training_stopped_at = self.wall_elapsed()
        self.stopping_window = self.training_window()
        if self.average is not None and self.average.apply():  # the run ends with the averaged parameters
            self.model.parameters_replaced()
        self.fire(Callback.AFTER_TRAIN)
        self.save()
        self.final_started_at = self.wall_elapsed()
        return evaluation.finish(self) if writer else None

    def flush_losses(self, bar=None) -> None:
        """The training rows of the steps since the last flush into ``history`` (their losses read back from
        the device together: one host sync) and the progress display updated."""
        if not self._losses:
            return
        mses = torch.stack([m.detach().reshape(()).float() for _, _, m in self._losses]).tolist()
        self.history["train"] += [[step, seconds, psnr_from_mse(m)] for (step, seconds, _), m in zip(self._losses, mses)]
        self._losses, self._logged_at = [], time.perf_counter()
        if bar is not None:
            step, seconds, psnr = self.history["train"][-1]
            bar.update(step, seconds, psnr, self.wall_elapsed())

    def periodic(self, evaluation, bar) -> None:
        every, ck = self.cfg.eval_every, self.cfg.checkpoint_every
        if (every and self.step % every == 0) or (ck and self.step % ck == 0):
            self.flush_losses(bar)  # validation and checkpoints see every step's loss
        if every and self.step % every == 0 and not self.done() and self.world.writer and evaluation.validation_due(self):
            psnr, ssim = evaluation.validate(self, self.cfg.eval_views, supersample=evaluation.INTERMEDIATE_SUPERSAMPLE)
            bar.log(f"step {self.step}: val PSNR {psnr:.2f} dB, SSIM {ssim:.3f} ({self.train_seconds:.0f} s training)")
        if ck and self.step % ck == 0:
            self.save()


class _Quiet:
    """The progress display of a rank that does not write (ranks 1 .. N-1 of a group)."""

    def __enter__(self) -> "_Quiet":
        return self

    def __exit__(self, *exc) -> None:
        pass

    def update(self, *args) -> None:
        pass

    def log(self, text: str) -> None:
        pass
