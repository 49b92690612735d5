"""The fast default model: multiresolution grids, an occupancy grid and packed rendering.

Only what the scene needs is modelled and evaluated: the field's finest level resolves one training
pixel and levels too fine to store densely are hashed into tables sized by the scene's pixel count
(memory follows the evidence, not the box's volume); the field lives in the scene box (tightened
to the occupied cells once training has found them), rays are marched only through occupied
cells with a step tied to the grid resolution (a coarser, dilated copy of the occupancy first bounds
the span of each ray worth marching; the sampling starts at one voxel and halves later), a cheap
density-only pass finds where each ray's transmittance has run out (in rounds of a few samples per
ray, so nothing behind an opaque surface is marched or evaluated), and the colour pass runs on the
samples that matter (packed, no padding).

Glossary:
    step_size   distance between samples along rays: ``step_ratio`` of the finest voxel
    preset      capacity (grid resolutions); ``auto`` picks one from image count and size
"""

import math
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import ClassVar
from collections.abc import Callable, Iterator

import torch

from nerfpipe.data.orbit import AROUND_ARC
from nerfpipe.data.rays import RayBundle
from nerfpipe.estimators.occupancy import OccupancyGridConfig, PackedSamples, ray_aabb_intersect
from nerfpipe.fields.background import BackgroundField, BackgroundFieldConfig
from nerfpipe.fields.fast_field import FastField, direction_encoding
from nerfpipe.fields.grid import BLOCK, axis_resolution, needed_blocks
from nerfpipe.fields.plane import PlaneTexture, PlaneTextureConfig
from nerfpipe.functional.gather import equirect_lookup
from nerfpipe.functional.packed import accumulate_packed, composite_packed, distortion_loss_packed, prune_mask, quantile_depth_packed, render_weights_packed
from nerfpipe.functional.volrend import binary_entropy
from nerfpipe.models.base import Callback, Model, ModelSpec, RenderOutputs, SceneInfo
from nerfpipe.util.typing import Float, Int, Tensor

PRESETS: "dict[str, dict]" = {
    "small": dict(levels=(32, 64, 128), feature_channels=4, hidden=64, log2_hashmap_size=None),
    "medium": dict(levels=(32, 64, 128, 256), feature_channels=4, hidden=64, log2_hashmap_size=19, spacing=192),
    "large": dict(levels=(32, 64, 128, 256), feature_channels=4, hidden=64, log2_hashmap_size=None),
    "compact": {},  # sized from the scene: compact_capacity
}
"""Capacity presets: vertices per axis of each grid level along the box's longest side. ``small`` and ``large``: dense
(every vertex stored); ``medium``: levels of more than 2^19 vertices hashed into 2^19 rows; ``auto`` (the default)
picks ``small`` or ``medium`` from the pixel count, and ``compact`` where ``large`` would be (:func:`auto_preset`).
``compact``: a hashed field sized from the scene (:func:`compact_capacity`). ``spacing``: the level whose voxel the
sample spacing (``step_ratio``) is counted in, where finer than the finest level's (None: the finest).

``medium`` was dense to 192 (83.2 MB on blender_lego after the box's tightening) until session 22; with a hashed finest
level of 256 at the same sample spacing (side by side at equal steps; the old medium first): blender_lego (5 views at
400²) 26.24 / 28.93 dB after 300 / 1,000 steps against 26.23 / **29.03** in **23.1 MB**, at 1.15x the seconds per step
(as landed, the spacing 255/191 of a 256-voxel rather than the run's 1.333 / 0.667 ratios: 26.21 / 29.06 in 23.0 MB);
a 23-photo real capture (colmap_mouse's, training images at 800 px, which ``auto`` puts in this tier; 3 held-out views
at 400 px) 23.31 / 22.80 dB after 300 / 600 steps against 23.31 / **22.97**, in 63.7 / 22.0 MB, at 0.170 / 0.160 s
per step (600); lego_200 (a ``small`` scene) with four such levels to 256 at 2^18 rows: 32.63 / 33.39 dB after 3,000
steps (README)."""


LEGACY_CAPACITY: "dict[str, dict]" = {"medium": dict(levels=(32, 64, 128, 192), log2_hashmap_size=0)}
"""Presets as they were before they changed (``medium`` was dense to 192 until session 22), for the runs written then:
:meth:`FastConfig.for_checkpoint`."""


def auto_preset(info: SceneInfo) -> str:
    """Capacity from the scene: more pixels of evidence afford finer grids, and where a dense field would be
    ``large`` (its tables of 256 vertices per side cost their optimizer step more than the hashing costs)
    the compact field takes its place.

    On colmap_mouse (``nerfpipe run --time-budget 300``) the compact field trained more steps in the same
    time (791 against 623: the dense large preset's 36 M parameters cost their optimizer step) to 24.28 dB
    against 24.23 dB, in 22 MB against 137 MB, and its mesh held the mouse alone where the dense one kept
    table fragments. On synthetic objects it shades more samples per ray than the dense presets, so within
    a time budget it trains fewer steps (the demo: 627 against 862, F-score 0.957 against 0.981)."""
    pixels = info.num_images * info.pixels_per_image
    if pixels < 6e6:
        return "small"
    return "medium" if pixels < 24e6 else "compact"


APPEARANCE_FOCAL_SPREAD = 0.3
"""Focal-length spread above which a real capture counts as a photo collection (colour corrections on)."""

APPEARANCE_EXPOSURE_SPREAD = 0.25
"""Exposure spread (``SceneInfo.exposure_spread``, the standard deviation of the training photos' log gains) above
which one camera's session gets per-image colour corrections too, the affine maps alone (no latent codes, no sky
residual): its photos differ in exposure (a phone's auto-exposure turned by a window or a lamp in view), which a field
without them explains with fog. Measured (session 65, :mod:`nerfpipe.data.exposure`, training photos): colmap_mouse
0.210, the same photos with each one's linear light scaled by exp(N(0, 0.25)) / exp(N(0, 0.4)) 0.262 / 0.354 (the
scales recovered photo by photo: correlation 0.99), the fox's sfm folder 0.223 (all photos), a 23-photo cut of
colmap_mouse 0.135, photos_sacre_coeur 0.418 (a collection: on by its focal lengths anyway), photos_sceaux_castle 0.259
over the 9 training photos of session 65's SfM (0.237 over all 11 of session 63's): on, and on that sfm folder
(``nerfpipe run SFM --time-budget 240``) 15.01 dB against 14.25 without (13.21 against 12.73 colour fitted; mesh 92.5
against 93.2 % of the points, violation 0.0124 against 0.0122).
Side by side at equal steps (``python -m benchmarks.side_by_side MOUSE --variants "base:" "aff0:appearance=True
appearance_dim=0 sky_residual=0" --marks 600 --eval-views 7 --eval-max-size 400 --eval-supersample 1 --chunk 50
--pictures P``), without / with the affine maps after 600 steps, the mean correction (``val_psnr``) and the held-out
views' corrections fitted on their left halves (the NeRF-W protocol; without: an affine colour map fitted there):
0.354: 17.28 / **19.55** dB and 21.94 / **24.14** dB, floaters over the table beside the mouse in the first's orbit and
depth pictures, few in the second's; 0.262: 20.36 / **21.11** and 23.17 / **24.14**, the same floaters; colmap_mouse
itself (0.210): **24.88** / 23.96 and 24.16 / 24.00, hence a threshold above it. The codes and the sky residual of
photo collections cost a single session dearly: the fields behind the box and of the table took each photo's light and
their mean rendered a washed-out table: all on (``appearance=True``) 19.16 / 21.06 dB at 0.354 and 20.91 / 20.59 on
colmap_mouse, the affine maps with the sky residual 19.33 / 21.66 and 21.70 / 21.46. See the session-65 row of docs/measured.md."""


def _per_image(values: Float[Tensor, "num_images *rest"], cam_idx: Int[Tensor, "*bs"]) -> Float[Tensor, "num_rays *rest"]:
    """Each ray's row of a per-image table, by ``index_select``: its backward adds each ray's gradient in order
    (``index_add_``), where advanced indexing's (``index_put_`` with ``accumulate``) adds them in whatever order two CPU
    threads reach them: two runs of a photo collection's training differed after one step (session 90: the
    per-image colour corrections by 2e-10, the whole field by 0.6 after 25 steps, and the held-out figures of two
    runs of the same variant by up to 0.9 dB after 900)."""
    return values.index_select(0, cam_idx.reshape(-1).long())


def photo_collection(info: SceneInfo) -> bool:
    """A real capture of photographs from several cameras or zoom settings (:data:`APPEARANCE_FOCAL_SPREAD`): per-image
    colour corrections, latent codes for the surroundings and each photograph's own sky by default."""
    return info.unbounded and info.focal_spread > APPEARANCE_FOCAL_SPREAD


def appearance_by_default(info: SceneInfo) -> bool:
    """Whether a scene gets the per-image colour corrections by default (``FastConfig.appearance``): a photo collection
    (:func:`photo_collection`) or a real capture whose photos differ in exposure (:data:`APPEARANCE_EXPOSURE_SPREAD`;
    the affine corrections alone there)."""
    return photo_collection(info) or (info.unbounded and info.exposure_spread > APPEARANCE_EXPOSURE_SPREAD)


APPEARANCE_DIM = 8
"""``FastConfig.appearance_dim`` of photo collections."""

SKY_RESIDUAL_ROWS = 16
"""``FastConfig.sky_residual`` of photo collections (the per-image colour corrections on): a cell of 11 degrees, a
photograph's sky a few cells wide. Their sky changes from photograph to photograph (clouds, haze); without a place for
that, the box filled with cloud floaters that every novel view shows over its own sky. photos_sacre_coeur (session 62;
``python -m benchmarks.side_by_side SFM --variants "base:" "sky32:sky_residual=32" "sky16:sky_residual=16" --marks 300
600 900 --eval-views 2 --eval-max-size 400 --eval-supersample 1 --chunk 50``, the sfm folders of two ``nerfpipe run``s),
right halves appearance fitted, none / 32 / 16 rows: 14.99 / 15.77 / **15.87** dB after 300 steps, 15.86 / 15.31 /
15.76 after 600, 15.83 / 14.85 / 15.81 after 900 (the other folder, none / 32: 14.29 / 15.84 after 300, 14.33 / 14.41
after 600), at 0.74-0.83x the seconds per step (13-23 samples per ray against 18-28: less fog in the box), the orbit's
sky clearer of cloud floaters with 32 rows than 16, and with 16 than none. End to end (``nerfpipe run SFM --time-budget
270``, the two codes at once, one thread each): see the session-62 row of docs/measured.md."""

SKY_MAP_ROWS = 32
"""``FastConfig.sky_map`` where the sky residual is on (photo collections): rows over the upper hemisphere, a cell of
2.8 degrees. The direction-only background reads the direction through spherical harmonics of degree 3 (a cell of
tens of degrees), and the per-image residual is zero-mean: the sky that the photographs share (clouds, their blue's
gradient) had no place at infinity and went into cloud floaters in the box, which every far orbit frame showed as a
box of cloud. photos_sacre_coeur (session 89; ``python -m benchmarks.side_by_side SFM --variants "base:sky_map=0"
"m64:sky_map=64 sky_map_upper=False" "m32:sky_map=32 sky_map_upper=False" --marks 300 600 900 --eval-views 2
--eval-max-size 400 --eval-supersample 1 --chunk 50``, the sfm folder of a ``nerfpipe run``; ``up32`` / ``up64``: the
upper hemisphere, in a second run of the same folder), right halves appearance fitted after 300 / 600 / 900 steps:
none 15.36 / 15.20 / 15.27 dB (17.1-18.5 samples per ray from 600 steps on), the whole sphere at 64 rows 15.42 /
15.59 / 15.58 (13.3-14.0), at 32 rows 15.44 / 15.45 / 15.58, the upper hemisphere at 32 rows 15.34 / 15.65 /
**15.85** (14.3-15.1), at 64 rows 15.46 / 15.38 / 15.36; on another run's sfm folder none 15.47 / 15.38 / 15.16, the
upper hemisphere at 32 rows 15.45 / **15.55** / **15.68** at 0.92x the seconds per step. The whole sphere also painted the trees and roofs at the
photographs' sides onto infinity, dark blobs low in the far orbit frames; the upper hemisphere keeps the ground
directions to the field behind the box. photos_sceaux_castle (not a photo collection: off by default), the whole
sphere at 64 / 128 rows against none: 14.68 / 14.55 against 15.16 dB after 900 steps (2 views): off there."""
SKY_MAP_FADE = 0.05
"""Height of a direction (its up component) over which :attr:`FastConfig.sky_map` fades in above the horizon (about
3 degrees): no seam at the horizon."""

DENSITY_LEVELS_REAL = 2
"""``FastConfig.density_levels`` of real captures: their density from the two coarsest levels (32 and 64 vertices along the
box), their colour from every level (to 256 on colmap_mouse). On colmap_mouse (side by side, 7 held-out views at 400
px, equal steps) the finer density levels add a speckle of opacity to novel views, not detail: every level / three /
two gave 23.97 / 24.01 / 24.06 dB after 300 steps and 24.35 / 24.39 / 24.43 after 600, at 0.205 / 0.186 / 0.171 s per
step (fewer gathers in the marching's density passes). End to end (``nerfpipe run --time-budget``): colmap_mouse
(300 s) 24.30 -> 24.42 dB (872 / 818 iterations), mesh 95.3 -> 96.2 % of the points within 1 %, free-space violation
0.017 both; ngp_fox (180 s) 26.73 dB after 377 iterations at 0.207 s each (every level: 26.59 after 376 in session 17;
run again here, on a slower machine hour, 25.28 after 264 at 0.253 s), mesh 97.1 % / 0.014. Scenes without the field
behind the box keep every level: the synthetic demo (``nerfpipe demo``, bounded, no such field) with two gave F-score@1 %
0.937 and 25.96 dB against 0.974 and 26.30: its sharp, textured geometry needs the fine density."""

MAX_LEVELS = 5
"""Grid levels of a ``compact`` field at most (each level costs a gather per sample)."""

MAX_FINEST = 256
"""Vertices along the box of a ``compact`` field's finest level at most: samples are spaced by half its voxel,
so a finer level multiplies the samples per ray. colmap_mouse's 1920x1440 photographs would ask for 1024; at 512
its ``nerfpipe run --time-budget 300`` trained 252 steps (val PSNR 22.42 dB), at 256 791 steps (24.28 dB)."""


MAX_FINEST_BOUNDED = 512
"""The finest level of a bounded scene's ``compact`` field at most, where its pixels ask for more than :data:`MAX_FINEST`
(:data:`FINER_FROM` times it or more): a fifth level above the 256-level, hashed, with the samples kept as far apart as that
level's (``spacing``: counted in 256-level voxels), so it adds detail, not samples per ray. The 800² stand-in
(``python -m benchmarks.lego800``, 88 training views, 4 held out at full size, one ray per pixel; side by side at equal
steps): levels to 256 / 512 **26.70 / 26.98 dB** after 1,000 steps and **28.55 / 29.17** after 3,000 (session 25), in
22.9 / 33.4 MB, 512 at 1.26x the seconds per step by 3,000 (1.13x over the first 300, 24.57 against 24.59 dB there:
session 26). Not finer: levels to 1,024 (2^19 rows each) gave 26.92 / 29.01 dB in 42.6 MB at 1.16x the time of 512's
(with the early samples of both in the active levels' voxels, where 512 gave 26.93 / 29.04). Real captures keep
:data:`MAX_FINEST`: their held-out views gain nothing from finer levels (colmap_mouse, session 15)."""

FINER_FROM = 2.0
"""A bounded scene's ``compact`` field gets a level above :data:`MAX_FINEST` where its pixels ask for this many times
as many vertices (lego800's 800 do; 400² views of it, 400, do not: not measured there)."""


FINE_HASH_VERTICES = 2**23
"""Hashed levels with more vertices than this get :data:`LOG2_FINE_ROWS_BOUNDED` rows in a bounded scene whose pixels
ask for that many (``log2_fine_hashmap_size``): where the 800² stand-in's occupied cells (about 12 % of its box) hold
more vertices than 2^19 rows, at its 256- and 512-levels (2 and 16 million there), not at its 128-level (0.25 million)."""

LOG2_FINE_ROWS_BOUNDED = 20
"""Rows (log2) of the finest hashed levels (:data:`FINE_HASH_VERTICES`) of a bounded scene whose training pixels over 32
are 2^20 or more. The 800² stand-in (``python -m benchmarks.lego800``, 4 views at full size, one ray per pixel, side by
side at equal steps, 16,384 rays a step): the 2^19 rows of
session 46 against these, **29.04 / 29.25 dB** after 600 steps (0.3 of the rays from the error map, the average scored) at
1.05x the seconds per step, in 32.7 / 52.8 MB; with CUDA's 0.5 from the error map, 30.24 / **30.54** after 1,000
(unaveraged) and 31.93 / **32.49** after 3,000 (31.83 / 32.40 unaveraged; issue #18's 32 dB), 52.7 MB. Every hashed level at
2^20 rows had scored 32.34 in 63.1 MB (under the goal's 64 by 0.9 MB, and a scene whose 64-level stays dense would pass
it); at this CPU's 4,096 rays 26.84 / **26.98** after 600 (every level at 2^20: 26.91), in 53.1 MB."""


def compact_capacity(info: SceneInfo) -> dict:
    """Capacity from the scene: the finest level resolves one training pixel at the box centre, the
    levels double from 32 vertices (at most :data:`MAX_LEVELS`, spaced evenly in log scale), and levels
    with more vertices than the scene's pixels can inform (a 32nd of them, as a power of two between
    2^17 and 2^19; the synthetic demo at 2^15: F-score 0.859, at 2^18 0.957) are hashed into tables of
    that many rows: memory follows the evidence and the occupied space (hash collisions fall mostly on
    empty cells, which no ray samples), not the box's volume."""
    extent = float((info.aabb[1] - info.aabb[0]).max())
    if info.pixel_footprint > 0:
        needed = extent / info.pixel_footprint
    else:  # no cameras known: as many vertices as the image has pixels along its side
        needed = math.sqrt(max(info.pixels_per_image, 1))
    finest = int(min(max(needed, 128), MAX_FINEST))
    count = min(MAX_LEVELS, 1 + math.ceil(math.log2(finest / 32) - 1e-9))
    growth = (finest / 32) ** (1 / (count - 1))
    levels = tuple(int(round(32 * growth**i)) for i in range(count))
    pixels = max(info.num_images * info.pixels_per_image, 1)
    asked = round(math.log2(pixels / 32))
    log2_rows = int(min(19, max(17, asked)))
    out = dict(levels=levels, feature_channels=4, hidden=64, log2_hashmap_size=log2_rows, log2_fine_hashmap_size=None)
    if not info.unbounded and needed >= FINER_FROM * MAX_FINEST and len(levels) < MAX_LEVELS:
        # a bounded scene whose pixels resolve more than the finest level: one more, hashed, at the spacing of the last
        out.update(levels=levels + (int(min(needed, MAX_FINEST_BOUNDED)),), spacing=levels[-1])
        if asked >= LOG2_FINE_ROWS_BOUNDED:  # and pixels enough for larger tables where the levels collide most
            out.update(log2_fine_hashmap_size=LOG2_FINE_ROWS_BOUNDED)
    return out


SPARSE_MAX_SHARE = 0.5
"""A level is stored sparse only where its blocks (with the free ones) take at most this share of its dense rows at the
tightening. blender_lego's 64-level takes 0.58 there, and by step 300 its blocks took more than the dense level (23.4
against 23.0 MB in all) for 7 % more time per step: it stays dense. lego_200's levels take 0.45 and 0.31."""

SPARSE_CHECK_EVERY = 256
"""Steps between the checks (one host read per level) whether a sparse level ran out of free blocks or holds many no
longer needed (then it is laid out again: :meth:`FastModel._relayout_sparse`)."""

LR_REFERENCE_RAYS = 4096
"""The batch (rays per training step) that :class:`FastConfig`'s learning rates are given for on bounded scenes: this
CPU's default (:data:`nerfpipe.training.trainer.DEVICE_RAYS_PER_STEP`; larger for objects on transparent backgrounds
with larger images: :func:`nerfpipe.training.trainer.default_rays_per_step`); a GPU's 16,384 rays a step take them twice as
large (:func:`batch_lr_scale`). Session 45, side by side at equal steps with 16,384 rays a step (this CPU; one ray per
pixel, the parameter average scored): the 800² stand-in (``python -m benchmarks.lego800``, 4 views at full size) the
rates as given 28.55 / 31.25 dB after 600 / 3,000 steps, twice as large **29.04 / 31.82** (0.80x the seconds per step at
600: 10 samples per ray against 15; three / four times as large 29.00 / 28.80); blender_lego (5 views, full size) after
300 29.09 against **29.65** (0.79x). Only the fine colour features' or only the MLP's twice as large: 28.56 / 28.71
after 600. At 4,096 rays the same doubling loses (lego800 26.78 against 26.84 after 600, lego_200 29.29 against 29.45
after 300): it is the batch, not the rates. Real captures keep their rates (colmap_mouse at 16,384 rays, 7 views at
400 px: 24.76 against 24.82 after 900)."""


def batch_lr_scale(rays_per_step: "int | None", reference: "int | None") -> float:
    """The factor on learning rates given for ``reference`` rays per step at a step of ``rays_per_step`` (Adam's
    square-root rule) where it is larger; 1 at smaller batches (not measured: the rates as given) or where either is None.

    Example:
        >>> batch_lr_scale(16384, 4096), batch_lr_scale(4096, 4096), batch_lr_scale(1024, 4096), batch_lr_scale(16384, None)
        (2.0, 1.0, 1.0, 1.0)
    """
    return math.sqrt(max(rays_per_step / reference, 1.0)) if rays_per_step and reference else 1.0


LR_DECAY_STEPS = 5000
"""Steps over which the learning rates fall tenfold, bounded scenes (``FastConfig.lr_decay_steps``). 2,000 until
session 25; lego_200 (``small``, sparse levels; 10 views, side by side at equal steps) 28.48 / 31.14 / **33.03 dB**
after 300 / 1,000 / 3,000 steps against 28.50 / 31.20 / 32.61, at 0.94x the seconds per step by 3,000 (fewer
samples per ray: 5.9 against 7.1): later steps still learn detail where the faster decay had frozen the grids."""

LR_DECAY_STEPS_REAL = 2000
"""The same for real captures (an SfM scene without alpha): their held-out views stop improving after a few hundred
steps, and the parameter average of the late steps (``TrainerConfig.average``) already smooths them. Faster decays
measured worse on colmap_mouse (session 9: tenfold per 700 / 500 steps, 24.29 / 24.18 dB after 760 steps against
24.33); the slower decay of bounded scenes neither helps nor hurts there (session 25, side by side, 7 views at 400 px:
24.42 / 24.37 dB after 600 / 900 steps against 24.45 / 24.37), so they keep this one."""

ADAM_BETA2 = 0.99
"""Adam's second-moment decay (``FastConfig.adam_beta2``) on bounded scenes: instant-ngp's (torch's default is 0.999),
the moments of a grid row that rays reach now and then following its gradients' scale within a hundred steps instead
of a thousand. Side by side at equal steps (session 51; after the last mark the parameter average scored): lego_200 (10 views) 29.12 / 32.05
-> 29.14 / **32.27 dB** after 300 / 1,000 steps; blender_lego (5 views at 400², 4,096 rays) 26.90 / 30.03 -> 26.93 /
**30.18**; the 800² stand-in (``python -m benchmarks.lego800``, 4 views, 16,384 rays) 30.50 -> **30.71** after 1,000 (30.28
-> 30.45 unaveraged), at 0.94x the seconds per step (8.0 against 9.0 samples per ray)."""

ADAM_BETA2_REAL = 0.999
"""The same for real captures, where 0.99 neither helps nor hurts (session 51, side by side at equal steps, 400 px, the
average scored; 0.999 against 0.99): colmap_mouse (7 views) 24.58 / 24.79 against 24.57 / 24.76 dB after 600 / 900
steps, a posed 23-photo cut of it (3 views) 24.58 against 24.56 after 600, the synthetic room (``nerfpipe synth --scene
room``, 7 views) 30.44 against 30.48: torch's default kept."""

APPEARANCE_FIT_RAYS = 65536
"""Rays of a held-out view's left half that :meth:`FastModel.fitted_appearance` fits its appearance to (a random
subset where there are more: every ray of a 400-pixel view's left half; the box's colour along them is rendered once,
what the appearance changes at every step). 16,384 until session 60: on two Sacre Coeur checkpoints (2 held-out views at
400 px, one ray per pixel, the fit's seed varied) a 600-step one scored 15.15 / 15.45 / 15.34 / 15.48 dB with 16,384
rays and 15.47 / 15.50 / 15.47 / 15.37 with every ray (mean 15.36 -> 15.45), a 451-step one 15.68 / 15.69 / 15.67 and
15.75 / 15.64 / 15.79 (15.68 -> 15.73); a view's fit and right-half render took 16.8 / 15.1 s against 14.5 / 13.4 (two runs, 2 threads, alone)."""

APPEARANCE_FIT_BATCH = 512
"""Rays of each step of that fit (drawn from those :data:`APPEARANCE_FIT_RAYS`). 2,048 until session 46: on a Sacre
Coeur checkpoint (``nerfpipe run --time-budget 300``, its 2 held-out views at 400 px) 1,024 steps of 2,048 / 1,024 /
512 / 256 rays scored 15.965 / 15.986 / 15.962 / 15.951 dB appearance fitted, 512 steps of 2,048 15.762: the steps
matter, not their rays; the fit took 6.0 s against 9.4-10.8 with 2,048 (1.6 s of it the box's colour, rendered once),
so a budget's final evaluation scores more views."""

APPEARANCE_FIT_LR = 0.05
"""Adam's first learning rate in that fit, falling to :data:`APPEARANCE_FIT_FINAL_LR` of it by the last step."""

APPEARANCE_FIT_FINAL_LR = 0.1

FRONT_MIN_IMAGES = 16
"""Training images from which rays that cross the box also read the field behind the box in front of it
(``BackgroundFieldConfig.front`` None, ``FastConfig.front_min_images``: :meth:`FastModel._in_front`). Without it the
field's haze between the cameras and the table lies only around the box, and the box's slab outline shows on the table
in every orbit. With 8 or 9 training images its haze is a poor guess for the rays that cross the box and the held-out
views lose (side by side, the average scored, one ray per pixel): 10 photos kept from a folded reconstruction of
another 23-photo folder (8 training images, 2 views) 19.39 -> 18.86 dB after 1,000 steps, photos_sacre_coeur (8, 2
views) appearance fitted 15.72 -> 15.43 after 700, photos_sceaux_castle (9) 14.85 -> 14.90. From about 20 on it costs
a few hundredths of a dB and removes the outline (session 54, after 900 steps, averaged): a posed 23-photo cut of
colmap_mouse (20 training images, 3 views), seeds 0-3, 24.81 / 24.65 / 24.83 / 24.56 -> 24.59 / 24.65 / 24.83 /
24.46 (colour fitted +0.07 to +0.46), 23 of ngp_fox's photos through SfM (20, 3 views) 25.97 -> 25.92, a synthetic
room of 26 views (23, 3 views; seeds 0 / 1, after 600) 29.77 / 28.23 -> 29.69 / 28.28: 0.06 dB on average (a 14-photo
cut, 12 training images, seeds 0 / 1 after 600: 23.04 / 23.08 -> 23.04 / 22.95; 13 to 15 untried); with 49 to
58 it neither gains nor costs: colmap_mouse 24.78 -> 24.79 after 900, the room scene 30.45 -> 30.44 after 600,
ngp_fox 27.95 -> 27.96 after 600 (session 48, when the rule was 32). Read but not trained by the rays that cross the
box (its gradients stopped there): colmap_mouse 24.83, the room 30.30, ngp_fox 27.96, the 23-photo cut 24.47, the
folded 10 19.10: not kept."""
FRONT_MIN_IMAGES_BEFORE = 32
""":data:`FRONT_MIN_IMAGES` of runs written before session 54 (``FastConfig.OPTIONS_SINCE``)."""
BEHIND_SEEN = 1e-3
"""Transmittance of the box below which a ray's colour behind the box is not computed (it changes the
pixel by less than a thousandth of the colour range)."""


SPARSITY_REAL = 0.01
"""``FastConfig.sparsity_weight`` of real captures of an object photographed from around it (``SceneInfo.arc`` at
least :data:`SPARSITY_MIN_ARC`), however many their images, where the field behind the box (``background_field``) takes
what the photographs show around the object: ``nerfpipe demo`` (a synthetic object on white, 42 training images, no
such field) with 0.01 scored F-score@1 % 0.942 against 0.975 and 26.52 against 26.85 dB (session 34).
Side by side at equal steps (``python -m benchmarks.side_by_side``, val PSNR at 400 px), 0 / 0.01: a 23-photo
cut of colmap_mouse (20 training images, 3 held-out views) 24.64 / 25.09 dB after 300 steps and 24.48 / 24.88
after 600, the occupied share of the box 0.48 / 0.29, the fog walls in front of the mouse in orbit views gone (0.1:
23.92 / 24.13 dB, holes in the mouse). Facades stay at 0: photos_sceaux_castle (10 photos) 13.63 / 13.34 dB after 300
steps (its lawn and facade thinned); photos_sacre_coeur (8) 15.02 / 15.02 dB with the appearance fitted, 11.12 / 11.66
with the mean code.

Whatever the image count (since session 34; before, captures with more than 32 training images kept
``sparsity_weight`` 0 (colmap_mouse, 49 training images, 0 / 0.01 side by side: 24.27 / 24.29 dB after 600 steps and
24.25 / 24.20 after 900; ngp_fox, 58, 25.67 / 25.44 after 300, but its cameras cover 92°: the arc rule, which came
later, keeps it off)). Session 34 measured the cap where a ground truth shows what the fog costs: ``nerfpipe synth
--scene room`` (the composite object on the floor of a room, 56 views, 49 training images, 7 held out, two of them
from 10-15° above the floor), side by side 0 / 0.01: **25.20 / 28.48 dB after 600 steps and 25.46 / 28.96 after
1,000**, the base's low held-out views with grey fog in front of the object (distortion loss 0.001 instead: 26.84 /
27.27); colmap_mouse end to end (``nerfpipe run --time-budget 300``, scored with 2 x 2 rays per pixel) 24.70 against
24.71 dB, mesh 97.6 % / violation 0.015 against 97.5 % / 0.019.

Its price: a plain surface over a plain background (colmap_mouse's lilac end over the white table) renders the same
half transparent in a more saturated colour as opaque, and the loss tips that tie toward transparency: holes there in
the depth renders and the mesh, in training views too (without it the end is whole and the table's slab returns).
Not removed (session 66, README): the table black under the object, each sample's own colour error, the loss counted
in occupied cells only. Fewer since session 66: the loss stops at :data:`SPARSITY_UNTIL`."""

SPARSITY_UNTIL = 300
"""``FastConfig.sparsity_until``'s default: the sparsity loss clears the box's fog in the first steps (the occupancy
grid then stops marching the cells it emptied, which nothing refills) and is off from this step on, before it thins
plain surfaces into holes (they form between steps 300 and 500 on colmap_mouse's lilac end). Side by side at equal
steps (session 66, one ray per pixel, 400 px), on throughout / off from step 300: colmap_mouse (7 views) after 600 /
900 / 1,200 24.876 / 24.866 / 24.900 dB (averaged after 1,200 25.008) against **24.894 / 24.887 / 24.908 (25.037)**,
7.3 / 6.6 / 6.0 against 8.1 / 7.7 / 7.5 samples per ray, the occupied share 0.13 against 0.18 after 900 (steady
from step 600 on: the fog does not return); the posed 23-photo cut (3 views) after 600 / 900 24.763 / 24.529 (24.70)
against 24.718 / 24.610 (**24.74**), the lilac end's holes in the depth renders mostly gone (off from 500: as on
throughout); the room scene (``nerfpipe synth --scene room``, 7 views) after 600 / 1,000 **30.947 / 31.833 (31.40)**
against 30.722 / 31.583 (31.12): its price. End to end (``nerfpipe run --time-budget 300``, alone): colmap_mouse
25.17 dB after 1,470 iterations, mesh 98.2 % / violation 0.021, 8,984 boundary edges and 86 pieces, against **25.20
dB** after 1,408, 98.2 % / 0.021, **6,522** boundary edges and 50 pieces; the cut (``180``) 24.84 after 1,016, 98.8 %
/ 0.018, 11,049 edges against 24.78 after 836, 98.7 % / 0.018, **9,072** edges."""
SPARSITY_NEVER_OFF = 10**9
"""``sparsity_until`` of runs written before session 66 (``FastConfig.OPTIONS_SINCE``): on throughout."""

DISTORTION_REAL = 0.01
"""``FastConfig.distortion_weight`` of real captures modelled with the field behind the box (``background_field``, on by
default for them) with at most :data:`DISTORTION_FULL_IMAGES` training images; with more it falls with their count
squared (:func:`distortion_real`).

The sparsity loss clears the box in its first 300 steps; afterwards a few-view capture grows a translucent slab around
the object, the colour of what lies behind it, which no training photograph sees (a white veil over a white table)
and every orbit view shows (session 76: the posed 23-photo cut of colmap_mouse, 20 training images, occupied share
≈ 0.25 against ≈ 0.17 clean, in 4 of 4 seeds). The distortion loss gathers each ray's weights about one place, and
the slab goes. Side by side at equal steps (``python -m benchmarks.side_by_side``, one ray per pixel, 400 px, the
parameter average scored after the last mark), 0 against 0.01: the posed cut (3 views) seeds 0 / 1 after 900 steps
24.98 / 25.16 against **24.99 / 25.02 dB**, seeds 2 / 3 after 600 24.81 / 24.78 against 24.65 / 24.67, the slab gone
in all four (0.005: seed 0's slab stays, 24.95 / 25.05); 23 of colmap_mouse's photographs through SfM (17 training
images, 3 views) 24.04 against **24.14** after 900; a synthetic room (``nerfpipe synth --scene room --views 26 --size
400x300``, 22 training images, 4 views) 27.03 against **28.93** after 1,000, dark floaters over the floor gone; 0.83 /
0.93 / 0.83 the seconds per step (the posed cut: 7 against 11 samples per ray). With more photographs the veil is thinner and the
loss costs detail: colmap_mouse (49 training images, 7 views) after 900 steps 24.96 against 24.84 at 0.01 and 25.01
at 0.005; end to end (``nerfpipe run --time-budget 300``, alone, the same hour) 25.15 dB with none, 25.01 with
0.0049 (one over the count) and **25.17** with 0.0024 (the square); the room with 56 views (49 training images, 7
views) after 1,000 steps 31.49 against 32.28 at 0.01 and 31.97 at 0.0049. Captures that do not surround their object
(no sparsity loss there) gain or keep (after 600 steps, none against 0.01): 23 of ngp_fox's photos through SfM (20
training images, 97° of azimuth, 3 views) 25.61 against **25.85 dB** at 0.85× the seconds per step;
photos_sacre_coeur's sfm folder (8, 2 views) appearance fitted 15.57 against **15.87** (colour fitted 15.04 / 15.36,
the mean code 11.86 / 12.17 averaged) at 0.85×, fewer cloud pieces in the orbit, another of its sfm folders 15.57
against 15.54; photos_sceaux_castle's (9, 2 views) 15.14 against 15.13. Session 77, more than 0.01: the 26-view room
after 1,000 steps 28.93 (0.01) against 29.25 at 0.02 and 29.31 at 0.04 (0.005: 28.09), but 23 of ngp_fox's photos
25.57 against 25.06 at 0.02 after 600 and the posed cut (seed 0) 24.99 against 24.94 after 900: a synthetic room's
gain that real captures do not share."""
DISTORTION_FULL_IMAGES = 24
"""Training images up to which real captures get all of :data:`DISTORTION_REAL`."""


def distortion_real(num_images: int) -> float:
    """The box's distortion weight of a real capture with ``num_images`` training images: :data:`DISTORTION_REAL` up to
    :data:`DISTORTION_FULL_IMAGES`, then in proportion to one over the count's square (the more photographs see
    through the air around the object, the less a prior has to keep it empty)."""
    return DISTORTION_REAL * min(1.0, DISTORTION_FULL_IMAGES / max(num_images, 1)) ** 2

EVIDENCE_SPARSITY = 0.3
"""``FastConfig.evidence_sparsity_weight`` of real captures with sparse points whose ``sparsity_weight`` is 0 (facades,
walls, photo collections). Their box filled with the sky's fog: the photographs' sky explained by density in the air
in front of the facade and above the roof, where SfM found no point. Session 47, side by side at equal steps (``python -m
benchmarks.side_by_side``, one ray per pixel, 400 px, the average scored after the last mark), 0 / 0.3 / 1.0:
photos_sacre_coeur (a ``nerfpipe run``'s sfm folder, 2 views) appearance fitted 15.58 / 15.56 / 12.64 dB after 400
steps and **15.47 / 15.80 / 13.43 after 700** (colour fitted 15.16 / 15.22 / 14.21, mean code 12.32 / 12.57 / 11.52
averaged) at 1 / 0.63 / 0.58 the time a step (46 / 27 / 24 samples per ray), the church standing clear in the orbit
instead of in a cube of cloud (at 1.0 clearest, but the sky is then all in the field behind the box and the code fitted
on a view's left half paints the right half's sky wrong); another sfm folder of it after 600 steps 14.38 / 14.35 /
14.17 appearance fitted. photos_sceaux_castle (its sfm folder, 2 views) **14.63 / 14.85 / 14.84** after 600 (14.41 /
14.58 / 14.67 after 300) at 0.9 / 0.81 the time a step; ngp_fox (points from the ``sfm`` stage, 9 views) 27.93 /
27.86 / 27.90 after 600, the same renders. An object photographed from around it keeps :data:`SPARSITY_REAL`
everywhere: a weight of 0.1 / 1.0 here ate a hole into colmap_mouse's lilac side, where SfM has no points (session 19)."""
ROBUST_TRIM = 0.1
"""``FastConfig.robust_trim`` of photo collections: a tenth of each batch's rays, those of the largest colour errors,
left out of the colour loss. Their photographs disagree (people on the steps, each one's clouds); fitted anyway, what
no other photograph contradicts went into the box as cloud floaters that every novel view showed over its own sky.
photos_sacre_coeur (session 90; ``python -m benchmarks.side_by_side SFM --variants "base:robust_trim=0"
"t10:robust_trim=0.1" --marks 300 600 900 --eval-views 2 --eval-max-size 400 --eval-supersample 1 --chunk 50
--threads 2``, the sfm folders of two runs of ``nerfpipe run``, deterministic since :func:`_per_image`), right halves
appearance fitted after 300 / 600 / 900 steps: folder A none 15.67 / 15.66 / 15.23 dB, 0.1 15.70 / 15.76 / **15.85**;
folder B none 15.34 / 15.40 / 15.73, 0.1 **15.65** / 15.40 / 15.69 (the mean of the six 15.51 against **15.68**; colour
fitted 14.64 against 14.62, the mean code's 0.1 lower), 13.3-13.9 samples per ray after 900 steps against 14.5-15.7:
the renders' sky around the church clear of the cloud floaters, their depth of the fragments around it. 0.2 (before
:func:`_per_image`, when runs of one variant differed by up to 0.9 dB after 900 steps) scored like 0.1 with a lower
colour-fitted figure (14.46 against 14.63). One camera's session has no such photographs: colmap_mouse (7 views, 600
steps) 24.89 dB against 23.90 with 0.1 and 23.73 with 0.2, its largest errors are the detail still to learn."""

EVIDENCE_MIN_POINTS = 50
"""Sparse points in the box below which the evidence sparsity stays off (too few to say where surfaces are)."""
EVIDENCE_CELLS = 64
"""Cells along the object region's longest side of the grid that records where sparse points lie."""


def evidence_grid(points: Float[Tensor, "num_points 3"], aabb: Float[Tensor, "2 3"], radius: float) -> "Tensor":
    """Cells of a grid over ``aabb`` (:data:`EVIDENCE_CELLS` along its longest side) within ``radius`` object-region
    diagonals of a sparse point (a box dilation of the cells that hold one; bool ``[X, Y, Z]``)."""
    aabb = aabb.float().cpu()
    extent = aabb[1] - aabb[0]
    cell = max(float(extent.max()), 1e-9) / EVIDENCE_CELLS
    shape = [max(1, int(math.ceil(float(e) / cell))) for e in extent]
    idx = ((points.float().cpu() - aabb[0]) / cell).long()
    for axis, n in enumerate(shape):
        idx[:, axis] = idx[:, axis].clamp(0, n - 1)
    grid = torch.zeros(shape)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = 1.0
    r = int(math.ceil(radius * float(extent.norm()) / cell))
    grid = torch.nn.functional.max_pool3d(grid[None, None], 2 * r + 1, stride=1, padding=r)[0, 0]
    return grid > 0


def evidence_at(grid: "Tensor", aabb: Float[Tensor, "2 3"], x: Float[Tensor, "num_points 3"]) -> "Tensor":
    """Whether each point's cell of ``grid`` (:func:`evidence_grid` over ``aabb``) lies near a sparse point (points
    outside ``aabb`` take the nearest cell)."""
    cell = (aabb[1] - aabb[0]).max().clamp(min=1e-9) / EVIDENCE_CELLS
    idx = ((x - aabb[0]) / cell).long().clamp(min=0)
    flat = grid.reshape(-1)
    nx, ny, nz = grid.shape
    i = idx[:, 0].clamp(max=nx - 1) * (ny * nz) + idx[:, 1].clamp(max=ny - 1) * nz + idx[:, 2].clamp(max=nz - 1)
    return flat[i]


SPARSITY_MIN_ARC = AROUND_ARC
"""Azimuth arc the training cameras must cover about the object (``SceneInfo.arc``) for :data:`SPARSITY_REAL` by default:
objects photographed from around them, not facades. 21 of colmap_mouse's photographs on one side of it (167°, 18
training images, 3 held out), 0 / 0.01: 24.85 / 24.77 dB after 300 steps and 25.01 / 25.07 after 600 side by side,
the occupied share 0.47 / 0.26; ``nerfpipe run --time-budget 180``: 25.02 / 25.04 dB (489 / 559 iterations), mesh
98.4 % / 98.6 % of the points within 1 %, free-space violation 0.011 / 0.0095, and the fog slabs along the box's
walls in the orbit's depth gone. The Sceaux castle's photographs cover 63°, the Sacre Coeur's 43°. The arc of
:data:`nerfpipe.data.orbit.AROUND_ARC`, which the novel-view path's rule shares."""


def object_support(info: SceneInfo) -> "tuple[float, float, float, float] | None":
    """The plane an object photographed from around it stands on (``info.support_plane`` where the cameras cover at least
    :data:`SPARSITY_MIN_ARC`): the table texture's plane, the one the mesh stage removes and the mesh figures' object
    points lie above; None for facades and photo collections, or without such a plane."""
    return info.support_plane if info.arc >= SPARSITY_MIN_ARC else None


@dataclass
class FastConfig:
    """The fast grid field (``fast``): the default model of ``nerfpipe train``."""

    OPTIONS_SINCE: ClassVar["dict[str, object]"] = {"behind.front": False, "log2_fine_hashmap_size": 0,
                                                   "front_min_images": FRONT_MIN_IMAGES_BEFORE, "sparsity_until": SPARSITY_NEVER_OFF}
    """Options added since runs were first written (dotted names), with the value such a run was trained as: a run's
    ``config.json`` that lacks one renders, meshes and scores as it trained (:func:`nerfpipe.training.runs.load_run`)."""

    preset: str = "auto"
    """Capacity: ``auto`` (from image count and resolution: ``small``, ``medium``, or ``compact`` where a dense
    field would be ``large``: :func:`auto_preset`), ``small``, ``medium``,
    ``large`` (dense), or ``compact`` (a hashed field sized from the cameras' pixel footprint and the pixel count:
    :func:`compact_capacity`)."""
    levels: "tuple[int, ...] | None" = None
    """Override the preset's grid levels (vertices along the box's longest side)."""
    log2_hashmap_size: "int | None" = None
    """Override the preset's hashing: levels with more than 2^this vertices are hashed into 2^this rows
    (0: every level dense)."""
    log2_fine_hashmap_size: "int | None" = None
    """Override the preset's rows (2^this) of the hashed levels of more than :data:`FINE_HASH_VERTICES` vertices (0: as
    the other hashed levels, ``log2_hashmap_size``)."""
    log2_dense_max: "int | None" = None
    """Levels of at most 2^this vertices are not hashed, even above ``log2_hashmap_size``'s rows: they start dense and are
    stored sparse once the box is tightened (``sparse_min_vertices``). None: ``log2_hashmap_size``. blender_lego (``medium``,
    side by side, 5 views) with its 128-level so (22): 29.14 against 29.05 dB after 1,000 steps, in 35.4 against 23.4 MB,
    at 1.06x the time per step: not a default."""
    feature_channels: "int | None" = None
    """Override the preset's colour features per vertex and level."""
    hidden: "int | None" = None
    """Override the preset's colour MLP width."""
    spacing: "int | None" = None
    """Override the level (vertices along the box) in whose voxel the sample spacing ``step_ratio`` is counted, where
    finer than the finest level's: finer levels then add detail without adding samples. None: the preset's, or the
    finest level's where ``levels`` is given."""
    density_levels: "int | None" = None
    """Density is the sum of the coarsest this many grid levels; colour reads every level. None:
    :data:`DENSITY_LEVELS_REAL` where a field behind the box models the surroundings (``background_field``, on by
    default for real captures), every level otherwise."""
    grid_lr: float = 1.0
    """Adam learning rate of the coarsest grid level's tables, and of the finer levels' density unless
    ``fine_density_lr`` is set (high: each step moves a vertex by about this much)."""
    fine_feature_lr: float = 0.1
    """Adam learning rate of the colour features of every grid level but the coarsest. Adam moves a vertex by about its
    learning rate whatever the size of its gradient, and at ``grid_lr`` (1.0) a fine vertex that few training rays reach
    jumps by whole units. Side by side at equal steps (``python -m benchmarks.side_by_side``), 1.0 against 0.1, at the
    same seconds per step: colmap_mouse (7 held-out views at 400 px, one ray per pixel) 23.79 / 24.27 dB against
    23.97 / 24.35 after 300 / 600 steps; lego_200 27.76 against 27.82 after 300 (0.3: 27.73). End to end, back to back:
    ``nerfpipe run ngp_fox --time-budget 180`` 26.38 dB (385 iterations) against 26.59 (376); ``nerfpipe demo`` 26.47 dB,
    F-score@1 % 0.978 (753) against 26.30, 0.974 (774)."""
    fine_density_lr: "float | None" = None
    """Adam learning rate of the density of every grid level but the coarsest (None: ``grid_lr``). At 1.0, renders of
    colmap_mouse after 600 steps show a salt-and-pepper speckle of opacity on the mouse and the table, in training and
    held-out views alike; 0.1 (with the features' 0.1) smooths it, but the softer surfaces stop rays later (more samples
    per ray), so a time budget buys fewer steps. colmap_mouse side by side after 300 / 600 steps: 24.10 / 24.50 dB at
    1.26x the seconds per step (the features at 1.0 and the density at 0.1: 23.98 / 24.42). End to end with both at 0.1
    against both at 1.0, back to back: ``nerfpipe run colmap_mouse --time-budget 300`` 24.38 dB (649 iterations) against
    24.22 (706), but ``nerfpipe run ngp_fox --time-budget 180`` 25.67 (271) against 26.38 (385), a 23-photo cut of
    colmap_mouse (``--time-budget 180``) 23.19 (340) against 23.28 (460), ``nerfpipe demo`` F-score@1 % 0.958 against
    0.978; lego_200 after 300 steps with its finest level's density and features at 0.1: 27.35 dB against 27.76. For a
    large capture trained to its plateau."""
    mlp_lr: float = 1e-2
    """Adam learning rate of the colour MLP."""
    lr_reference_rays: "int | None" = None
    """The rays per training step the learning rates here are given for: a step of ``R`` rays, more than these,
    multiplies every one of them by ``sqrt(R / lr_reference_rays)`` (Adam's square-root rule: four times the rays
    average out half of the noise of a step's mean gradient, and the steps may be twice as long). None:
    :data:`LR_REFERENCE_RAYS` on bounded scenes, the rates as given at any batch for real captures
    (``SceneInfo.unbounded``); 0: never scaled. See :data:`LR_REFERENCE_RAYS`."""
    adam_beta2: "float | None" = None
    """Adam's second-moment decay for every parameter group (None: :data:`ADAM_BETA2` on bounded scenes,
    :data:`ADAM_BETA2_REAL` for real captures)."""
    lr_decay_steps: "int | None" = None
    """Learning rates fall tenfold every this many steps (exponentially; 0: constant; None: :data:`LR_DECAY_STEPS`, or
    :data:`LR_DECAY_STEPS_REAL` for real captures)."""
    lr_min_factor: float = 0.03
    """Learning rates never fall below this fraction of their start."""
    step_ratio: float = 0.5
    """Sample spacing along rays, in voxels of the finest active level (from ``fine_steps_from`` on)."""
    early_step_ratio: float = 1.0
    """Sample spacing before step ``fine_steps_from``: coarser while the field is still blurry, so the
    first minutes train on about half the samples per ray."""
    fine_steps_from: int = 512
    """Training step from which ``step_ratio`` is used (0: from the start)."""
    occupancy: OccupancyGridConfig = field(default_factory=OccupancyGridConfig)
    """The occupancy grid that skips empty space."""
    init_alpha: float = 0.01
    """Opacity of one step everywhere at the start."""
    coarse_to_fine_every: int = 32
    """Grid levels beyond the first two are switched on one by one every this many steps (0: all at once)."""
    warmup_step_factor: float = 4.0
    """Before the first occupancy update every cell is occupied: march with this many times the step."""
    tighten_step: int = 64
    """Shrink the box to the occupied cells at this step and resample the grids (0: never): the levels keep their
    vertices along the box's longest side, so the voxels get finer and the grids smaller. Only the connected
    pieces holding ``box_min_share`` of the occupied cells count; the floaters that the first steps leave
    around the object would otherwise keep the box whole (lego_200: at step 128 the occupied cells' box was
    the scene box; the pieces' box 1.45 x 2.45 x 2.06 of its 2.9 x 2.9 x 2.9). Side by side at equal steps
    (``python -m benchmarks.side_by_side``): lego_200 after 300 / 600 steps, tightened at step 64 **28.49 /
    30.20 dB** in a 25.5 MB field, against 27.86 / 29.72 dB in 45.7 MB at step 256 with
    every occupied cell (the rule until session 21; at step 128 28.08, at 1.07x the seconds per step); the pieces' box at step 32 / 48 /
    96 / 128: 28.38 / 28.36 / 28.43 / 28.30 dB after 300; a second tightening later lost 0.04-0.3 dB (each
    resampling blurs); colmap_mouse (7 held-out views at 400 px) 24.10 dB after 300 steps against 24.08."""
    sparse_min_vertices: int = 1 << 17
    """When the box is tightened, dense levels of more vertices than this are stored sparse from then on
    (:meth:`~nerfpipe.fields.grid.DenseGridEncoding.sparsify`): only the blocks of 4 x 4 x 4 vertices that a read in the
    occupied cells (dilated by ``sparse_dilation`` cells) reaches, plus ``sparse_headroom`` free blocks that cells
    occupied later take (on the device, at each occupancy refresh; a level out of them, or holding many blocks no
    longer needed, is laid out again at a check every :data:`SPARSE_CHECK_EVERY` steps). Values and gradients where
    the field is read are the dense level's (0: every level stays dense). lego_200 (``small``) at equal steps: 28.50 / 30.19 / 32.61 dB after 300 / 600 / 3,000 steps in 8.46 /
    8.68 / 6.93 MB against 28.49 / 30.20 / 32.63 dB in 25.5 MB dense, at 0.101 against 0.095 s per step (README)."""
    sparse_dilation: int = 0
    """Occupancy cells around the occupied ones whose blocks a sparse level stores too (lego_200 with 1 and 25 % free
    blocks: the same PSNR in 10.8 MB)."""
    sparse_headroom: float = 0.1
    """Free blocks of a sparse level, as a fraction of the blocks stored when it was made sparse (and of those needed
    when it is laid out again)."""
    box_margin: float = 0.05
    """Fraction of the box size added around the occupied cells when tightening."""
    box_min_share: float = 0.01
    """When tightening, the box holds the connected pieces of occupied cells with at least this share of them
    (:meth:`OccupancyGrid.supported_aabb`), not the floaters around them (0: every occupied cell)."""
    min_transmittance: float = 1e-4
    """Early ray termination: samples behind this transmittance are not shaded."""
    min_alpha: float = 1e-4
    """Samples less opaque than this are not shaded (after warm-up)."""
    stop_opacity: float = 0.3
    """Rendered rays count as stopped where their accumulated opacity reaches this (``RenderOutputs.stop_depth``:
    the depth that TSDF meshes fuse). Below 0.5 because a trained surface is a soft shell whose front is where
    the photographs see it: on the synthetic demo 0.3 / 0.4 / 0.5 gave F-score 0.973 / 0.966 / 0.957 and
    free-space violation 0.037 / 0.022 / 0.012; colmap_mouse's violation 0.035 at 0.3 and 0.013 at 0.5."""
    early_termination: bool = True
    """Evaluate the density-only pass in rounds and stop each ray once opaque (False: evaluate every
    marched sample; the same samples are kept either way)."""
    fixed_shapes: "bool | None" = None
    """Train without host syncs but one per step: the density-only pass marches every ray over the longest span
    the box allows in shapes known on the host (``OccupancyGrid.march_until_opaque(fixed_shapes=True)``; the same
    samples are kept), and the field behind the box is computed for every ray. Default: on CUDA, where each read
    back stalls the GPU (and the trainer's CUDA graph needs the step free of them); off on the CPU, where a read back
    costs nothing and the rounds are as fast or faster (session 23, the density at occupied intervals only: lego_200
    side by side 0.113 / 0.118 s per step with rounds / fixed shapes, colmap_mouse 0.201 / 0.243 s)."""
    learned_background: "bool | None" = None
    """Learn the colour behind the box per viewing direction (default: for scenes without alpha, where
    the photographs show more than the box, e.g. COLMAP captures); otherwise the trainer's background."""
    background_field: "bool | None" = None
    """Model what lies outside the box with a coarse field in contracted space (default: for real captures,
    ``SceneInfo.unbounded``); it is rendered behind the box, so the box need not explain floor, walls and
    sky with fog."""
    behind: BackgroundFieldConfig = field(default_factory=BackgroundFieldConfig)
    """The field behind the box (when ``background_field``)."""
    front_min_images: int = FRONT_MIN_IMAGES
    """Training images from which ``behind.front`` None reads the field behind the box in front of it too, for the
    rays that cross the box (:data:`FRONT_MIN_IMAGES`)."""
    support_texture: "bool | None" = None
    """Render the plane the object stands on (``SceneInfo.support_plane``, found in the sparse points) as a texture with
    an opacity (:mod:`nerfpipe.fields.plane`), in front of the field behind the box, from ``behind_from`` on. Default:
    where there is that field and such a plane and the cameras surround the object (``SceneInfo.arc`` at least
    :data:`SPARSITY_MIN_ARC`, the sparsity loss's rule). Side by side at equal steps (7 held-out views at 400 px, one
    ray per pixel, session 35): colmap_mouse 24.37 / 24.41 dB after 600 / 900 steps without, **24.52 / 24.56** with;
    the room scene (``nerfpipe synth --scene room``) 26.27 / 28.48 after 300 / 600 without, **27.69 / 30.71** with,
    its floor sharp to the horizon instead of smeared; a 23-photo cut of colmap_mouse 23.61 / 23.10 against 23.61 /
    23.16; photos_sceaux_castle (2 views, its arc 63 degrees) 14.37 / 14.25 against 14.27 / 14.12 and
    photos_sacre_coeur (appearance fitted) 16.06 / 15.44 against 15.73 / 15.71: hence the arc rule. Not kept:
    the box without density below the plane (the texture alone shows the table there; colmap_mouse 23.98 after 600),
    the field behind the box cut off at the plane (22.38), the plane opaque instead of a sheet (24.26). Since session 36
    the texture lies at its distance among the samples of the field behind the box (a wall or a chair in front of
    where a ray meets the plane hides it; until then it was drawn over all of that field): the room scene 27.69 / 30.71
    → 27.69 / **30.96** after 300 / 600, colmap_mouse 24.52 / 24.56 → 24.46 / 24.53 after 600 / 900, the cut 23.61 /
    23.16 → 23.61 / 23.08. Session 45, not kept: a footprint loss (a training ray meeting the plane within the convex
    hull of the object's sparse points above it, 2 % of the region's diagonal inside its edges, must stop in the box
    before the plane: the mean of ``(1 - opacity before the plane)^2`` over those rays): colmap_mouse 24.59 / 24.65 dB
    (weight 0.01) and 24.52 / 24.66 (0.1) after 600 / 900, averaged 24.73 / 24.68, against 24.62 / 24.72, averaged
    24.78; the lilac end's dark pits go from the renders, its mottled colour stays (session 15's plane prior, over the
    whole box, had cost more)."""
    plane: PlaneTextureConfig = field(default_factory=PlaneTextureConfig)
    """The texture on the support plane (when ``support_texture``)."""
    behind_from: int = 256
    """Training step from which the field behind the box is rendered: the box's own field first explains
    what it can (a coarse field behind it would otherwise paint near geometry on the far shell, and
    the occupancy grid would then cull it from the box for good)."""
    appearance: "bool | None" = None
    """Per-image colour correction (an affine map of RGB per training image, zero-mean over the images,
    so evaluation and novel views use the mean: the identity). Default: for real captures that are
    collections of photographs from several cameras or zoom settings (``SceneInfo.focal_spread`` above
    :data:`APPEARANCE_FOCAL_SPREAD`), where light and exposure vary, and for sessions whose photos differ in exposure
    (``SceneInfo.exposure_spread`` above :data:`APPEARANCE_EXPOSURE_SPREAD`); off for one camera's session under
    steady light, where it measured 0.1-0.3 dB lower on colmap_mouse's held-out views (:func:`appearance_by_default`)."""
    appearance_lr: float = 1e-3
    """Adam learning rate of the per-image colour corrections."""
    appearance_dim: "int | None" = None
    """With the colour corrections on: size of a per-image latent code (GLO, as in NeRF-W) given to the colour
    of what lies outside the object region (the direction-only background and the field behind the box), so
    each photograph's sky and surroundings take its own light and weather without fog in the box; zero-mean
    over the images, so novel views get the mean (0: off). Default: :data:`APPEARANCE_DIM` for photo collections
    (:func:`photo_collection`), 0 for one camera's session (:data:`APPEARANCE_EXPOSURE_SPREAD`). photos_sacre_coeur (8 training photos, 2 held out,
    ``python -m benchmarks.side_by_side``), after 300 / 600 steps, with 8 / without: right halves with the
    appearance fitted 14.74 / 14.33 and 14.69 / 14.35 dB, with an affine colour map fitted 14.88 / 14.62 and
    14.82 / 14.63 dB; with the mean code 11.54 / 12.05 and 11.67 / 12.29 dB."""
    appearance_fit_steps: int = 1024
    """Adam steps that fit a held-out view's correction and code to the left half of its image for the
    ``val_psnr_appearance_fitted`` figure (the NeRF-W protocol; the right half is scored). Each step re-renders only
    what the appearance changes, over the box's colour rendered once (:data:`APPEARANCE_FIT_RAYS`). Sacre Coeur
    (session 27's 330-step run, 2 views at 400 px): 64 / 256 / 1,024 / 4,096 steps 14.97 / 15.34 / **15.78** / 15.86 dB
    in 10 / 11 / 22 / 64 s for both views, right halves rendered included (64 steps re-rendering the box every step, as
    until session 27, at a fixed rate of 0.02: 15.03 dB, 1,024: 15.79 in about 180 s); a first rate of 0.03 / 0.1 / 0.2
    (:data:`APPEARANCE_FIT_LR`) at 1,024 steps 15.70 / 15.34 / 15.30."""
    pose_refine: bool = False
    """Learn a small rigid correction per training image (a rotation about its centre and a translation,
    zero-mean over the images so that the frame stays the one of the held-out views), applied to its rays in
    training: camera refinement, as nerfacto's camera optimiser. Off: on colmap_mouse (7 held-out views after
    600 steps, ``python -m benchmarks.side_by_side``) it scored 24.03 dB (``pose_lr`` 1e-3) and 24.00 dB (3e-4)
    against 24.30 dB without; COLMAP's poses of one phone session are already as good as the field can use. Nor
    the sfm stage's own poses of few photographs (session 77, after 600 steps): 23 of colmap_mouse's photos 24.20
    against 23.62 dB, 23 of ngp_fox's 25.51 against 24.19, at 1.4-1.5x the seconds per step (the held-out views keep
    their poses, so the corrections also move the training views away from them)."""
    sky_residual: "int | None" = None
    """Rows of a per-image colour residual over the sphere of directions (twice as many columns; 0: off), added in
    training to what the direction-only background shows behind everything: each training photograph's clouds and
    haze in its own sky, zero-mean over the images (novel views and renders see the mean: none), instead of as fog in
    the box. None: :data:`SKY_RESIDUAL_ROWS` where the per-image colour corrections are on in a photo collection
    (:func:`photo_collection`), else 0 (one camera's session: see :data:`APPEARANCE_EXPOSURE_SPREAD`)."""
    sky_residual_lr: float = 1e-2
    """Adam learning rate of :attr:`sky_residual`'s textures."""
    sky_map: "int | None" = None
    """Rows of a colour texture over the directions (the upper hemisphere: :attr:`sky_map_upper`; twice as many columns;
    0: off) added, in training and in every render, to what the direction-only background shows behind everything: the
    sky's detail at infinity, shared by every photograph (the background's head reads only a low-degree encoding of the
    direction). None: :data:`SKY_MAP_ROWS` where :attr:`sky_residual` is on, else 0."""
    sky_map_lr: float = 1e-2
    """Adam learning rate of :attr:`sky_map`."""
    sky_map_upper: bool = True
    """The sky map covers the upper hemisphere alone (about the world's up, +z), fading to nothing over the last
    :data:`SKY_MAP_FADE` of height above the horizon; False: the whole sphere."""
    pose_lr: float = 1e-3
    """Adam learning rate of the per-image pose corrections (radians and scene units)."""
    depth_weight: float = 0.1
    """Weight of the sparse-point depth loss on rays through COLMAP track observations (the trainer's
    ``track_rays``): no opacity in front of an observed point, and the ray stops near it when the point
    lies in the object region (0 = off). The posed 23-photo cut of colmap_mouse (session 77, seed 0, the average
    after 900 steps): 0.03 / 0.1 / 0.3 / 1.0 25.07 / 24.99 / 25.01 / 25.02 dB, within the spread of seeds."""
    depth_tolerance: float = 0.006
    """Half-width of the window around an observed point where its ray may stop, as a fraction of the
    object region's diagonal. Below the free-space figure's 1% of the points' extent: colmap_mouse after 800
    steps, TSDF mesh of 16 views, 0.01 / 0.006 gave free-space violation 0.085 / 0.021, points near the mesh
    0.963 / 0.956 and val PSNR 24.29 / 24.25 dB (with the 10% region margin of before: 0.045 / 0.016)."""
    depth_front_margin: float = 2.0
    """The depth loss's free space ends this many ``depth_tolerance`` windows in front of an observed point (1: where
    the window begins). A sparse point of a plain, glossy surface may lie a little behind it; free space right up to
    the window punished the surface itself (pits in colmap_mouse's lilac side, in training views too). colmap_mouse
    side by side at equal steps (``python -m benchmarks.side_by_side``, 7 held-out views at 400 px), val PSNR after
    600 / 900 steps: margin 1 24.45 / 24.63 dB, 2 24.54 / 24.70, 3 24.67 / 24.71, 6 24.51 / 24.71, at the same speed
    a step. ``nerfpipe demo`` in one hour, margin 1 / 2 / 3: F-score@1 % 0.965 / 0.973 / 0.975, free-space violation
    0.032 / 0.041 / 0.046 (the looser the free space, the more fog the mesh keeps: 2 leaves the 0.05 goal room)."""
    distortion_weight: "float | None" = None
    """Weight of the box's distortion loss (mip-NeRF 360's: each training ray's weights gathered toward one place along
    it, so no fog is spread along it; 0 = off). Default: :func:`distortion_real` of the training images for real
    captures with the field behind the box (``background_field``), 0 otherwise (synthetic scenes on a plain
    background: on lego_200 0.01 scored 23.75 / 26.90 dB after 20 / 60 s against 24.02 / 27.21 without, session 2)."""
    tv_weight: float = 0.0
    """Weight of total variation on the finest density grid (0 = off)."""
    sparsity_weight: "float | None" = None
    """Weight of the mean opacity of one marching step at ``sparsity_points`` random points of the box per
    training step: density decays wherever no photograph needs it, also where no training ray passes and
    the photometric loss cannot see fog, while opaque surfaces (whose opacity saturates) keep theirs
    (0 = off). Default: :data:`SPARSITY_REAL` for real captures (``SceneInfo.unbounded``) of an object photographed from
    around it (``SceneInfo.arc`` at least :data:`SPARSITY_MIN_ARC`) and modelled with the field behind the box
    (``background_field``, on by default for real captures), 0 otherwise."""
    sparsity_points: int = 4096
    """Random points per step of the sparsity loss."""
    sparsity_until: "int | None" = None
    """Training step from which the sparsity loss is off (None: :data:`SPARSITY_UNTIL`)."""
    evidence_sparsity_weight: "float | None" = None
    """Weight of the sparsity loss at the box's random points that lie farther than ``evidence_radius`` from every
    sparse point (where SfM saw no surface: the air in front of a facade and above its roof, which the box fills with
    the sky's fog). Default: :data:`EVIDENCE_SPARSITY` for real captures with sparse points where ``sparsity_weight``
    is 0 (facades, walls, photo collections: the cameras on one side), 0 otherwise."""
    evidence_radius: float = 0.05
    """Distance from the nearest sparse point, in object-region diagonals, beyond which the evidence sparsity applies.
    photos_sacre_coeur side by side (session 47, the weight 0.3, 2 views, appearance fitted) after 400 / 700 steps: 0.03
    14.63 / 14.89 dB, **0.05 15.56 / 15.80**, 0.08 14.22 / 15.40 (colour fitted after 700 15.12 / 15.22 / 15.10; 22.5 /
    26.9 / 34.1 samples per ray)."""
    entropy_weight: float = 0.0
    """Weight of the binary entropy of each training ray's opacity in the box (``-a log a - (1-a) log(1-a)``),
    from step ``behind_from`` on when there is a field behind the box: a ray either stops at a surface in the box
    or passes through it to what lies behind, so no veil of fog is left in the box (0 = off). Off: on a 23-photo cut
    of colmap_mouse (``python -m benchmarks.side_by_side``, 3 held-out views) 0 / 0.003 / 0.01 / 0.03 gave 24.48 /
    24.43 / 24.53 / 24.42 dB after 600 steps and the box's fog turned into opaque white slabs rather than clearing
    (occupied share 0.48 / 0.50 / 0.51 / 0.53); :attr:`sparsity_weight` clears it. Session 77, over the sparsity and
    distortion losses (the posed cut, seed 0, the average after 900 steps): 0 / 0.003 / 0.01 / 0.03 24.99 / 24.93 /
    25.00 / 24.97 dB; from 0.01 the lilac end's holes fewer in depth, but opaque white table slabs beside the mouse
    (occupied share 0.17 / 0.19 / 0.22 / 0.24)."""
    robust_trim: "float | None" = None
    """Share of each training batch's rays with the largest colour errors left out of the colour loss, from step
    ``behind_from`` on (a trimmed least squares, as RobustNeRF's: what the other photographs contradict, such as people
    on steps or one photograph's clouds, is fitted by no one; 0: off). None: :data:`ROBUST_TRIM` in a photo collection
    (:func:`photo_collection`), else 0."""

    def __post_init__(self) -> None:
        if self.preset != "auto" and self.preset not in PRESETS:  # checked when configured, not when training starts
            raise ValueError(f"unknown preset {self.preset!r}; choose from auto, {', '.join(PRESETS)}")
        if self.robust_trim is not None and not 0.0 <= self.robust_trim < 1.0:
            raise ValueError(f"robust_trim must lie in [0, 1), got {self.robust_trim}")
        if self.adam_beta2 is not None and not 0.0 <= self.adam_beta2 < 1.0:
            raise ValueError(f"adam_beta2 must lie in [0, 1), got {self.adam_beta2}")
        if self.sky_residual is not None and not (self.sky_residual == 0 or self.sky_residual >= 2):
            raise ValueError(f"sky_residual must be 0 (off) or at least 2 rows, got {self.sky_residual}")
        if self.sky_map is not None and not (self.sky_map == 0 or self.sky_map >= 2):
            raise ValueError(f"sky_map must be 0 (off) or at least 2 rows, got {self.sky_map}")
        if self.appearance_dim is not None and self.appearance_dim < 0:
            raise ValueError(f"appearance_dim must be 0 (off) or more, got {self.appearance_dim}")

    def setup(self, scene_info: SceneInfo) -> "FastModel":
        return FastModel(self, scene_info)

    def for_checkpoint(self, state: dict, scene_info: SceneInfo) -> "FastConfig":
        """This config, or the one a checkpoint's ``state`` (a model state dict) was trained with where its preset has
        changed since (:data:`LEGACY_CAPACITY`): the finest level's table is not hashed as the preset now hashes it.
        Runs written by an earlier nerfpipe then still render, mesh and score. The colour corrections' default is the
        checkpoint's (their rule reads the photos, :data:`APPEARANCE_EXPOSURE_SPREAD`)."""
        trained = {"appearance": "appearance" in state, "appearance_dim": state["image_codes"].shape[1] if "image_codes" in state else 0,
                   "sky_residual": state["sky"].shape[1] if "sky" in state else 0}
        if self.appearance_parts(scene_info) != tuple(trained.values()):  # what it was trained with, whatever the photos say today
            self = replace(self, **{k: v for k, v in trained.items() if getattr(self, k) is None})
        map_rows = state["sky_map"].shape[0] if "sky_map" in state else 0
        if self.sky_map is None and map_rows != self.sky_map_rows(scene_info):
            self = replace(self, sky_map=map_rows)  # what it was trained with (none before session 89)
        cap = self.resolved(scene_info)
        legacy = LEGACY_CAPACITY.get(cap["preset"])
        if legacy is None or self.levels is not None or self.log2_hashmap_size is not None or not cap["log2_hashmap_size"]:
            return self
        finest = state.get(f"field.density_grid.tables.{len(cap['levels']) - 1}")
        if finest is None or finest.shape[0] == 2 ** cap["log2_hashmap_size"]:
            return self
        return replace(self, **legacy)

    def appearance_parts(self, scene_info: SceneInfo) -> "tuple[bool, int, int]":
        """Whether the model has per-image colour corrections, its image codes' size and its sky residual's rows, as
        resolved for a scene (:func:`appearance_by_default`, :func:`photo_collection`)."""
        use_app = appearance_by_default(scene_info) if self.appearance is None else self.appearance
        collection = photo_collection(scene_info)
        code_dim = ((APPEARANCE_DIM if collection else 0) if self.appearance_dim is None else self.appearance_dim) if use_app else 0
        rows = (SKY_RESIDUAL_ROWS if use_app and collection else 0) if self.sky_residual is None else self.sky_residual
        return use_app, code_dim, rows

    def sky_map_rows(self, scene_info: SceneInfo) -> int:
        """The sky map's rows as resolved for a scene (0: none): :data:`SKY_MAP_ROWS` where the sky residual is on."""
        if self.sky_map is not None:
            return self.sky_map
        return SKY_MAP_ROWS if self.appearance_parts(scene_info)[2] > 0 else 0

    def resolved(self, scene_info: SceneInfo) -> dict:
        """The capacity actually used: preset values with overrides applied."""
        name = auto_preset(scene_info) if self.preset == "auto" else self.preset  # a known name: __post_init__
        base = compact_capacity(scene_info) if name == "compact" else PRESETS[name]
        out = dict(base, preset=name)
        out.setdefault("log2_fine_hashmap_size", None)
        for key in ("levels", "feature_channels", "hidden", "log2_hashmap_size", "log2_fine_hashmap_size"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        if self.levels is not None or not out.get("spacing"):  # levels of one's own: spacing in their finest voxel
            out["spacing"] = None
        if self.spacing is not None:
            out["spacing"] = self.spacing
        if not out["log2_hashmap_size"]:
            out["log2_hashmap_size"] = None
        if not out["log2_fine_hashmap_size"] or out["log2_hashmap_size"] is None:
            out["log2_fine_hashmap_size"] = None
        return out


class FastModel(Model):
    """Grid field (dense coarse levels, hashed fine ones) + occupancy grid + packed volume rendering."""

    render_chunk = 16384
    """Rays per forward pass when rendering whole images (:attr:`Model.render_chunk`): each pass has fixed costs (the
    rays' coarse span through the occupancy grid, the rounds of early termination, the field behind the box). On this
    2-core CPU a held-out view of colmap_mouse at 400 x 300 (a run's averaged checkpoint) renders in 2.9-3.0 s against
    3.3-3.4 s with 4,096 rays (32,768: 2.7-3.0), three lego_200 views at 200² in 1.70-1.79 s against 2.08-2.18 (65,536:
    1.63-1.86); the same pixels (within 6e-8). A GPU gains more from fewer, larger launches."""
    averaged = True
    """Averaged on synthetic scenes too (:attr:`Model.averaged`): lego_200 after 300 / 1,000 steps 28.48 / 31.14 dB ->
    28.75 / 31.51 (``TrainerConfig.average_power``)."""
    error_sampled = True
    """A share of the rays from an error map on bounded scenes (:attr:`Model.error_sampled`): lego_200 after 300 steps
    28.75 -> 29.45 dB (``TrainerConfig.error_sampling``)."""
    batch_follows_pixels = True
    """On the CPU, larger batches for objects on transparent backgrounds with larger images (:data:`nerfpipe.training.trainer.CPU_PIXELS_PER_RAY`)."""

    def __init__(self, cfg: FastConfig, info: SceneInfo) -> None:
        super().__init__()
        self.cfg, self.info = cfg, info
        self.capacity = cfg.resolved(info)
        aabb = info.aabb.detach().float()
        self._step = 0
        self.register_buffer("trained_steps", torch.tensor(0))
        self.register_buffer("sparse_pending", torch.tensor(False))
        """Whether the levels are to be made sparse at the next step (:meth:`tighten` leaves it for then)."""
        self._sparse_pending = False
        """:attr:`sparse_pending` on the host (read once when a checkpoint is loaded)."""
        log2_rows = self.capacity["log2_hashmap_size"]
        spacing, finest = self.capacity["spacing"], max(self.capacity["levels"])
        self._spacing_scale = 1.0 if spacing is None else (finest - 1) / (spacing - 1)
        """Sample spacing over ``step_ratio`` finest voxels: a preset's finer finest level keeps the spacing of its
        ``spacing`` level."""
        self.field = FastField(
            aabb, self._resolutions(aabb), self.capacity["feature_channels"], self.capacity["hidden"],
            max_rows=None if log2_rows is None else 2**log2_rows, dense_max=None if cfg.log2_dense_max is None else 2**cfg.log2_dense_max,
            fine_rows=None if self.capacity["log2_fine_hashmap_size"] is None else 2 ** self.capacity["log2_fine_hashmap_size"],
            fine_min_vertices=FINE_HASH_VERTICES,
        )
        self.field.shift = math.log(math.expm1(-math.log1p(-cfg.init_alpha) / self.step_size))
        n_levels = len(self.capacity["levels"])
        self.field.active_levels = min(2, n_levels) if cfg.coarse_to_fine_every > 0 else n_levels
        self.register_buffer("active_levels", torch.tensor(self.field.active_levels))
        real = info.unbounded
        self.lr_decay_steps = (LR_DECAY_STEPS_REAL if real else LR_DECAY_STEPS) if cfg.lr_decay_steps is None else cfg.lr_decay_steps
        """Steps over which learning rates fall tenfold (:attr:`FastConfig.lr_decay_steps` resolved for the scene)."""
        self.adam_beta2 = (ADAM_BETA2_REAL if real else ADAM_BETA2) if cfg.adam_beta2 is None else cfg.adam_beta2
        """Adam's second-moment decay (:attr:`FastConfig.adam_beta2` resolved for the scene)."""
        self.lr_reference_rays = (None if real else LR_REFERENCE_RAYS) if cfg.lr_reference_rays is None else (cfg.lr_reference_rays or None)
        """The batch the learning rates are given for (:attr:`FastConfig.lr_reference_rays` resolved for the scene; None: not scaled)."""
        self.lr_batch_scale = 1.0
        """The factor on the learning rates of the latest :meth:`param_groups` given a batch (the trainer's; in ``metrics.json``)."""
        use_behind = real if cfg.background_field is None else cfg.background_field  # a field behind the box
        density_levels = (DENSITY_LEVELS_REAL if use_behind else n_levels) if cfg.density_levels is None else cfg.density_levels
        self.field.density_levels = max(1, min(density_levels, n_levels))
        self.register_buffer("density_levels", torch.tensor(self.field.density_levels))  # checkpoints keep what they were trained with
        self.grid = cfg.occupancy.setup(aabb)
        self.register_buffer("march_box", aabb.clone())
        use_app, code_dim, rows = cfg.appearance_parts(info)
        self.exposure_spread = info.exposure_spread
        """The training photos' exposure spread the model was built with (``metrics.json``; 0: not measured)."""
        self.appearance = torch.nn.Parameter(torch.zeros(max(info.num_images, 1), 12)) if use_app else None
        self.image_codes = torch.nn.Parameter(torch.zeros(max(info.num_images, 1), code_dim)) if code_dim else None
        self.pose_deltas = torch.nn.Parameter(torch.zeros(max(info.num_images, 1), 6)) if cfg.pose_refine else None
        self.sky = torch.nn.Parameter(torch.zeros(max(info.num_images, 1), rows, 2 * rows, 3)) if rows > 0 else None
        map_rows = cfg.sky_map_rows(info)
        self.sky_map = torch.nn.Parameter(torch.zeros(map_rows, 2 * map_rows, 3)) if map_rows > 0 else None
        self._view_appearance: "Tensor | None" = None
        """A held-out view's fitted correction and code (:meth:`fitted_appearance`), used instead of the mean."""
        learn_bg = (not info.has_alpha) if cfg.learned_background is None else cfg.learned_background
        self.background = self._background_head(code_dim) if learn_bg else None
        self.behind = BackgroundField(cfg.behind, aabb, code_dim) if use_behind else None
        front = info.num_images >= cfg.front_min_images if cfg.behind.front is None else cfg.behind.front
        self.front = use_behind and front
        """Rays that cross the box read the field behind it in front of the box too (:meth:`_in_front`)."""
        around = use_behind and info.arc >= SPARSITY_MIN_ARC  # an object photographed from around it, its surroundings modelled
        use_plane = info.support_plane is not None and (around if cfg.support_texture is None else cfg.support_texture)
        self.plane = PlaneTexture(cfg.plane, torch.tensor(info.support_plane), aabb.mean(0), 0.5 * self._diagonal(aabb), code_dim) if use_plane else None
        if self.plane is not None and info.cameras is not None:
            self.plane.cover(info.cameras)  # the texture only where photographs show the plane (PlaneTextureConfig.min_views)
        self.register_buffer("object_box", aabb.clone(), persistent=False)
        self._object_diagonal = self._diagonal(aabb)
        """The object region's diagonal, read once (not from the device every step)."""
        self.register_buffer("_samples_per_ray", torch.zeros(()), persistent=False)
        """Running mean of the samples shaded per training ray (on the device: a captured step updates it too)."""
        self.register_buffer("_sample_count", torch.zeros(2, dtype=torch.long), persistent=False)
        """The samples the latest training step kept and the occupied intervals it evaluated (0 where not known: the
        rounds), before any were dropped from :attr:`sample_capacity`'s slots."""
        sparse = around  # the field behind the box takes what the box may not keep
        self.sparsity_weight = (SPARSITY_REAL if sparse else 0.0) if cfg.sparsity_weight is None else cfg.sparsity_weight
        self.sparsity_until = SPARSITY_UNTIL if cfg.sparsity_until is None else cfg.sparsity_until
        self.distortion_weight = (distortion_real(info.num_images) if use_behind else 0.0) if cfg.distortion_weight is None else cfg.distortion_weight
        """:attr:`FastConfig.distortion_weight` resolved for the scene."""
        points = info.points if info.points is not None and len(info.points) >= EVIDENCE_MIN_POINTS else None
        evidence = EVIDENCE_SPARSITY if (use_behind and points is not None and self.sparsity_weight == 0) else 0.0
        self.evidence_sparsity_weight = evidence if cfg.evidence_sparsity_weight is None else cfg.evidence_sparsity_weight
        self.robust_trim = (ROBUST_TRIM if photo_collection(info) else 0.0) if cfg.robust_trim is None else cfg.robust_trim
        """:attr:`FastConfig.robust_trim` resolved for the scene."""
        use_evidence = self.evidence_sparsity_weight > 0 and info.points is not None
        self.register_buffer("evidence", evidence_grid(info.points, aabb, cfg.evidence_radius) if use_evidence else None, persistent=False)
        """Cells near a sparse point (:func:`evidence_grid`), where the evidence sparsity is on; None elsewhere."""

    @staticmethod
    def _diagonal(aabb: Float[Tensor, "2 3"]) -> float:
        return float((aabb[1] - aabb[0]).norm())

    @staticmethod
    def _background_head(code_dim: int = 0) -> torch.nn.Module:
        """Direction code (and image code) -> colour offset from the trainer's background; starts at exactly zero."""
        head = torch.nn.Sequential(torch.nn.Linear(16 + code_dim, 32), torch.nn.ReLU(), torch.nn.Linear(32, 3))
        torch.nn.init.zeros_(head[2].weight)
        torch.nn.init.zeros_(head[2].bias)
        return head

    def _resolutions(self, aabb: Float[Tensor, "2 3"]) -> "list[tuple[int, int, int]]":
        extent = aabb[1] - aabb[0]
        return [axis_resolution(extent, int(n)) for n in self.capacity["levels"]]

    @property
    def step_size(self) -> float:
        return self.field.voxel_size(self.field.active_levels - 1) * self._step_ratio() * self._spacing_scale

    def _step_ratio(self) -> float:
        fine = not self.cfg.fine_steps_from or self._step >= self.cfg.fine_steps_from
        return self.cfg.step_ratio if fine else self.cfg.early_step_ratio

    def _march_step(self) -> float:
        warm = self.training and self._step < self.cfg.occupancy.warmup_steps
        return self.step_size * (self.cfg.warmup_step_factor if warm else 1.0)

    # ------------------------------------------------------------------ rendering
    def density_fn(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points"]:
        return self.field.density(points)

    def rgb_fn(self, points: Float[Tensor, "num_points 3"], directions: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 3"]:
        return self.field.rgb(points, directions)

    def _min_alpha(self) -> "float | None":
        """The alpha test is off while the occupancy grid warms up (every cell is occupied then)."""
        return self.cfg.min_alpha if self._step > self.cfg.occupancy.warmup_steps or not self.training else None

    @torch.no_grad()
    def _prune(self, samples: PackedSamples, rays: RayBundle) -> "tuple[PackedSamples, Tensor]":
        """Full density-only pass (the reference of :meth:`_samples`): densities of every marched
        sample, then keep those the ray still reaches that are not transparent."""
        if len(samples) == 0:
            return samples, samples.t_starts
        sigma = torch.cat([self.field.density(p) for p in samples.points(rays.origins, rays.directions).split(1 << 20)])
        keep = prune_mask(sigma, samples.t_ends - samples.t_starts, samples.ray_indices, self.cfg.min_transmittance, self._min_alpha())
        return samples.select(keep), sigma[keep]

    def _samples(self, rays: RayBundle) -> "tuple[PackedSamples, Tensor]":
        """The samples to shade and their densities (no gradients): marched through occupied cells,
        densities evaluated in rounds that stop at opaque rays (or all at once, ``early_termination=False``)."""
        args = (rays.origins, rays.directions, self.info.near, self.info.far, self._march_step())
        if not self.cfg.early_termination:
            return self._prune(self.grid.march(*args, jitter=self.training, aabb=self.march_box, generator=self.generator), rays)

        def sigma_fn(samples: PackedSamples) -> Tensor:
            return self.field.density(samples.points(rays.origins, rays.directions))

        fixed = self._fixed_shapes(rays)
        return self.grid.march_until_opaque(
            *args, sigma_fn, self.cfg.min_transmittance, self._min_alpha(), jitter=self.training, aabb=self.march_box,
            generator=self.generator, fixed_shapes=fixed, capacity=self.sample_capacity if fixed else None,
        )

    def _fixed_shapes(self, rays: RayBundle) -> bool:
        """Whether this training step runs in shapes known on the host (:attr:`FastConfig.fixed_shapes`; rendering
        never does: it marches many more rays, whose longest span would not fit)."""
        return self._fixed_on(rays.origins.device)

    def _fixed_on(self, device: torch.device) -> bool:
        """:meth:`_fixed_shapes` for a training step on ``device``."""
        fixed = device.type == "cuda" if self.cfg.fixed_shapes is None else self.cfg.fixed_shapes
        return fixed and self.training

    def get_outputs(self, rays: RayBundle, background: Float[Tensor, "*bs 3"]) -> RenderOutputs:
        shape = rays.shape
        flat = rays.reshape(-1)
        if self.training and self.pose_deltas is not None:
            flat = self._refined(flat)
        bg = background.expand(*shape, 3).reshape(-1, 3)
        dir_code = direction_encoding(flat.directions)
        t_exit = self._behind_start(flat)
        extras = {}
        samples, weights, t_mids, rgb, depth, acc = self._in_box(flat, dir_code)
        rgb = self._over_surroundings(flat, rgb, acc, bg, dir_code, t_exit, extras)
        if self.training:
            n = len(samples) if samples.count is None else samples.count
            self._samples_per_ray.mul_(0.9).add_(0.1 * n / max(len(flat), 1))  # in place: a captured step updates it
            if samples.count is not None:
                self._sample_count[0].copy_(samples.count)
            else:
                self._sample_count[0].fill_(len(samples))
            if samples.intervals is not None:
                self._sample_count[1].copy_(samples.intervals)
        if self.training and self.cfg.depth_weight > 0:
            extras.update(weights=weights, t_mids=t_mids, ray_indices=samples.ray_indices, t_exit=t_exit)
        if self.training and self.distortion_weight > 0:
            extras["distortion"] = distortion_loss_packed(
                weights, samples.t_starts, samples.t_ends, samples.ray_indices, len(flat)
            ).mean()
        stop = None
        if not self.training:
            stop = quantile_depth_packed(weights, samples.t_starts, samples.t_ends, samples.ray_indices, len(flat), self.cfg.stop_opacity).view(shape)
        return RenderOutputs(
            rgb=rgb.view(*shape, 3), depth=depth.view(shape), acc=acc.view(shape), stop_depth=stop,
            num_samples=len(samples), extras=extras,
        )

    def _over_surroundings(self, rays: RayBundle, rgb: Float[Tensor, "num_rays 3"], acc: Float[Tensor, "num_rays"], bg: Float[Tensor, "num_rays 3"],
                           dir_code: Float[Tensor, "num_rays 16"], t_exit: Float[Tensor, "num_rays"], extras: dict) -> Float[Tensor, "num_rays 3"]:
        """The box's colour ``rgb`` (over black, opacity ``acc``) over what lies outside it (the direction-only
        background over ``bg``, the field behind the box), through the image's colour correction: all that the
        per-image appearance changes (:meth:`fitted_appearance` fits it on the box's colour computed once)."""
        codes = self._image_codes(rays)
        if self.background is not None:
            head_in = dir_code if codes is None else torch.cat([dir_code, codes], dim=-1)
            bg = (bg + self.background(head_in)).clamp(0.0, 1.0)
        if self.sky_map is not None:
            bg = bg + self._sky_map(rays.directions.reshape(-1, 3))
        if self.sky is not None and self.training:
            bg = bg + self._sky_residual(rays)
        if self.sky is not None or self.sky_map is not None:
            bg = bg.clamp(0.0, 1.0)
        beyond = self._step >= self.cfg.behind_from or not self.training
        if self.behind is not None and beyond:  # the table (the plane's texture) at its distance among what lies behind the box
            layer = self.plane.layer(rays.origins, rays.directions, codes) if self.plane is not None else None
            bg = self._behind(rays, dir_code, t_exit, bg, acc, extras, codes, layer)
        elif self.plane is not None and beyond:
            bg = self.plane(rays.origins, rays.directions, bg, codes)
        rgb = rgb + (1.0 - acc)[:, None] * bg  # over the background, as composite_packed does
        if self.appearance is not None and (self.training or self._view_appearance is not None):
            rgb = self._corrected(rgb, rays.cam_idx)
        return rgb

    def graph_key(self) -> "tuple | None":
        """The Python-level state a training step branches on and the tensors it reads (see ``Model.graph_key``):
        in shapes known on the host every step can be captured; with rounds of early termination (the CPU's) none."""
        if not (self._fixed_on(self.march_box.device) and torch.is_grad_enabled() and self.cfg.early_termination) or self._view_appearance is not None:
            return None
        step = self._march_step()
        late = self.behind is not None or self.plane is not None or self.robust_trim > 0
        flags = (late and self._step >= self.cfg.behind_from, self._sparsity_on())
        where = tuple((t.data_ptr(), tuple(t.shape)) for t in (*self.parameters(), *self.buffers()))
        return (step, self.step_size, self.grid.max_intervals(step), self._min_alpha(), self.field.active_levels,
                self.field.density_levels, *flags, where)

    def sample_count(self) -> "Tensor | None":
        return self._sample_count

    def _behind(self, rays: RayBundle, dir_code, t_exit, bg, acc, extras: dict, codes=None, layer=None) -> Float[Tensor, "num_rays 3"]:
        """The colour behind the box for every ray, computed only where the box lets ``BEHIND_SEEN`` of it
        through (``acc``: the box's opacity); the others keep ``bg``, which they do not show. ``layer``: the support
        plane's texture (:meth:`PlaneTexture.layer`), composited at its distance among the field's samples."""
        if self._fixed_shapes(rays):  # every ray: which ones the box lets through would be read back
            behind = self.behind(rays.origins, rays.directions, dir_code, t_exit, bg, generator=self.generator, codes=codes, layer=layer)
            self._behind_extras(behind, extras)
            return self._in_front(rays, dir_code, behind.rgb, codes, layer)
        seen = ((1.0 - acc.detach()) > BEHIND_SEEN).nonzero()[:, 0]
        if len(seen) == 0:
            return bg
        sub, sub_codes = rays[seen], None if codes is None else codes[seen]
        sub_layer = None if layer is None else tuple(x[seen] for x in layer)
        behind = self.behind(sub.origins, sub.directions, dir_code[seen], t_exit[seen], bg[seen], generator=self.generator,
                             codes=sub_codes, layer=sub_layer)
        self._behind_extras(behind, extras)
        return bg.index_put((seen,), self._in_front(sub, dir_code[seen], behind.rgb, sub_codes, sub_layer))

    def _in_front(self, rays: RayBundle, dir_code, rgb: Float[Tensor, "num_rays 3"], codes=None, layer=None) -> Float[Tensor, "num_rays 3"]:
        """``rgb`` (what lies behind the box) under the field's part in front of the box, for the rays that cross the
        box: from the near bound, where the samples of a ray that misses the box begin, to where the ray enters the
        box or meets the support plane (:meth:`BackgroundField.front`; ``BackgroundFieldConfig.front``).

        It is composited behind the box's content, with what lies behind the box: a ray that the box lets through
        sees the surroundings' field along all of its length outside the box, as its neighbour that misses the box
        does (without it the box's outline showed on the table in every orbit: the field's haze between the cameras
        and the table lay only around the box), and the field never veils what the box holds. colmap_mouse side by
        side (7 views at 400 px, one ray per pixel) after 600 / 900 steps: 24.62 / 24.72 dB, averaged 24.78, without;
        24.72 / 24.73, averaged **24.79**, with (colour fitted 23.99 → 24.15); composited in front of the box's content
        (physically in order) 24.54 / 24.60, averaged 24.67: the haze then veils the mouse. On where the capture has
        :data:`FRONT_MIN_IMAGES` training images (``self.front``; the other scenes' figures there)."""
        if not self.front:
            return rgb
        near = torch.full_like(rays.origins[:, 0], self.info.near)
        t_in, t_out = ray_aabb_intersect(rays.origins, rays.directions, self.object_box)
        t_end = torch.where(t_out >= t_in, t_in, near)
        if layer is not None:  # the plane hides what lies behind it
            t_end = torch.where(layer[0] > 0, torch.minimum(t_end, layer[0]), t_end)
        if self._fixed_shapes(rays):
            f_rgb, f_trans = self.behind.front(rays.origins, rays.directions, dir_code, near, t_end, generator=self.generator, codes=codes)
            return f_rgb + f_trans[:, None] * rgb
        some = (t_end > near).nonzero()[:, 0]
        if len(some) == 0:
            return rgb
        f_rgb, f_trans = self.behind.front(rays.origins[some], rays.directions[some], dir_code[some], near[some], t_end[some],
                                           generator=self.generator, codes=None if codes is None else codes[some])
        return rgb.index_put((some,), f_rgb + f_trans[:, None] * rgb[some])

    @staticmethod
    def _behind_extras(behind, extras: dict) -> None:
        if behind.distortion is not None:
            extras["behind_distortion"] = behind.distortion.mean()
        if behind.proposal is not None:
            extras["behind_proposal"] = behind.proposal.mean()

    def _behind_start(self, rays: RayBundle) -> Float[Tensor, "num_rays"]:
        """Where each ray leaves the object region (rays that miss it: the near bound)."""
        t_in, t_out = ray_aabb_intersect(rays.origins, rays.directions, self.object_box)
        return torch.where(t_out >= t_in, t_out, torch.zeros_like(t_out)).clamp(min=self.info.near)

    @property
    def appearance_fit_steps(self) -> int:
        """Steps of the held-out views' appearance fit; 0 without image codes: the affine correction alone, fitted to a
        left half, is the least-squares map of ``val_psnr_colour_fitted`` (a session with colour corrections,
        :data:`APPEARANCE_EXPOSURE_SPREAD`: on colmap_mouse's photos scaled to a 0.354 spread the fit gave 24.25 dB
        against the least squares' 24.08, and took 66 s of a 300 s run's final evaluation for its 7 views)."""
        return self.cfg.appearance_fit_steps if self.appearance is not None and self.image_codes is not None else 0

    @contextmanager
    def fitted_appearance(self, rays: RayBundle, rgb: Float[Tensor, "num_rays 3"], background: Float[Tensor, "3"],
                          steps: "int | None" = None) -> Iterator[bool]:
        """Within the block (evaluation), render with the colour correction and image code fitted by Adam to
        ``rgb`` along ``rays`` (``steps`` steps, default ``appearance_fit_steps``, of up to :data:`APPEARANCE_FIT_BATCH` of them, everything
        else frozen), instead of the mean. Yields False, fitting nothing, without per-image appearance or without image
        codes (:attr:`appearance_fit_steps`)."""
        if self.appearance is None or self.image_codes is None:
            yield False
            return
        flat, target = rays.reshape(-1), rgb.reshape(-1, 3).to(rays.origins)
        background = background.to(target)
        size = 12 + (0 if self.image_codes is None else self.image_codes.shape[1])  # the correction, then the code
        vec = torch.zeros(size, device=flat.device, requires_grad=True)
        steps = self.cfg.appearance_fit_steps if steps is None else steps
        opt = torch.optim.Adam([vec], lr=APPEARANCE_FIT_LR)
        decay = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: APPEARANCE_FIT_FINAL_LR ** (k / max(steps - 1, 1)))
        frozen = [p for p in self.parameters() if p.requires_grad]
        gen = torch.Generator(device=flat.device).manual_seed(0)
        was_training = self.training
        self.eval()
        try:
            for p in frozen:
                p.requires_grad_(False)
            with torch.no_grad():  # what the appearance does not change, once: the box's colour and opacity
                keep = torch.randperm(len(flat), generator=gen, device=flat.device)[:APPEARANCE_FIT_RAYS]
                flat, target = flat[keep], target[keep]
                dir_code, t_exit = direction_encoding(flat.directions), self._behind_start(flat)
                *_, box_rgb, _, box_acc = self._in_box(flat, dir_code)
            self._view_appearance = vec
            with torch.enable_grad():
                for _ in range(steps):
                    i = torch.randint(len(flat), (min(APPEARANCE_FIT_BATCH, len(flat)),), generator=gen, device=flat.device)
                    out = self._over_surroundings(flat[i], box_rgb[i], box_acc[i], background.expand(len(i), 3), dir_code[i], t_exit[i], {})
                    loss = torch.mean((out - target[i]) ** 2)
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
                    decay.step()
            self._view_appearance = vec.detach()
            yield True
        finally:
            for p in frozen:
                p.requires_grad_(True)
            self._view_appearance = None
            self.train(was_training)

    def _in_box(self, rays: RayBundle, dir_code: Float[Tensor, "num_rays 16"]) -> tuple:
        """What the box renders along ``rays`` (``dir_code``: their :func:`direction_encoding`): its samples, their
        weights and midpoints, and the box's colour over black, depth and opacity, which :meth:`get_outputs` composites
        over the surroundings (:meth:`_over_surroundings`)."""
        samples, sigma = self._samples(rays)
        corners = self.field.corners(samples.points(rays.origins, rays.directions))
        if torch.is_grad_enabled():  # the pruning pass ran without gradients: evaluate again with them
            sigma = self.field.density_from_corners(corners)
        rgbs = self.field.rgb_from_corners(corners, dir_code[samples.ray_indices])
        weights, _ = render_weights_packed(sigma, samples.t_ends - samples.t_starts, samples.ray_indices)
        t_mids = 0.5 * (samples.t_starts + samples.t_ends)
        rgb, depth, acc = composite_packed(weights, rgbs, t_mids, samples.ray_indices, rays.origins.new_zeros(len(rays), 3))
        return samples, weights, t_mids, rgb, depth, acc

    def _refined(self, rays: RayBundle) -> RayBundle:
        """Training rays through their image's pose correction (zero-mean over the images): directions rotated
        about the camera centre, origins moved."""
        from dataclasses import replace

        delta = self.pose_deltas - self.pose_deltas.mean(0, keepdim=True)
        w = delta[:, :3]
        zero = torch.zeros_like(w[:, 0])
        skew = torch.stack([zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], dim=-1).view(-1, 3, 3)
        rot = _per_image(torch.linalg.matrix_exp(skew), rays.cam_idx)
        directions = (rot @ rays.directions[:, :, None])[:, :, 0]
        return replace(rays, origins=rays.origins + _per_image(delta[:, 3:], rays.cam_idx), directions=directions)

    def _sky_map(self, directions: Float[Tensor, "num_rays 3"]) -> Float[Tensor, "num_rays 3"]:
        """:attr:`FastConfig.sky_map` at each direction."""
        if not self.cfg.sky_map_upper:
            return equirect_lookup(self.sky_map, directions)
        fade = (directions[:, 2:3] * (1.0 / SKY_MAP_FADE)).clamp(0.0, 1.0)
        return equirect_lookup(self.sky_map, directions, polar_max=math.pi / 2) * fade

    def _sky_residual(self, rays: RayBundle) -> Float[Tensor, "num_rays 3"]:
        """Each training ray's image's residual (:attr:`FastConfig.sky_residual`) at its direction, bilinear over an
        equirectangular grid about the world's z axis (:func:`~nerfpipe.functional.gather.equirect_lookup`)."""
        return equirect_lookup(self.sky - self.sky.mean(0, keepdim=True), rays.directions.reshape(-1, 3), rays.cam_idx.reshape(-1))

    def _image_codes(self, rays: RayBundle) -> "Float[Tensor, 'num_rays code_dim'] | None":
        """Each ray's image code: its training image's (zero-mean over the images) in training, else a fitted
        view's (:meth:`fitted_appearance`) or the mean (zero); None without codes."""
        if self.image_codes is None:
            return None
        if self.training:
            return _per_image(self.image_codes - self.image_codes.mean(0, keepdim=True), rays.cam_idx)
        code = self.image_codes.new_zeros(self.image_codes.shape[1]) if self._view_appearance is None else self._view_appearance[12:]
        return code.expand(len(rays), -1)

    def _corrected(self, rgb: Float[Tensor, "num_rays 3"], cam_idx) -> Float[Tensor, "num_rays 3"]:
        """Colours through their image's affine correction (codes zero-mean over images), or a fitted view's
        (:meth:`fitted_appearance`) while there is one."""
        if self._view_appearance is None:
            codes = self.appearance - self.appearance.mean(0, keepdim=True)
            p = _per_image(codes, cam_idx)
        else:
            p = self._view_appearance[:12].expand(len(rgb), -1)
        matrix = p[:, :9].view(-1, 3, 3) + torch.eye(3, device=rgb.device, dtype=rgb.dtype)
        return (matrix @ rgb[:, :, None])[:, :, 0] + p[:, 9:]

    def get_losses(
        self, outputs: RenderOutputs, target_rgb: Float[Tensor, "*bs 3"], target_depth: "Float[Tensor, '*bs'] | None" = None
    ) -> "dict[str, Tensor]":
        if self.robust_trim > 0 and self.training and self._step >= self.cfg.behind_from:
            errors = ((outputs.rgb - target_rgb) ** 2).reshape(-1, 3).sum(-1)
            kept, seen = max(1, int(len(errors) * (1.0 - self.robust_trim))), errors.detach()
            inlier = seen <= seen.kthvalue(kept).values
            losses = {"rgb": (errors * inlier).sum() / (3 * kept)}
        else:
            losses = {"rgb": torch.mean((outputs.rgb - target_rgb) ** 2)}
        if target_depth is not None and "weights" in outputs.extras:
            losses["depth"] = self.cfg.depth_weight * self._depth_loss(outputs.extras, target_depth.reshape(-1))
        if "distortion" in outputs.extras:
            losses["distortion"] = self.distortion_weight * outputs.extras["distortion"]
        if "behind_distortion" in outputs.extras:
            losses["behind_distortion"] = self.cfg.behind.distortion_weight * outputs.extras["behind_distortion"]
        if "behind_proposal" in outputs.extras:
            losses["behind_proposal"] = self.cfg.behind.proposal_weight * outputs.extras["behind_proposal"]
        if self.cfg.entropy_weight > 0 and self.training and (self.behind is None or self._step >= self.cfg.behind_from):
            losses["entropy"] = self.cfg.entropy_weight * binary_entropy(outputs.acc).mean()
        if self.training and self._sparsity_on():
            losses["sparsity"] = self.sparsity_weight * self._sparsity()
        if self.evidence_sparsity_weight > 0 and self.evidence is not None and self.training:
            losses["evidence_sparsity"] = self.evidence_sparsity_weight * self._sparsity(away_from_points=True)
        if self.cfg.tv_weight > 0 and self.training:
            losses["tv"] = self.cfg.tv_weight * self.field.density_tv(1 << 16, self.generator)
        return losses

    def _sparsity_on(self) -> bool:
        """Whether this step has the sparsity loss (its weight, until :attr:`sparsity_until`)."""
        return self.sparsity_weight > 0 and self._step < self.sparsity_until

    def _sparsity(self, away_from_points: bool = False) -> Float[Tensor, ""]:
        """Mean opacity of one marching step at uniform random points of the marched box (``away_from_points``: counted
        only at those farther than ``evidence_radius`` from every sparse point, :attr:`evidence`)."""
        lo, hi = self.march_box[0], self.march_box[1]
        u = torch.rand(self.cfg.sparsity_points, 3, device=lo.device, generator=self.generator)
        x = lo + u * (hi - lo)
        opacity = -torch.expm1(-self.field.density(x) * self.step_size)
        if away_from_points:
            opacity = opacity * ~evidence_at(self.evidence, self.object_box, x)
        return opacity.mean()

    def _depth_loss(self, extras: dict, target: Float[Tensor, "num_rays"]) -> Float[Tensor, ""]:
        """Mean over rays with a target of: the opacity in front of the observed point, plus, when the
        point lies in the object region, the share of the ray not stopped within the tolerance of it."""
        has = ~torch.isnan(target)  # (masked sums, not a branch or a boolean index: no host sync)
        w, t, ri = extras["weights"], extras["t_mids"], extras["ray_indices"]
        d = target.nan_to_num(0.0)
        eps = self.cfg.depth_tolerance * self._object_diagonal
        d_s = d[ri]
        front = w * (t < d_s - self.cfg.depth_front_margin * eps)
        window = w * ((t - d_s).abs() <= eps)
        sums = accumulate_packed(torch.stack([front, window], dim=-1), ri, len(target))
        inside = (d < extras["t_exit"]).to(w.dtype)
        per_ray = sums[:, 0] + inside * (1.0 - sums[:, 1])
        return torch.where(has, per_ray, 0.0).sum() / has.sum().clamp(min=1)

    # ------------------------------------------------------------------ training hooks
    def callbacks(self) -> "dict[Callback, list[Callable[[int], None]]]":
        return {Callback.BEFORE_TRAIN_ITERATION: [self._before_step]}

    def _before_step(self, step: int) -> None:
        self._step = step
        if self._sparse_pending:
            self._sparsify()
            self._sparse_pending = False
            self.sparse_pending.fill_(False)
        self.trained_steps.fill_(step)
        every, n = self.cfg.coarse_to_fine_every, len(self.field.density_grid.resolutions)
        self.field.active_levels = min(n, 2 + step // every) if every > 0 else n
        self.active_levels.fill_(self.field.active_levels)
        occ = self.cfg.occupancy
        if step >= occ.warmup_steps and step % occ.update_every == 0:
            if step % SPARSE_CHECK_EVERY == 0:
                self._relayout_sparse()
            self.grid.update(self.field.density, self.step_size, generator=self.generator, rotation=step // occ.update_every)
            self.march_box.copy_(self.grid.occupied_aabb())
            self._grow_sparse()
        if self.cfg.tighten_step and step == self.cfg.tighten_step:
            self.tighten()

    @torch.no_grad()
    def parameters_replaced(self) -> None:
        """The occupancy grid and the marching box from the new field: every cell refreshed, its running density kept
        (an average of the parameters holds no density where the last steps had none)."""
        self.grid.update(self.field.density, self.step_size, full=True, generator=self.generator)
        self.march_box.copy_(self.grid.occupied_aabb())

    def lr_factor(self, step: int) -> float:
        """Exponential decay: tenfold every ``lr_decay_steps``, floored at ``lr_min_factor``."""
        if not self.lr_decay_steps:
            return 1.0
        return max(self.cfg.lr_min_factor, 0.1 ** (step / self.lr_decay_steps))

    @torch.no_grad()
    def tighten(self) -> None:
        """Shrink the field's box to the occupied cells (plus a margin) and resample its grids."""
        if self._sparse_levels():
            raise RuntimeError("the box is tightened once, before its levels are stored sparse")
        box = self.grid.supported_aabb(self.cfg.box_min_share)
        margin = self.cfg.box_margin * (box[1] - box[0])
        old = self.field.aabb
        box = torch.stack([torch.maximum(box[0] - margin, old[0]), torch.minimum(box[1] + margin, old[1])])
        resolutions = self._resolutions(box)
        for grid in (self.field.density_grid, self.field.feature_grid):
            for i, (table, res) in enumerate(zip(grid.tables, resolutions)):
                if grid.hash_rows[i] is None:  # hashed levels keep their lattice (it spans the first box)
                    table.data = self._resample(table.data, grid.resolutions[i], old, box, res)
                    grid.resolutions[i] = res
        self.field.aabb.copy_(box)
        self.grid.aabb.copy_(box)
        self.grid.density.zero_()
        self.grid.update(self.field.density, self.step_size, full=True, generator=self.generator)
        self.march_box.copy_(self.grid.occupied_aabb())
        self._sparse_pending = True  # at the next step's start, from this occupancy as processes trained together share it
        self.sparse_pending.fill_(True)

    def _needed_blocks(self, levels: "list[int]") -> "list[Tensor]":
        """The blocks of some levels that reads in the occupied cells reach (:func:`~nerfpipe.fields.grid.needed_blocks`;
        the occupancy grid and the field share the box once it is tightened)."""
        r = self.grid.cfg.resolution
        resolutions = [self.field.density_grid.resolutions[lv] for lv in levels]
        return needed_blocks(self.grid.binary.view(r, r, r), resolutions, self.cfg.sparse_dilation) if levels else []

    def _sparsify(self) -> None:
        """Store the dense levels above :attr:`FastConfig.sparse_min_vertices` sparse (both grids alike: they share
        their corners). Run at the start of the step after the tightening, from the occupancy as it stands then: under
        torchrun rank 0's, which every process received after the tightening's step, so every process's tables
        take the same shapes."""
        if not self.cfg.sparse_min_vertices:
            return
        grids = (self.field.density_grid, self.field.feature_grid)
        levels = [
            lv for lv, res in enumerate(grids[0].resolutions)
            if grids[0].hash_rows[lv] is None and not grids[0].sparse(lv) and math.prod(res) > self.cfg.sparse_min_vertices
        ]
        for level, blocks in zip(levels, self._needed_blocks(levels)):
            rows = int(blocks.sum()) * (1 + self.cfg.sparse_headroom) * BLOCK**3
            if rows > SPARSE_MAX_SHARE * math.prod(grids[0].resolutions[level]):
                continue  # most of the level is needed: blocks would save little memory and cost their index arithmetic
            for grid in grids:
                grid.sparsify(level, blocks, self.cfg.sparse_headroom)

    def _sparse_levels(self) -> "list[int]":
        """The levels stored sparse (the density and feature grids alike)."""
        return [lv for lv in range(len(self.field.density_grid.resolutions)) if self.field.density_grid.sparse(lv)]

    def _grow_sparse(self) -> None:
        """Store the blocks that newly occupied cells reach, in the sparse levels' free slots (on the device)."""
        levels = self._sparse_levels()
        for level, blocks in zip(levels, self._needed_blocks(levels)):
            for grid in (self.field.density_grid, self.field.feature_grid):
                grid.grow(level, blocks)

    def _relayout_sparse(self) -> None:
        """Lay a sparse level out again (one host read per level) where it ran out of free slots at the last refresh,
        or where more of its blocks than ``sparse_headroom`` of them are no longer needed: it then stores exactly the
        blocks the occupancy needs now, and ``sparse_headroom`` more free ones. Decided from the occupancy and counts of
        the last refresh, which processes trained together share (rank 0's), so every process's tables change alike."""
        grids = (self.field.density_grid, self.field.feature_grid)
        levels = self._sparse_levels()
        for level, blocks in zip(levels, self._needed_blocks(levels)):
            used, missing = int(grids[0].slots_used(level)), int(grids[0].blocks_missing(level))
            needed = int(blocks.sum())
            if missing or used + missing - needed > self.cfg.sparse_headroom * needed:
                for grid in grids:
                    grid.relayout(level, blocks, self.cfg.sparse_headroom)

    @staticmethod
    def _resample(table, old_res, old_box, new_box, new_res) -> Tensor:
        """Values of a grid table at the vertices of a new grid over ``new_box``."""
        from nerfpipe.fields.grid import trilinear

        axes = [torch.linspace(float(new_box[0, a]), float(new_box[1, a]), new_res[a], device=table.device) for a in range(3)]
        pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        x01 = (pts - old_box[0]) / (old_box[1] - old_box[0])
        return torch.cat([trilinear(table, old_res, x) for x in x01.split(1 << 20)])

    def param_groups(self, rays_per_step: "int | None" = None) -> "list[dict]":
        groups = self._param_groups()
        scale = batch_lr_scale(rays_per_step, self.lr_reference_rays)
        if rays_per_step is not None:  # the trainer's call
            self.lr_batch_scale = scale
        for group in groups:
            group["lr"] *= scale
            group["betas"] = (0.9, self.adam_beta2)
        return groups

    def _param_groups(self) -> "list[dict]":
        coarsest = [self.field.density_grid.tables[0], self.field.feature_grid.tables[0]]
        density_lr = self.cfg.grid_lr if self.cfg.fine_density_lr is None else self.cfg.fine_density_lr
        groups = [
            {"params": coarsest, "lr": self.cfg.grid_lr, "eps": 1e-15},
            {"params": list(self.field.mlp.parameters()), "lr": self.cfg.mlp_lr, "eps": 1e-15},
            {"params": list(self.field.density_grid.tables[1:]), "lr": density_lr, "eps": 1e-15},
            {"params": list(self.field.feature_grid.tables[1:]), "lr": self.cfg.fine_feature_lr, "eps": 1e-15},
        ]
        if self.background is not None:
            groups[1]["params"] += list(self.background.parameters())
        if self.behind is not None:
            groups.append({"params": self.behind.grid_parameters(), "lr": self.cfg.behind.grid_lr, "eps": 1e-15})
            groups[1]["params"] += list(self.behind.mlp.parameters())
        if self.plane is not None:
            groups.append({"params": list(self.plane.textures), "lr": self.cfg.plane.grid_lr, "eps": 1e-15})
            groups[1]["params"] += list(self.plane.mlp.parameters())
        if self.appearance is not None:
            groups.append({"params": [self.appearance], "lr": self.cfg.appearance_lr, "eps": 1e-15})
        if self.image_codes is not None:
            groups[1]["params"].append(self.image_codes)
        if self.pose_deltas is not None:
            groups.append({"params": [self.pose_deltas], "lr": self.cfg.pose_lr, "eps": 1e-15})
        if self.sky is not None:
            groups.append({"params": [self.sky], "lr": self.cfg.sky_residual_lr, "eps": 1e-15})
        if self.sky_map is not None:
            groups.append({"params": [self.sky_map], "lr": self.cfg.sky_map_lr, "eps": 1e-15})
        return groups

    def stats(self) -> "dict[str, float]":
        out = {k: float(v) for k, v in super().stats().items()}
        out.update(
            occupied_fraction=self.grid.occupied_fraction,
            samples_per_ray=float(self._samples_per_ray),
            finest_resolution=float(max(self.field.density_grid.resolutions[-1])),
            finest_voxel=self.field.voxel_size(len(self.field.density_grid.resolutions) - 1),
            hashed_levels=float(sum(h is not None for h in self.field.density_grid.hash_rows)),
            **self._sparse_stats(),
            sparsity_weight=float(self.sparsity_weight), sparsity_until=float(self.sparsity_until),
            distortion_weight=float(self.distortion_weight),
            evidence_sparsity_weight=float(self.evidence_sparsity_weight),
            support_texture=float(self.plane is not None),
            behind_front=float(self.front),
            appearance=float(self.appearance is not None),
            sky_map_rows=float(0 if self.sky_map is None else self.sky_map.shape[0]),
            exposure_spread=self.exposure_spread,
            lr_batch_scale=self.lr_batch_scale,
        )
        return out

    def _sparse_stats(self) -> "dict[str, float]":
        """Sparse levels, the share of their blocks stored and the blocks needed but not stored (no free slot left)."""
        grid, levels = self.field.density_grid, self._sparse_levels()
        if not levels:
            return {}
        blocks = sum(grid.block_map(lv).numel() for lv in levels)
        stored = sum(int(grid.slots_used(lv)) for lv in levels)
        missing = sum(int(grid.blocks_missing(lv)) for lv in levels)
        return dict(sparse_levels=float(len(levels)), sparse_stored_share=stored / max(blocks, 1), sparse_blocks_missing=float(missing))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        """Accept checkpoints whose grids were resampled to a tightened box."""
        # checkpoints from before the step count was saved were trained with the fine spacing
        # checkpoints from before the field behind the box and the colour corrections: render without them
        if self.behind is not None and not any(k.startswith(prefix + "behind.") for k in state_dict):
            self.behind = None
        if self.plane is not None and not any(k.startswith(prefix + "plane.") for k in state_dict):  # from before the support's texture
            self.plane = None
        if self.plane is not None:  # from before the texture's coverage: everywhere
            state_dict.setdefault(prefix + "plane.coverage", torch.ones_like(self.plane.coverage))
        if self.appearance is not None and prefix + "appearance" not in state_dict:
            self.appearance = None
        if self.image_codes is not None and prefix + "image_codes" not in state_dict:  # from before the image codes
            self.image_codes = None
            device = self.object_box.device
            if self.background is not None:
                self.background = self._background_head().to(device)
            if self.behind is not None:
                self.behind = BackgroundField(self.cfg.behind, self.behind.aabb).to(device)
        if self.sky is not None and prefix + "sky" not in state_dict:  # from before the sky residual (off in renders)
            self.sky = None
        if self.sky_map is not None and prefix + "sky_map" not in state_dict:  # from before the sky map
            self.sky_map = None
        steps = state_dict.setdefault(prefix + "trained_steps", torch.tensor(10**9))
        self._sparse_pending = bool(state_dict.setdefault(prefix + "sparse_pending", torch.tensor(False)))  # once per load
        # checkpoints from before density_levels: density from every level
        state_dict.setdefault(prefix + "density_levels", torch.tensor(len(self.field.density_grid.tables)))
        self._step = int(steps)
        key = prefix + "field.aabb"
        if key in state_dict:
            resolutions = self._resolutions(state_dict[key].to(self.field.aabb))
            for name in ("density_grid", "feature_grid"):
                grid = getattr(self.field, name)
                for i, table in enumerate(grid.tables):
                    if grid.hash_rows[i] is not None:
                        continue  # hashed: the lattice of the first box, never resampled
                    src = state_dict.get(f"{prefix}field.{name}.tables.{i}")
                    if src is not None and src.shape != table.shape:
                        table.data = torch.empty_like(src, device=table.device)  # the checkpoint is read on the CPU
                    grid.resolutions[i] = resolutions[i]
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self.field.active_levels = int(self.active_levels)
        self.field.density_levels = int(self.density_levels)


SPEC = ModelSpec(
    name="fast",
    description="Multiresolution grids (hashed where fine) + occupancy grid + packed rendering: fast on CPU.",
    config=FastConfig,
)
