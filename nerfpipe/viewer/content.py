"""What the viewer draws, as plain arrays (no viser here): camera frustums, the scene box, a sample of
training rays with their samples, the sparse points, the mesh, and what a folder holds.

Everything is in the run's world frame (nerfpipe's normalised world, :mod:`nerfpipe.data.scene`), with
OpenCV camera axes, as viser draws cameras.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.scene import SceneData
from nerfpipe.util.errors import NerfpipeError

SPLIT_COLOURS = {"train": (40, 110, 230), "val": (240, 140, 20), "test": (130, 130, 130)}
"""Frustum colour of each split."""


@dataclass
class Frustum:
    """One camera as viser draws it."""

    name: str
    wxyz: np.ndarray
    """Orientation (camera to world), scalar first."""
    position: np.ndarray
    fov: float
    """Vertical field of view in radians."""
    aspect: float
    split: str


def frustums(scene: SceneData) -> "list[Frustum]":
    """One :class:`Frustum` per camera of the scene, named ``<split>/<index>``, in camera order."""
    from nerfpipe.data.camera_path import matrix_to_wxyz

    cams = scene.cameras
    split_of = {int(i): name for name, idx in scene.splits.items() for i in idx}
    wxyz = matrix_to_wxyz(cams.world_from_cam[:, :3, :3].double()).numpy()
    pos = cams.centers.double().numpy()
    fov = (2 * torch.atan(cams.height.double() / (2 * cams.fy.double()))).numpy()
    aspect = (cams.width.double() / cams.height.double()).numpy()
    out = []
    for i in range(len(cams)):
        split = split_of.get(i, "train")
        out.append(Frustum(f"{split}/{i:04d}", wxyz[i], pos[i], float(fov[i]), float(aspect[i]), split))
    return out


def thumbnail(image: np.ndarray, longest: int = 96) -> np.ndarray:
    """uint8 RGB image shrunk (area average, integer factor) to at most ``longest`` pixels on its longer side."""
    rgb = image[..., :3]
    f = max(1, math.ceil(max(rgb.shape[:2]) / longest))
    h, w = (rgb.shape[0] // f) * f, (rgb.shape[1] // f) * f
    small = rgb[:h, :w].reshape(h // f, f, w // f, f, 3).mean(axis=(1, 3))
    return (small + 0.5).astype(np.uint8)


def frustum_scale(scene: SceneData) -> float:
    """A frustum depth that reads at the scene's size: 6 % of the box diagonal."""
    return float(0.06 * (scene.aabb[1] - scene.aabb[0]).double().norm())


def box_segments(aabb: torch.Tensor) -> np.ndarray:
    """The 12 edges ``[12, 2, 3]`` of an axis-aligned box ``[[min], [max]]``.

    Example:
        >>> box_segments(torch.tensor([[0.0, 0, 0], [1, 1, 1]])).shape
        (12, 2, 3)
    """
    lo, hi = aabb.double().numpy()
    corners = np.array([[hi[j] if (k >> j) & 1 else lo[j] for j in range(3)] for k in range(8)])
    edges = [(a, a | (1 << j)) for a in range(8) for j in range(3) if not (a >> j) & 1]
    return corners[np.array(edges)]


def _box_span(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor) -> "tuple[torch.Tensor, torch.Tensor]":
    """Entry and exit distance of rays through a box (slab test); exit < entry where a ray misses it."""
    inv = 1.0 / torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0, t1 = (aabb[0] - origins) * inv, (aabb[1] - origins) * inv
    return torch.minimum(t0, t1).amax(-1).clamp(min=0), torch.maximum(t0, t1).amin(-1)


def training_rays(scene: SceneData, num_rays: int = 64, num_samples: int = 16, seed: int = 0) -> "tuple[np.ndarray, np.ndarray]":
    """A sample of training rays and points along them, as the CS180 course draws them.

    Random pixels of random training cameras; each ray is drawn from its camera centre to where it
    leaves the scene box, with ``num_samples`` evenly spaced samples where it crosses the box (the
    stretch a sampler marches). Returns ``(segments [R, 2, 3], samples [R * num_samples, 3])``.
    """
    from nerfpipe.data.rays import generate_rays

    train = torch.as_tensor(scene.splits["train"], dtype=torch.long)
    if len(train) == 0:
        return np.zeros((0, 2, 3)), np.zeros((0, 3))
    g = torch.Generator().manual_seed(seed)
    cam_idx = train[torch.randint(len(train), (num_rays,), generator=g)]
    cams = scene.cameras
    uv = torch.rand(num_rays, 2, generator=g, dtype=torch.float64) * torch.stack([cams.width[cam_idx], cams.height[cam_idx]], -1).double()
    rays = generate_rays(cams.to(dtype=torch.float64), cam_idx, uv)
    aabb = scene.aabb.double()
    near, far = _box_span(rays.origins, rays.directions, aabb)
    hit = far > near
    far = torch.where(hit, far, torch.full_like(far, scene.far))
    near = torch.where(hit, near, torch.full_like(near, scene.near))
    segments = torch.stack([rays.origins, rays.points_at(far)], dim=1)
    t = near[:, None] + (far - near)[:, None] * (torch.arange(num_samples, dtype=torch.float64) + 0.5) / num_samples
    samples = rays.origins[:, None] + t[..., None] * rays.directions[:, None]
    return segments.numpy(), samples[hit].reshape(-1, 3).numpy()


def sparse_points(scene: SceneData, limit: int = 100_000) -> "tuple[np.ndarray, np.ndarray] | None":
    """``(xyz, rgb uint8)`` of the sparse points (an even subsample above ``limit``), or None."""
    if scene.points is None or len(scene.points.xyz) == 0:
        return None
    step = max(1, math.ceil(len(scene.points.xyz) / limit))
    return scene.points.xyz[::step].double().numpy(), np.asarray(scene.points.rgb[::step], dtype=np.uint8)


def read_mesh(path: Path, scene: SceneData, max_faces: int = 300_000) -> "tuple[np.ndarray, np.ndarray, np.ndarray | None]":
    """``(vertices in the world frame, faces, vertex colours uint8 or None)`` of a mesh file written in the
    input frame (``nerfpipe mesh``), mapped by the scene's ``world_from_input``. Larger meshes than
    ``max_faces`` are refused (the simplified one is the one to show)."""
    from nerfpipe.util.errors import require

    trimesh = require("trimesh", "mesh")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except (OSError, ValueError) as exc:
        raise NerfpipeError(f"cannot read the mesh ({type(exc).__name__}: {exc})", path) from exc
    if len(mesh.faces) > max_faces:
        raise NerfpipeError(f"mesh has {len(mesh.faces)} faces (more than {max_faces} to show)", path)
    vertices = scene.world_from_input.apply_points(torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64)).numpy()
    colours = getattr(mesh.visual, "vertex_colors", None)
    colours = None if colours is None or len(colours) != len(vertices) else np.asarray(colours)[:, :3].astype(np.uint8)
    return vertices, np.asarray(mesh.faces, dtype=np.int64), colours


def find_mesh(folders: "list[Path]") -> "Path | None":
    """The mesh to show: ``mesh/mesh_simplified.ply``, else ``mesh/mesh.ply``, in the first folder that has one."""
    for folder in folders:
        for name in ("mesh_simplified.ply", "mesh.ply"):
            if (folder / "mesh" / name).is_file():
                return folder / "mesh" / name
    return None


__all__ = ["Frustum", "box_segments", "find_mesh", "frustums", "read_mesh", "sparse_points", "thumbnail", "training_rays"]
