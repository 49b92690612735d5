"""Rays from cameras: :class:`RayBundle` and :func:`generate_rays`.

Glossary:
    cam_idx  index of the camera each ray comes from, into a :class:`Cameras` batch
    uv       pixel coordinates (centre of the top-left pixel is (0.5, 0.5))
    t        distance along a unit-length ray direction
"""

from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.tensor_dataclass import TensorDataclass
from nerfpipe.util.typing import Float, Int, Tensor


@dataclass
class RayBundle(TensorDataclass):
    """A batch of rays in world coordinates."""

    origins: Float[Tensor, "*bs 3"]
    """Ray origins (camera centres)."""
    directions: Float[Tensor, "*bs 3"]
    """Unit-length ray directions."""
    cam_idx: Int[Tensor, "*bs"]
    """Index of the camera each ray belongs to."""
    z_scale: Float[Tensor, "*bs"]
    """Camera-z depth per unit distance along the ray (cosine to the optical axis);
    ``depth_z = t * z_scale``."""

    _batch_field: ClassVar[str] = "cam_idx"

    def points_at(self, t: Float[Tensor, "*bs"]) -> Float[Tensor, "*bs 3"]:
        return self.origins + t[..., None] * self.directions


def pixel_centers(height: int, width: int, device=None, dtype=torch.float32) -> Float[Tensor, "H W 2"]:
    """Pixel-centre coordinates ``(u, v)`` of a whole image, row-major: ``[i, j] = (j + .5, i + .5)``."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype) + 0.5,
        torch.arange(width, device=device, dtype=dtype) + 0.5,
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def generate_rays(
    cameras: Cameras, cam_idx: Int[Tensor, "*bs"], uv: Float[Tensor, "*bs 2"], present: "tuple[bool, bool] | None" = None
) -> RayBundle:
    """Rays through pixel coordinates ``uv`` of cameras ``cameras[cam_idx]``, undistorted.

    Args:
        cameras: a flat batch of cameras ``[num_cams]``.
        cam_idx: which camera each pixel belongs to.
        uv: pixel coordinates; integer pixel ``(i, j)`` has its centre at ``(j + 0.5, i + 0.5)``.
        present: ``cameras.distortion_models()``, when the caller keeps it (a sampler drawing every step from
            the same cameras): no read back per call (None: read back, a host sync on CUDA).

    Returns:
        Unit-direction rays from the camera centres, in world coordinates.

    Example:
        >>> cams = Cameras.create(torch.eye(4)[None], 100.0, 100.0, 50.0, 50.0, 100, 100)
        >>> rays = generate_rays(cams, torch.tensor([0]), torch.tensor([[50.0, 50.0]]))
        >>> rays.directions.tolist()
        [[0.0, 0.0, 1.0]]
    """
    cams = cameras[cam_idx]
    xy = cams.pixel_to_normalized(uv.to(cams.fx.dtype), present)
    d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)
    d_cam = F.normalize(d_cam, dim=-1)
    rot = cams.world_from_cam[..., :3, :3]
    directions = (rot @ d_cam[..., None])[..., 0]
    return RayBundle(
        origins=cams.world_from_cam[..., :3, 3].clone(),
        directions=directions,
        cam_idx=cam_idx,
        z_scale=d_cam[..., 2],
    )


def camera_rays(cameras: Cameras, index: int) -> RayBundle:
    """All rays of one camera, shaped ``[H, W]`` (the camera is broadcast, not copied per pixel)."""
    h, w = int(cameras.height[index]), int(cameras.width[index])
    cam = cameras[index]
    uv = pixel_centers(h, w, device=cameras.device, dtype=cameras.fx.dtype)
    xy = cam.expand(h, w).pixel_to_normalized(uv)
    d_cam = F.normalize(torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1), dim=-1)
    return RayBundle(
        origins=cam.world_from_cam[:3, 3].expand(h, w, 3).clone(),
        directions=d_cam @ cam.world_from_cam[:3, :3].T,
        cam_idx=torch.full((h, w), index, dtype=torch.long, device=cameras.device),
        z_scale=d_cam[..., 2],
    )
