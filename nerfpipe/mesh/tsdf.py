"""TSDF fusion of depth maps (rendered from a field, or any depth source): :func:`tsdf_fuse`.

Depth maps from the training cameras are fused into Open3D's tensor ``VoxelBlockGrid`` (a
sparse TSDF) and the zero level set is extracted with its marching cubes, with colour when the
frames carry it. (The legacy ``ScalableTSDFVolume`` of Open3D 0.20 returned empty meshes on
float depth here, so the tensor API is used.)

Convention conversion (checked against Open3D's ``VoxelBlockGridImpl.h``): the extrinsic is
``cam_from_world`` with OpenCV camera axes, as nerfpipe's; depth is camera-z depth; a voxel
projects to ``u = fx x/z + cx`` and reads pixel ``floor(u)``, so pixel ``j`` covers
``[j, j + 1)`` with its centre at ``j + 0.5``: the same as nerfpipe, K passes through
unchanged. Fusion is pinhole only: cameras must have no distortion (render undistorted views).
"""

from collections.abc import Callable, Iterable

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import camera_rays
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.util.typing import Float, Tensor

BLOCK_RESOLUTION = 16
"""Voxels per side of one TSDF block."""

FrameFn = Callable[[int], "tuple[np.ndarray, np.ndarray | None]"]
"""``frame_fn(camera_index) -> (depth [H, W] camera-z, 0 or inf where unknown; rgb uint8 [H, W, 3] or None)``."""


def open3d_camera(cameras: Cameras, index: int):
    """Open3D tensors ``(intrinsic K 3x3, extrinsic cam_from_world 4x4)`` (float64) of one camera."""
    o3c = require("open3d.core", "mesh")
    c = cameras[index]
    return o3c.Tensor(c.K.double().cpu().numpy()), o3c.Tensor(c.cam_from_world.double().cpu().numpy())


def ray_depth_to_z(depth: Float[Tensor, "*bs"], z_scale: Float[Tensor, "*bs"]) -> Float[Tensor, "*bs"]:
    """Distance along unit rays -> camera-z depth (``RayBundle.z_scale``)."""
    return depth * z_scale


def _images(o3d, depth: np.ndarray, rgb: "np.ndarray | None"):
    """Open3D tensor images: float32 depth (0 = unknown) and float32 colour in [0, 1]."""
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    color = np.zeros((*depth.shape, 3), np.float32) if rgb is None else np.ascontiguousarray(rgb[..., :3], dtype=np.float32) / 255.0
    return o3d.t.geometry.Image(o3d.core.Tensor(depth)), o3d.t.geometry.Image(o3d.core.Tensor(color))


def tsdf_fuse(
    cameras: Cameras,
    frame_fn: FrameFn,
    aabb: Float[Tensor, "2 3"],
    voxel_size: float,
    trunc_voxels: float = 4.0,
    depth_max: float = 1e3,
    min_weight: float = 1.0,
    indices: "list[int] | None" = None,
    max_faces: "int | None" = None,
    max_voxel_size: "float | None" = None,
) -> TriangleMesh:
    """Fuse depth (and colour) of ``cameras[indices]`` into a TSDF and extract its surface.

    Args:
        cameras: nerfpipe cameras (OpenCV convention, no distortion), world frame.
        frame_fn: depth and optional colour per camera index.
        aabb: box ``[min, max]``; the mesh is cropped to it.
        voxel_size: TSDF voxel size in world units.
        trunc_voxels: truncation distance in voxels.
        depth_max: depths beyond this are ignored.
        min_weight: voxels observed by fewer frames are left out of the surface.
        indices: camera indices to fuse (default all).
        max_faces: where the surface has more faces than this (what follows fusion, cleaning and simplification,
            takes a time about proportional to them), the same frames are fused again with voxels as much larger as
            brings the faces to about this many (faces go with the inverse square of the voxel size), but no larger
            than ``max_voxel_size``; ``mesh.info["voxel_size"]`` is the size used.
        max_voxel_size: the coarsest voxel ``max_faces`` may lead to (default: no limit).

    Raises:
        NerfpipeError: distorted cameras, or no surface.
    """
    if cameras.has_distortion():
        raise NerfpipeError("TSDF fusion needs pinhole cameras: render undistorted depth maps (set distortion to NONE)")
    frames = ((i, *frame_fn(i)) for i in (range(len(cameras)) if indices is None else indices))  # rendered as fused
    if max_faces is not None:
        frames = list(frames)  # kept for a second fusion
    mesh = _fuse(cameras, frames, aabb, voxel_size, trunc_voxels, depth_max, min_weight)
    if max_faces is not None and mesh.num_faces > max_faces:
        coarser = voxel_size * (1.05 * mesh.num_faces / max(max_faces, 1)) ** 0.5
        coarser = coarser if max_voxel_size is None else min(coarser, max_voxel_size)
        if coarser > voxel_size:
            try:
                mesh = _fuse(cameras, frames, aabb, coarser, trunc_voxels, depth_max, min_weight)
            except NerfpipeError:  # a surface too thin for the coarser voxels: the finer one stays
                pass
    return mesh


def _fuse(cameras: Cameras, frames: "Iterable[tuple[int, np.ndarray, np.ndarray | None]]", aabb: Float[Tensor, "2 3"], voxel_size: float, trunc_voxels: float, depth_max: float,
          min_weight: float) -> TriangleMesh:
    """:func:`tsdf_fuse` of ``frames`` (``(camera index, depth, rgb)``) at one voxel size."""
    o3d = require("open3d", "mesh")
    margin = trunc_voxels * voxel_size
    lo, hi = aabb[0].double() - margin, aabb[1].double() + margin
    vbg = _voxel_block_grid(o3d, voxel_size, _block_budget(hi - lo, voxel_size))
    has_color, fused = False, 0
    for i, depth, rgb in frames:
        depth = _mask_outside(np.asarray(depth, dtype=np.float64), cameras, i, lo, hi)
        if not (depth > 0).any():
            continue
        has_color |= rgb is not None
        d_img, c_img = _images(o3d, depth, rgb)
        k, cam_from_world = open3d_camera(cameras, i)
        args = (k, cam_from_world, 1.0, float(depth_max))
        blocks = vbg.compute_unique_block_coordinates(d_img, *args, trunc_voxel_multiplier=float(trunc_voxels))
        vbg.integrate(blocks, d_img, c_img, k, *args, trunc_voxel_multiplier=float(trunc_voxels))
        fused += 1
    if fused == 0:
        raise NerfpipeError("TSDF fusion produced no surface: no depth map has valid depth inside the scene box")
    mesh = _from_tensor_mesh(vbg.extract_triangle_mesh(weight_threshold=float(min_weight)), has_color)
    return _crop(mesh, aabb, voxel_size)


def _voxel_block_grid(o3d, voxel_size: float, block_count: int):
    o3c = o3d.core
    return o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)), voxel_size=float(voxel_size), block_resolution=BLOCK_RESOLUTION, block_count=block_count,
    )


def _block_budget(extent: Float[Tensor, "3"], voxel_size: float) -> int:
    """Blocks of 16³ voxels covering the (dilated) box, plus one layer around: the most fusion can touch."""
    per_axis = torch.ceil(extent / (BLOCK_RESOLUTION * voxel_size)) + 2
    return int(per_axis.prod())


def _mask_outside(depth: np.ndarray, cameras: Cameras, index: int, lo: Tensor, hi: Tensor) -> np.ndarray:
    """Zero the depth of pixels whose surface point lies outside the box (keeps allocation bounded)."""
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    rays = camera_rays(cameras.to(dtype=torch.float64), index)
    if rays.shape != depth.shape:
        raise NerfpipeError(f"depth map {index} is {depth.shape[1]}x{depth.shape[0]} but its camera is {rays.shape[1]}x{rays.shape[0]}")
    pts = rays.points_at(torch.from_numpy(depth) / rays.z_scale)
    inside = ((pts >= lo) & (pts <= hi)).all(-1).numpy()
    return np.where(inside, depth, 0.0)


def _from_tensor_mesh(m, has_color: bool) -> TriangleMesh:
    verts = m.vertex.positions.numpy() if "positions" in m.vertex else np.zeros((0, 3))
    faces = m.triangle.indices.numpy() if "indices" in m.triangle else np.zeros((0, 3), np.int64)
    colors = None
    if has_color and "colors" in m.vertex:
        colors = np.clip(m.vertex.colors.numpy() * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return TriangleMesh(verts, faces, colors).canonical()  # Open3D's threads emit the blocks in any order


def _crop(mesh: TriangleMesh, aabb: Float[Tensor, "2 3"], voxel_size: float) -> TriangleMesh:
    if mesh.num_faces == 0:
        raise NerfpipeError("TSDF fusion produced no surface: the depth maps are empty or outside the truncation range")
    lo, hi = (aabb.double().cpu().numpy()[i] for i in (0, 1))
    centres = mesh.vertices[mesh.faces].mean(1)
    keep = np.all((centres >= lo) & (centres <= hi), axis=1)
    if not keep.any():
        raise NerfpipeError("TSDF fusion produced no surface inside the scene box")
    out = mesh.submesh(keep)
    out.info.update({"method": "tsdf", "voxel_size": float(voxel_size)})
    return out
