"""The one camera model of nerfpipe. Every input format is converted into it at the boundary.

Convention (the same as COLMAP and OpenCV):

* camera axes: **+x right, +y down, +z forward** (the camera looks along +z);
* ``world_from_cam`` (``[*bs, 4, 4]``) maps camera coordinates to world coordinates; its
  inverse is ``cam_from_world``. No bare ``c2w``/``pose`` names anywhere in nerfpipe;
* pixel coordinates ``(u, v)``: u to the right, v down, **the centre of the top-left pixel
  is (0.5, 0.5)**, so pixel ``(row i, col j)`` has its centre at ``(j + 0.5, i + 0.5)``;
* intrinsics per camera: ``fx fy cx cy`` in pixels, ``width height`` in pixels (cameras in
  one batch may differ in size, e.g. portrait and landscape frames of one capture);
* distortion per camera: a :class:`~nerfpipe.functional.distortion.Distortion` code and four
  parameters (``k1 k2 p1 p2`` for OPENCV, ``k1..k4`` for FISHEYE), applied to normalised
  coordinates exactly as COLMAP does.

Blender/NeRF/nerfstudio ``transform_matrix`` is camera-to-world in the OpenGL convention
(+y up, camera looks along -z); :func:`opengl_to_opencv` converts it.
"""

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import torch

from nerfpipe.data.tensor_dataclass import TensorDataclass
from nerfpipe.functional.distortion import Distortion, distort, models_present, undistort
from nerfpipe.util.typing import Float, Int, Tensor

# OpenGL camera axes expressed in OpenCV camera axes: flip y and z.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def opengl_to_opencv(world_from_cam_gl: Float[Tensor, "*bs 4 4"]) -> Float[Tensor, "*bs 4 4"]:
    """Convert camera-to-world matrices from OpenGL camera axes to OpenCV camera axes.

    Example:
        >>> m = torch.eye(4)
        >>> opengl_to_opencv(m)[:3, :3].diagonal().tolist()
        [1.0, -1.0, -1.0]
    """
    return world_from_cam_gl @ _GL_TO_CV.to(world_from_cam_gl)


def invert_rigid(m: Float[Tensor, "*bs 4 4"]) -> Float[Tensor, "*bs 4 4"]:
    """Invert rigid transforms ``[R t; 0 1]`` without a general matrix inverse."""
    rot = m[..., :3, :3].transpose(-1, -2)
    t = -(rot @ m[..., :3, 3:4])
    out = torch.zeros_like(m)
    out[..., :3, :3] = rot
    out[..., :3, 3:4] = t
    out[..., 3, 3] = 1
    return out


@dataclass
class Cameras(TensorDataclass):
    """A batch of cameras in the OpenCV convention (see the module docstring).

    All fields share the batch shape ``*bs``. Index, reshape and move it like a tensor:
    ``cams[3]``, ``cams[idx]``, ``cams.to("cuda")``.
    """

    world_from_cam: Float[Tensor, "*bs 4 4"]
    """Camera-to-world rigid transform; camera axes +x right, +y down, +z forward."""
    fx: Float[Tensor, "*bs"]
    """Focal length along u, in pixels."""
    fy: Float[Tensor, "*bs"]
    """Focal length along v, in pixels."""
    cx: Float[Tensor, "*bs"]
    """Principal point u, in pixels (image centre is width / 2)."""
    cy: Float[Tensor, "*bs"]
    """Principal point v, in pixels (image centre is height / 2)."""
    width: Int[Tensor, "*bs"]
    """Image width in pixels."""
    height: Int[Tensor, "*bs"]
    """Image height in pixels."""
    distortion: Int[Tensor, "*bs"]
    """Distortion model code, a :class:`Distortion` value."""
    dist_params: Float[Tensor, "*bs 4"]
    """Distortion parameters: k1 k2 p1 p2 (OPENCV) or k1 k2 k3 k4 (FISHEYE); zeros for NONE."""

    _batch_field: ClassVar[str] = "fx"

    # ---------------------------------------------------------------- construction
    @classmethod
    def create(
        cls,
        world_from_cam,
        fx,
        fy,
        cx,
        cy,
        width,
        height,
        distortion=Distortion.NONE,
        dist_params=None,
        dtype: torch.dtype = torch.float32,
    ) -> "Cameras":
        """Build a batch from tensors, arrays or scalars, broadcasting intrinsics to the batch."""
        w2c = torch.as_tensor(world_from_cam, dtype=dtype)
        bs = w2c.shape[:-2]
        as_f = lambda v: torch.as_tensor(v, dtype=dtype).expand(bs).clone()  # noqa: E731
        as_i = lambda v: torch.as_tensor(v).round().long().expand(bs).clone()  # noqa: E731
        params = torch.zeros(4, dtype=dtype) if dist_params is None else torch.as_tensor(dist_params, dtype=dtype)
        return cls(
            world_from_cam=w2c,
            fx=as_f(fx),
            fy=as_f(fy),
            cx=as_f(cx),
            cy=as_f(cy),
            width=as_i(width),
            height=as_i(height),
            distortion=torch.as_tensor(int(distortion) if isinstance(distortion, int) else distortion).long().expand(bs).clone(),
            dist_params=params.expand(*bs, 4).clone(),
        )

    @staticmethod
    def cat(cams: "list[Cameras]") -> "Cameras":
        return Cameras(**{f.name: torch.cat([getattr(c, f.name) for c in cams]) for f in fields(Cameras)})

    # ---------------------------------------------------------------- derived quantities
    @property
    def cam_from_world(self) -> Float[Tensor, "*bs 4 4"]:
        return invert_rigid(self.world_from_cam)

    @property
    def centers(self) -> Float[Tensor, "*bs 3"]:
        """Camera centres in world coordinates."""
        return self.world_from_cam[..., :3, 3]

    @property
    def forward(self) -> Float[Tensor, "*bs 3"]:
        """Viewing directions (camera +z) in world coordinates."""
        return self.world_from_cam[..., :3, 2]

    @property
    def up(self) -> Float[Tensor, "*bs 3"]:
        """Image-up directions (camera -y) in world coordinates."""
        return -self.world_from_cam[..., :3, 1]

    @property
    def K(self) -> Float[Tensor, "*bs 3 3"]:
        """Pinhole intrinsic matrices."""
        k = torch.zeros(*self.shape, 3, 3, dtype=self.fx.dtype, device=self.device)
        k[..., 0, 0], k[..., 1, 1] = self.fx, self.fy
        k[..., 0, 2], k[..., 1, 2] = self.cx, self.cy
        k[..., 2, 2] = 1
        return k

    def capped(self, max_side: "int | None") -> "Cameras":
        """The same cameras with the longer image side at most ``max_side`` pixels (the same field of view:
        intrinsics scaled per axis by the rounded size; distortion, in normalised coordinates, unchanged).
        Cameras already small enough are returned as they are; None: no cap."""
        if max_side is None:
            return self
        s = torch.clamp(max_side / torch.maximum(self.width, self.height).to(self.fx), max=1.0)
        return self.resized((self.width * s).round().clamp(min=1), (self.height * s).round().clamp(min=1))

    def resized(self, width: Tensor, height: Tensor) -> "Cameras":
        """The same cameras for images of ``width`` x ``height`` pixels (each camera's own, or one for all):
        the same field of view, intrinsics scaled per axis (distortion, in normalised coordinates, unchanged)."""
        w = torch.as_tensor(width).to(self.fx).expand_as(self.fx)
        h = torch.as_tensor(height).to(self.fx).expand_as(self.fx)
        sx, sy = w / self.width.to(self.fx), h / self.height.to(self.fx)
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w.round().long(), height=h.round().long())

    def has_distortion(self) -> bool:
        return any(self.distortion_models())

    # ---------------------------------------------------------------- pixels <-> camera rays
    def pixel_to_normalized(self, uv: Float[Tensor, "*bs 2"], present: "tuple[bool, bool] | None" = None) -> Float[Tensor, "*bs 2"]:
        """Pixel coordinates -> undistorted normalised coordinates ``(X/Z, Y/Z)``.

        ``self`` must have the same batch shape as ``uv`` (index the cameras first). ``present``: the
        :meth:`distortion_models` of these cameras or of the set they were drawn from, when known (None: read back).
        """
        xy_d = torch.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], dim=-1)
        return undistort(xy_d, self.distortion, self.dist_params, present)

    def distortion_models(self) -> "tuple[bool, bool]":
        """Whether any of these cameras has the OpenCV model, and whether any has the fisheye model
        (:func:`~nerfpipe.functional.distortion.models_present`: one read back)."""
        return models_present(self.distortion)

    def normalized_to_pixel(self, xy: Float[Tensor, "*bs 2"]) -> Float[Tensor, "*bs 2"]:
        """Undistorted normalised coordinates -> pixel coordinates (applies distortion)."""
        xy_d = distort(xy, self.distortion, self.dist_params)
        return torch.stack([xy_d[..., 0] * self.fx + self.cx, xy_d[..., 1] * self.fy + self.cy], dim=-1)

    def project(self, points: Float[Tensor, "*bs 3"]) -> "tuple[Float[Tensor, '*bs 2'], Float[Tensor, '*bs']]":
        """World points -> (pixel coordinates, depth along +z). Batch shapes must match."""
        cfw = self.cam_from_world
        p = (cfw[..., :3, :3] @ points[..., None])[..., 0] + cfw[..., :3, 3]
        z = p[..., 2]
        xy = p[..., :2] / z[..., None]
        return self.normalized_to_pixel(xy), z
