"""The classic NeRF model: stratified coarse samples, an optional importance-sampled fine pass.

Registered in the ``nerfpipe.models`` entry-point group as ``vanilla`` (:data:`SPEC`).
"""

from dataclasses import dataclass, field

import torch

from nerfpipe.data.rays import RayBundle
from nerfpipe.data.samples import RaySamples
from nerfpipe.fields.vanilla import VanillaField, VanillaFieldConfig
from nerfpipe.functional.sampling import merge_edges, pdf_samples, stratified_samples
from nerfpipe.functional.volrend import composite, render_weights
from nerfpipe.models.base import Model, ModelSpec, RenderOutputs, SceneInfo
from nerfpipe.util.errors import refuse_unless
from nerfpipe.util.typing import Float, Tensor


@dataclass
class VanillaConfig:
    """Classic NeRF: a positional-encoding MLP field, 64 stratified samples per ray."""

    num_samples: int = 64
    """Stratified (coarse) samples per ray between near and far."""
    num_importance: int = 0
    """Extra samples per ray drawn from the coarse weights for a fine field (0: coarse only, as in the course)."""
    field: VanillaFieldConfig = field(default_factory=VanillaFieldConfig)
    """Sizes of the MLP (shared by the coarse and the fine field)."""
    near: "float | None" = None
    """Near bound; ``None`` takes the scene's."""
    far: "float | None" = None
    """Far bound; ``None`` takes the scene's."""

    def __post_init__(self) -> None:
        """Impossible sample counts are one clear error when configured (from the CLI, a pipeline file, Python)."""
        refuse_unless([("num_samples", self.num_samples >= 1, "at least 1", self.num_samples),
                       ("num_importance", self.num_importance >= 0, "0 or more", self.num_importance)])

    def setup(self, scene_info: SceneInfo) -> "VanillaModel":
        return VanillaModel(self, scene_info)


class VanillaModel(Model):
    """Coarse field (+ fine field when ``num_importance > 0``) rendered by volume compositing."""

    def __init__(self, cfg: VanillaConfig, scene_info: SceneInfo) -> None:
        super().__init__()
        self.cfg = cfg
        self.near = scene_info.near if cfg.near is None else cfg.near
        self.far = scene_info.far if cfg.far is None else cfg.far
        self.coarse = VanillaField(cfg.field)
        self.fine = VanillaField(cfg.field) if cfg.num_importance > 0 else None

    def _render(self, field_: VanillaField, rays: RayBundle, edges: Tensor, background: Tensor):
        samples = RaySamples.from_edges(rays, edges)
        sigma, rgb = field_(samples.positions, samples.directions)
        weights, _ = render_weights(sigma, samples.deltas)
        return composite(weights, rgb, samples.t_mids, background), weights

    def get_outputs(self, rays: RayBundle, background: Float[Tensor, "*bs 3"]) -> RenderOutputs:
        near = torch.full(rays.shape, self.near, dtype=rays.origins.dtype, device=rays.origins.device)
        edges = stratified_samples(near, torch.full_like(near, self.far), self.cfg.num_samples, perturb=self.training, generator=self.generator)
        (rgb, depth, acc), weights = self._render(self.coarse, rays, edges, background)
        n = self.cfg.num_samples
        if self.fine is None:
            return RenderOutputs(rgb=rgb, depth=depth, acc=acc, num_samples=n * rays.cam_idx.numel())
        extra = pdf_samples(edges, weights, self.cfg.num_importance, perturb=self.training, generator=self.generator)
        edges_f = merge_edges(edges, extra)
        (rgb_f, depth_f, acc_f), _ = self._render(self.fine, rays, edges_f, background)
        n += edges_f.shape[-1] - 1
        return RenderOutputs(rgb=rgb_f, depth=depth_f, acc=acc_f, num_samples=n * rays.cam_idx.numel(), extras={"rgb_coarse": rgb})

    def get_losses(
        self, outputs: RenderOutputs, target_rgb: Float[Tensor, "*bs 3"], target_depth: "Float[Tensor, '*bs'] | None" = None
    ) -> "dict[str, Tensor]":
        losses = {"rgb": torch.mean((outputs.rgb - target_rgb) ** 2)}
        if "rgb_coarse" in outputs.extras:
            losses["rgb_coarse"] = torch.mean((outputs.extras["rgb_coarse"] - target_rgb) ** 2)
        return losses

    def _last(self) -> VanillaField:
        return self.coarse if self.fine is None else self.fine

    def density_fn(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points"]:
        return self._last().density(points)

    def rgb_fn(self, points: Float[Tensor, "num_points 3"], directions: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 3"]:
        return self._last()(points, directions)[1]

    def stats(self) -> "dict[str, int | float]":
        return {**super().stats(), "samples_per_ray": self.cfg.num_samples + self.cfg.num_importance}


SPEC = ModelSpec(name="vanilla", description="Classic NeRF: positional-encoding MLP, stratified (+ importance) sampling", config=VanillaConfig)
