"""One renderer for every image a model makes: validation views, test paths, orbits, depth.

:func:`render_cameras` renders whole cameras in chunks of rays under ``torch.no_grad``, so the
memory it needs is set by ``chunk`` (rays) times the model's samples per ray, not by the image size.
"""

from dataclasses import dataclass, replace

import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import RayBundle, camera_rays
from nerfpipe.models.base import Model
from nerfpipe.util.typing import Float, Tensor


@dataclass
class RenderedView:
    """One rendered camera."""

    rgb: Float[Tensor, "H W 3"]
    """Colour composited over the background, in [0, 1]."""
    depth: Float[Tensor, "H W"]
    """Expected distance along the ray ``sum w t`` (not divided by ``acc``)."""
    acc: Float[Tensor, "H W"]
    """Accumulated opacity."""
    stop_depth: "Float[Tensor, 'H W'] | None" = None
    """Where the ray stops (``RenderOutputs.stop_depth``), NaN where it does not; None when the model does not give it."""

    @property
    def surface_depth(self) -> Float[Tensor, "H W"]:
        """Expected distance of the surface the ray hits: ``depth / acc``."""
        return self.depth / self.acc.clamp(min=1e-6)


def render_rays(model: Model, rays: RayBundle, background: Float[Tensor, "3"], chunk: "int | None" = None) -> "tuple[Tensor, Tensor, Tensor]":
    """Render a flat batch of rays in chunks (None: the model's :attr:`~nerfpipe.models.base.Model.render_chunk`);
    returns ``(rgb [N,3], depth [N], acc [N])``."""
    return _render_rays(model, rays, background, chunk)[:3]


def _render_rays(model: Model, rays: RayBundle, background: Float[Tensor, "3"], chunk: "int | None") -> "tuple[Tensor, Tensor, Tensor, Tensor | None]":
    """:func:`render_rays` plus the stop depth (None when the model does not give it)."""
    chunk = chunk or getattr(model, "render_chunk", Model.render_chunk)
    out = {"rgb": [], "depth": [], "acc": [], "stop_depth": []}
    for start in range(0, len(rays), chunk):
        part = rays[start : start + chunk]
        res = model.get_outputs(part, background.to(part.origins).expand(len(part), 3))
        for key in out:
            out[key].append(getattr(res, key))
    stop = None if any(m is None for m in out["stop_depth"]) else torch.cat(out["stop_depth"])
    return (*(torch.cat(out[k]) for k in ("rgb", "depth", "acc")), stop)


@torch.no_grad()
def render_cameras(
    model: Model, cameras: Cameras, chunk: "int | None" = None, background: "Float[Tensor, '3'] | None" = None, supersample: int = 1
) -> "list[RenderedView]":
    """Render every camera of a flat batch (sizes may differ), model in eval mode.

    Args:
        model: any :class:`~nerfpipe.models.base.Model`.
        cameras: ``[num_cams]`` cameras on the model's device.
        chunk: rays per forward pass (bounds memory; None: the model's ``render_chunk``).
        background: colour behind the volume (default black).
        supersample: ``k``: each pixel is the mean of ``k x k`` rays spread evenly over its area (a camera's
            pixel integrates its area; one ray through its centre aliases detail finer than the pixel, as a
            field learnt from larger photographs has: :func:`supersample_factor`). The stop depth is the mean
            over the rays that stop (NaN where none does).
    """
    background = torch.zeros(3) if background is None else background
    was_training = model.training
    model.eval()
    views = []
    try:
        for i in range(len(cameras)):
            if supersample > 1:
                cam = cameras[i : i + 1]
                rays = camera_rays(resize_cameras(cam, int(cam.width[0]) * supersample, int(cam.height[0]) * supersample), 0)
            else:
                rays = camera_rays(cameras, i)
            h, w = rays.shape
            rgb, depth, acc, stop = _render_rays(model, rays.reshape(h * w), background, chunk)
            view = RenderedView(rgb.reshape(h, w, 3).clamp(0, 1), depth.reshape(h, w), acc.reshape(h, w), None if stop is None else stop.reshape(h, w))
            views.append(view if supersample == 1 else _pooled(view, supersample))
    finally:
        model.train(was_training)
    return views


def _pooled(view: RenderedView, k: int) -> RenderedView:
    """Means over ``k x k`` blocks of a view rendered at ``k`` times the size (stop depth: over the rays that stop)."""
    h, w = view.acc.shape[0] // k, view.acc.shape[1] // k

    def pool(x: Tensor) -> Tensor:
        return x.reshape(h, k, w, k, *x.shape[2:]).mean(dim=(1, 3))

    stop = None
    if view.stop_depth is not None:
        valid = ~torch.isnan(view.stop_depth)
        count = pool(valid.to(view.acc.dtype))
        stop = pool(view.stop_depth.nan_to_num(0.0)) / count.clamp(min=1e-12)
        stop = torch.where(count > 0, stop, torch.full_like(stop, float("nan")))
    return RenderedView(pool(view.rgb), pool(view.depth), pool(view.acc), stop)


MAX_SUPERSAMPLE = 2
"""Rays per pixel side at most when renders are coarser than the photographs (:func:`supersample_factor`)."""


def supersample_factor(render_size: int, source_size: int, limit: int = MAX_SUPERSAMPLE) -> int:
    """Rays per pixel side for a render whose longer side is ``render_size`` of a view whose photographs had
    ``source_size``: the whole number of photograph pixels one rendered pixel spans, at most ``limit`` (1 when the
    render is at least half the photographs' size).

    Example:
        >>> supersample_factor(400, 1920), supersample_factor(400, 400), supersample_factor(300, 500)
        (2, 1, 1)
    """
    return int(max(1, min(limit, source_size // max(render_size, 1))))


def capped_size(width: int, height: int, scale: float, max_size: "int | None") -> "tuple[int, int]":
    """``scale`` times a camera's size, the longer side capped at ``max_size`` pixels (None: no cap).

    Example:
        >>> capped_size(1920, 1440, 1.0, 800), capped_size(200, 200, 1.0, 800), capped_size(400, 400, 0.5, None)
        ((800, 600), (200, 200), (200, 200))
    """
    s = scale if max_size is None else min(scale, max_size / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


def resize_cameras(cameras: Cameras, width: int, height: int) -> Cameras:
    """The same cameras imaging ``width x height`` pixels (intrinsics scaled per axis)."""
    sx = width / cameras.width.to(cameras.fx.dtype)
    sy = height / cameras.height.to(cameras.fx.dtype)
    return replace(
        cameras,
        fx=cameras.fx * sx,
        fy=cameras.fy * sy,
        cx=cameras.cx * sx,
        cy=cameras.cy * sy,
        width=torch.full_like(cameras.width, width),
        height=torch.full_like(cameras.height, height),
    )


@dataclass(frozen=True)
class FramePlan:
    """How many views to render, at what fraction of their size, and the time that should take."""

    frames: int
    scale: float
    estimated_seconds: float


def plan_frames(frames: int, min_frames: int, seconds_per_frame: float, allowed: "float | None", min_scale: float = 0.25,
                fixed_per_frame: float = 0.0) -> FramePlan:
    """Views and scale that fit ``allowed`` seconds, from the time one full-size view takes (``seconds_per_frame``,
    which follows the pixel count, plus ``fixed_per_frame``, which does not: a view's appearance fit).

    Without a limit, or when all ``frames`` fit, all of them at full size. Otherwise as many as fit,
    down to ``min_frames``; below that the views shrink (time follows pixel count), to no less than
    ``min_scale`` of the side. Used by the render stage, the trainer's final evaluation and its video.

    Example:
        >>> plan_frames(60, 12, 1.0, 30.0), plan_frames(60, 12, 1.0, 3.0).scale
        (FramePlan(frames=30, scale=1.0, estimated_seconds=30.0), 0.5)
    """
    per = max(seconds_per_frame, 1e-6)
    full = per + fixed_per_frame
    if allowed is None or frames * full <= allowed:
        return FramePlan(frames, 1.0, frames * full)
    fitting = int(max(allowed, 0.0) // full)
    if fitting >= min_frames:
        return FramePlan(fitting, 1.0, fitting * full)
    count = min(min_frames, frames)
    scale = shrink(count, per, allowed, min_scale, fixed_per_frame)
    return FramePlan(count, scale, count * (fixed_per_frame + per * scale**2))


def shrink(count: int, per: float, allowed: float, min_scale: float, fixed: float = 0.0) -> float:
    """The side's scale at which ``count`` views fit ``allowed`` seconds (``per`` a full view's scalable seconds,
    ``fixed`` each view's others), within ``[min_scale, 1]``."""
    return max(min_scale, min(1.0, (max(max(allowed, 0.0) / max(count, 1) - fixed, 0.0) / max(per, 1e-6)) ** 0.5))


def to_uint8(image: Float[Tensor, "*bs"]) -> "object":
    """``[0, 1]`` float image -> uint8 numpy array."""
    return (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


__all__ = ["FramePlan", "RenderedView", "plan_frames", "render_cameras", "render_rays", "resize_cameras", "shrink", "supersample_factor", "to_uint8"]
