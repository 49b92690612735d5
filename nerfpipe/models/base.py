"""The protocol every NeRF model follows, so one trainer, renderer and mesher serve them all.

A model is built from its config dataclass by ``config.setup(scene_info)`` and renders a
:class:`~nerfpipe.data.rays.RayBundle` into :class:`RenderOutputs`. Models are registered in the
entry-point group ``nerfpipe.models`` as :class:`ModelSpec` objects.
"""

from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import Enum
from collections.abc import Callable, Iterator

import torch
from torch import nn

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import RayBundle
from nerfpipe.util.typing import Float, Tensor


@dataclass
class RenderOutputs:
    """What rendering a batch of rays returns."""

    rgb: Float[Tensor, "*bs 3"]
    """Composited colour, background included."""
    depth: Float[Tensor, "*bs"]
    """Expected distance along the ray (``sum w_i t_i``; divide by ``acc`` for the surface)."""
    acc: Float[Tensor, "*bs"]
    """Accumulated opacity ``sum w_i`` in [0, 1]."""
    stop_depth: "Float[Tensor, '*bs'] | None" = None
    """Where the ray stops: the distance at which its accumulated opacity reaches the model's stop opacity
    (NaN where it never does); set by models that render packed samples, outside training."""
    num_samples: int = 0
    """Samples evaluated by the field for this batch (for cost reports)."""
    extras: "dict[str, Tensor]" = field(default_factory=dict)
    """Model-specific outputs (e.g. weights for a distortion loss)."""


@dataclass
class SceneInfo:
    """What a model may know about the scene when it is built (no images)."""

    aabb: Float[Tensor, "2 3"]
    near: float
    far: float
    num_images: int
    pixels_per_image: int
    has_alpha: bool = False
    unbounded: bool = False
    """A real capture: the photographs show more than the scene box (floor, walls, sky) and vary in
    exposure (inputs with sparse points from SfM and no alpha, e.g. COLMAP)."""
    focal_spread: float = 0.0
    """Spread (interquartile range / median) of the training cameras' focal lengths relative to their image
    diagonals: near 0 for one camera (0.05 on colmap_mouse, whose COLMAP model has one camera per image),
    large for a collection of photographs from several cameras or zoom settings (1.5 on the Sacre Coeur
    photos)."""
    exposure_spread: float = 0.0
    """Spread (standard deviation) of the training photos' log exposure gains measured on the sparse points' tracks
    (:func:`nerfpipe.data.exposure.exposure_gains`; 0: not measured): about 0.2 for one phone's session under steady
    light (colmap_mouse), 0.42 for the Sacre Coeur photo collection."""
    arc: float = 0.0
    """The azimuth arc (radians) the training cameras cover about the scene box's centre, seen from above
    (:func:`nerfpipe.data.orbit.camera_arc`): 2 pi for an object photographed all round (no gap wider than
    :data:`nerfpipe.data.orbit.ARC_GAP`), about 2.9 for 21 of colmap_mouse's photographs on one side of it,
    1.1 for the Sceaux castle's facade photographs, 0.75 for the Sacre Coeur collection."""
    pixel_footprint: float = 0.0
    """Width of one training pixel at the scene box's centre, in scene units (median over the training
    cameras of their distance to the centre over their focal length; 0: unknown). The finest detail the
    photographs resolve there."""
    support_plane: "tuple[float, float, float, float] | None" = None
    """The plane the object stands on, ``(a, b, c, d)`` with a unit normal and ``a x + b y + c z + d > 0`` on the
    cameras' side, found in the sparse points (:func:`nerfpipe.training.trainer.support_plane_of`); None: none found
    (no points, a free-standing object, an aerial or a facade capture)."""
    points: "Float[Tensor, 'num_points 3'] | None" = None
    """The sparse points of a real capture in the scene box (SfM's evidence of surfaces; None: none)."""
    cameras: "Cameras | None" = None
    """The training cameras (poses and intrinsics, no images; None: not known): what they see
    (:meth:`nerfpipe.fields.plane.PlaneTexture.cover`)."""


class Callback(Enum):
    """Named places in the training loop where hooks fire (STYLE habit 15)."""

    BEFORE_TRAIN_ITERATION = "before_train_iteration"
    AFTER_TRAIN_ITERATION = "after_train_iteration"
    AFTER_TRAIN = "after_train"


class Model(nn.Module):
    """Base class of radiance-field models.

    Subclasses implement :meth:`get_outputs` and :meth:`density_fn`; the others have
    sensible defaults.
    """

    averaged: bool = False
    """Whether the trainer averages this model's parameters over the late steps by default on every scene
    (``TrainerConfig.average`` None; real captures always)."""

    error_sampled: bool = False
    """Whether the trainer draws a share of the rays from an error map by default on bounded scenes
    (``TrainerConfig.error_sampling`` None)."""

    batch_follows_pixels: bool = False
    """Whether the trainer's default batch on the CPU grows with the training images of an object on a transparent background
    (``TrainerConfig.rays_per_step`` None: :func:`nerfpipe.training.trainer.default_rays_per_step`)."""

    generator: "torch.Generator | None" = None
    """The stream of every random draw in training (sample jitter, occupancy refreshes, regulariser
    points), on the model's device. The trainer sets it so that a run is reproducible and leaves
    torch's global stream alone; None: torch's global stream."""

    render_chunk: int = 4096
    """Rays per forward pass when rendering whole images where the caller names none (bounds memory: the classic
    MLP's 192 samples per ray take a few GB at 16,384 rays)."""

    def get_outputs(self, rays: RayBundle, background: Float[Tensor, "*bs 3"]) -> RenderOutputs:
        """Render rays, compositing over ``background`` (one colour per ray)."""
        raise NotImplementedError

    def density_fn(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points"]:
        """Volume density at world points (for meshing and occupancy)."""
        raise NotImplementedError

    def rgb_fn(self, points: Float[Tensor, "num_points 3"], directions: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 3"]:
        """Colour at world points seen along ``directions`` (for mesh vertex colours)."""
        raise NotImplementedError

    def get_losses(
        self, outputs: RenderOutputs, target_rgb: Float[Tensor, "*bs 3"], target_depth: "Float[Tensor, '*bs'] | None" = None
    ) -> "dict[str, Tensor]":
        """Loss terms; the trainer sums them. Default: MSE on colour.

        ``target_depth`` is the distance along each ray of a sparse point seen through it (NaN where
        none; None when the batch has none); models that do not use it ignore it."""
        return {"rgb": torch.mean((outputs.rgb - target_rgb) ** 2)}

    appearance_fit_steps: int = 0
    """Optimiser steps of :meth:`fitted_appearance` by default (0: nothing is fitted); the final evaluation times a
    few of them to plan for the fit (:func:`nerfpipe.training.evaluation.appearance_fit_seconds`)."""

    @contextmanager
    def fitted_appearance(self, rays: RayBundle, rgb: Float[Tensor, "num_rays 3"], background: Float[Tensor, "3"],
                          steps: "int | None" = None) -> Iterator[bool]:
        """Within the block, render as the image that shows ``rgb`` along ``rays`` was taken: models with
        per-image appearance fit a held-out view's appearance to these pixels (the NeRF-W protocol: fit on
        part of an image, score the rest), in ``steps`` optimiser steps (None: the model's own count; fewer to time
        the fit). Yields whether anything was fitted; default: nothing to fit."""
        yield False

    def callbacks(self) -> "dict[Callback, list[Callable[[int], None]]]":
        """Hooks by place, each called with the step number (e.g. occupancy-grid updates)."""
        return {}

    def parameters_replaced(self) -> None:
        """Called after the trainer replaced the parameters (their average at the end of training): rebuild
        whatever was derived from them (e.g. an occupancy grid). Default: nothing."""

    def param_groups(self, rays_per_step: "int | None" = None) -> "list[dict]":
        """Optimiser parameter groups (``{"params": [...], "lr": ...}``); default: all, trainer lr. ``rays_per_step``:
        the trainer's batch, for models whose learning rates follow it (None: unknown)."""
        return [{"params": [p for p in self.parameters() if p.requires_grad]}]

    def lr_factor(self, step: int) -> float:
        """Learning-rate multiplier at ``step`` (the trainer applies it to every group's ``initial_lr``)."""
        return 1.0

    def graph_key(self) -> "tuple | None":
        """What a training step's device work depends on beyond its inputs' values, for the trainer's CUDA graph
        (:mod:`nerfpipe.training.cuda_graph`): everything the Python code of :meth:`get_outputs` and
        :meth:`get_losses` branches on or sizes by, and where the tensors they read live. A captured step is
        replayed while the key stays equal and captured anew when it changes. None (the default): this step
        cannot be captured (it reads values back or is shaped by them); it runs as it is."""
        return None

    sample_capacity: "tuple[int, ...] | None" = None
    """Slots a captured training step packs its variable-sized work into, one number per entry of
    :meth:`sample_count` (set by the trainer's CUDA graph; None otherwise: as many as there are). Models whose
    :meth:`graph_key` is None ignore it."""

    def sample_count(self) -> "Tensor | None":
        """What the latest training step needed of each of :attr:`sample_capacity`'s slots, on the device (not read
        back), or None: what the trainer's graph checks the slots against."""
        return None

    def stats(self) -> "dict[str, int | float]":
        """Figures for metrics.json (parameters, MB, occupied fraction, ...)."""
        n = sum(p.numel() for p in self.parameters())
        return {"model_params": n, "model_mb": sum(p.numel() * p.element_size() for p in self.parameters()) / 2**20}


@dataclass(frozen=True)
class ModelSpec:
    """A model registered in the ``nerfpipe.models`` entry-point group."""

    name: str
    description: str
    config: type
    """Config dataclass with ``setup(scene_info: SceneInfo) -> Model``."""
