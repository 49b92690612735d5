"""The scene record every data adapter returns: :class:`SceneData`.

Glossary:
    input frame   the world coordinates of the files on disk
    world frame   nerfpipe's normalised world: ``x_world = scale * R @ x_input + t``
                  (:class:`Similarity` ``world_from_input``); exports map back with its inverse
"""

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.data.image_file import read_image_uint8  # noqa: F401 (the one image reader; re-exported)
from nerfpipe.util.typing import Bool, Float, Int, Tensor

SPLITS = ("train", "val", "test")


@dataclass
class Similarity:
    """A similarity transform ``x -> scale * rotation @ x + translation``."""

    rotation: Float[Tensor, "3 3"] = field(default_factory=lambda: torch.eye(3, dtype=torch.float64))
    translation: Float[Tensor, "3"] = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    scale: float = 1.0

    def apply_points(self, x: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        r, t = self.rotation.to(x), self.translation.to(x)
        return self.scale * (x @ r.T) + t

    def apply_world_from_cam(self, m: Float[Tensor, "*bs 4 4"]) -> Float[Tensor, "*bs 4 4"]:
        """Map camera-to-world rigid transforms into the new frame (rotation stays orthonormal)."""
        out = m.clone()
        r = self.rotation.to(m)
        out[..., :3, :3] = r @ m[..., :3, :3]
        out[..., :3, 3] = self.apply_points(m[..., :3, 3])
        return out

    def inverse(self) -> "Similarity":
        r_inv = self.rotation.T
        return Similarity(r_inv, -(r_inv @ self.translation) / self.scale, 1.0 / self.scale)

    def compose(self, first: "Similarity") -> "Similarity":
        """``self ∘ first``: apply ``first`` and then ``self``."""
        return Similarity(
            self.rotation @ first.rotation,
            self.scale * (self.rotation @ first.translation) + self.translation,
            self.scale * first.scale,
        )

    def matrix(self) -> Float[Tensor, "4 4"]:
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = self.scale * self.rotation.double()
        m[:3, 3] = self.translation.double()
        return m


@dataclass
class Points3D:
    """Sparse 3D points (e.g. from COLMAP) in the world frame, with their tracks when the source has them.

    A track observation says that camera ``track_camera[k]`` sees point ``track_point[k]`` at pixel
    ``track_xy[k]``; the three are flat, one row per observation (a point seen by 6 cameras has 6
    rows). Indices stay valid under a change of frame (only ``xyz`` moves); code that drops points
    must renumber ``track_point`` (:meth:`select`).
    """

    xyz: Float[Tensor, "num_points 3"]
    rgb: "Tensor"  # uint8 [num_points, 3]
    error: "Tensor | None" = None
    """Per-point reprojection error in pixels, when the source has it."""
    track_point: "Int[Tensor, 'num_obs'] | None" = None
    """int64 row into ``xyz`` of each observation's point."""
    track_camera: "Int[Tensor, 'num_obs'] | None" = None
    """int64 index into :attr:`SceneData.cameras` of each observation's camera."""
    track_xy: "Float[Tensor, 'num_obs 2'] | None" = None
    """float64 pixel of each observation (the keypoint; top-left pixel centre at (0.5, 0.5))."""

    def __post_init__(self) -> None:
        tracks = (self.track_point, self.track_camera, self.track_xy)
        if any(t is None for t in tracks) != all(t is None for t in tracks):
            raise ValueError("give all of track_point, track_camera and track_xy, or none")
        if self.track_point is not None and not len(self.track_point) == len(self.track_camera) == len(self.track_xy):
            raise ValueError("track_point, track_camera and track_xy need one row per observation")
        if self.track_point is not None and len(self.track_point) and not 0 <= int(self.track_point.min()) <= int(self.track_point.max()) < len(self.xyz):
            raise ValueError(f"track_point must index the {len(self.xyz)} points")

    @property
    def has_tracks(self) -> bool:
        return self.track_point is not None

    def select(self, keep: "Bool[Tensor, 'num_points']") -> "Points3D":
        """The points where ``keep`` is true, with their observations renumbered (the others' dropped)."""
        keep = torch.as_tensor(keep, dtype=torch.bool)
        error = None if self.error is None else self.error[keep]
        if not self.has_tracks:
            return Points3D(self.xyz[keep], self.rgb[keep], error)
        row = torch.cumsum(keep.long(), 0) - 1
        obs = keep[self.track_point]
        return Points3D(self.xyz[keep], self.rgb[keep], error, row[self.track_point[obs]], self.track_camera[obs], self.track_xy[obs])


class ImageSet:
    """Images of a scene, loaded lazily and kept uint8 until used.

    Either ``paths`` (one per camera; ``None`` for poses without an image, such as a
    test split of poses only) or an in-memory ``array`` ``[M, H, W, C]`` uint8. With an
    array, ``has_image`` (bool ``[N]``) marks the cameras that have an image; the array then
    holds only those, in camera order (``M = has_image.sum()``). Without it, ``M = N``.
    """

    def __init__(
        self,
        paths: "list[Path | None] | None" = None,
        array: "np.ndarray | None" = None,
        has_image: "np.ndarray | None" = None,
    ) -> None:
        if (paths is None) == (array is None):
            raise ValueError("give exactly one of paths or array")
        if has_image is not None and (array is None or int(np.sum(has_image)) != len(array)):
            raise ValueError("has_image needs an array with one row per True entry")
        self.paths = paths
        self.array = array
        self._rows = None if has_image is None else np.where(has_image, np.cumsum(has_image) - 1, -1)
        """Array row of each camera, -1 for none (``None``: row i is camera i)."""

    def __len__(self) -> int:
        if self.paths is not None:
            return len(self.paths)
        return len(self.array) if self._rows is None else len(self._rows)

    def has(self, i: int) -> bool:
        if self.array is not None:
            return self._rows is None or bool(self._rows[i] >= 0)
        return self.paths[i] is not None

    def name(self, i: int) -> str:
        return str(self.paths[i]) if self.paths is not None else f"image[{i}]"

    def load(self, i: int) -> np.ndarray:
        """Image ``i`` as uint8 ``[H, W, C]`` (C = 3 or 4)."""
        if not self.has(i):
            raise NerfpipeError(f"camera {i} has no image (poses only)")
        if self.array is not None:
            return self.array[i if self._rows is None else self._rows[i]]
        return read_image_uint8(self.paths[i])


@dataclass
class SceneData:
    """What every data adapter returns, in nerfpipe's single camera convention."""

    cameras: Cameras
    """All cameras ``[N]`` (OpenCV convention, normalised world frame)."""
    images: ImageSet
    """One entry per camera; test cameras may have no image."""
    splits: "dict[str, np.ndarray]"
    """Camera indices per split: ``train``, ``val``, ``test`` (int64 arrays, possibly empty)."""
    near: float
    """Near bound along rays, in world units."""
    far: float
    """Far bound along rays, in world units."""
    aabb: Float[Tensor, "2 3"]
    """Axis-aligned scene box ``[min, max]`` in world units."""
    world_from_input: Similarity
    """The normalisation applied to the input frame; exports map back with its inverse."""
    source: Path
    """The file or folder the scene was read from."""
    format: str
    """Adapter name, e.g. ``"cs180-npz"``, ``"blender"``, ``"colmap"``."""
    points: "Points3D | None" = None
    """Sparse 3D points with colours, if the source has them."""
    has_alpha: bool = False
    """Whether the images carry an alpha channel (RGBA input)."""
    camera_models: "list[str]" = field(default_factory=list)
    """The source's camera model name per camera (e.g. ``PINHOLE``, ``OPENCV``)."""
    meta: dict = field(default_factory=dict)
    """Format-specific extras (e.g. ``aabb_scale``, ``applied_transform``)."""

    def split_cameras(self, split: str) -> Cameras:
        return self.cameras[torch.as_tensor(self.splits[split], dtype=torch.long)]

    @property
    def shows_surroundings(self) -> bool:
        """Whether the photographs show more than the object region: a real capture (sparse points from SfM, no
        alpha), whose floor, walls and sky a model must explain too (``SceneInfo.unbounded``)."""
        return self.points is not None and not self.has_alpha

    def __post_init__(self) -> None:
        for name in SPLITS:
            self.splits.setdefault(name, np.zeros(0, dtype=np.int64))
        self._check_geometry()

    def _check_geometry(self) -> None:
        """Every adapter builds a SceneData, so a degenerate capture is refused here, once, naming the source:
        cameras all at one place (or NaN intrinsics) give empty or NaN bounds, which training would divide by."""
        cams = self.cameras
        intrinsics = torch.stack([cams.fx, cams.fy, cams.cx, cams.cy]).double()
        if not (torch.isfinite(intrinsics).all() and torch.isfinite(cams.dist_params.double()).all()):
            raise NerfpipeError("camera intrinsics or distortion contain NaN or Inf", self.source)
        box = self.aabb.double()
        if not (math.isfinite(self.near) and math.isfinite(self.far) and 0 <= self.near < self.far):
            raise NerfpipeError(f"degenerate scene: near {self.near:.4g}, far {self.far:.4g} (are all cameras at one position?)", self.source)
        if not (torch.isfinite(box).all() and bool((box[1] > box[0]).all())):
            raise NerfpipeError("degenerate scene: its box has no volume or is not finite (are all cameras at one position?)", self.source)


def check_images(scene: SceneData, indices=None) -> None:
    """Decode the images of ``indices`` (default: all) once and check each against its camera's size.

    Adapters read only the file headers; this finds a truncated or corrupt image, or an array of the
    wrong size, before any work starts (the load stage, the trainer's validation images), as one
    :class:`NerfpipeError` naming the file.
    """
    cams = scene.cameras
    for i in range(len(cams)) if indices is None else (int(i) for i in indices):
        if not scene.images.has(i):
            continue
        h, w = scene.images.load(i).shape[:2]
        if (w, h) != (int(cams.width[i]), int(cams.height[i])):
            raise NerfpipeError(f"image is {w}x{h} but its camera is {int(cams.width[i])}x{int(cams.height[i])}", scene.images.name(i))


def holdout_split(n: int, every: int = 8) -> "dict[str, np.ndarray]":
    """The shared train/val rule for captures without their own splits (COLMAP, single-file transforms).

    Cameras are taken in the adapter's stable order (sorted by image name); every ``every``-th
    one, starting with the first (``i % every == 0``), is ``val``, the rest ``train``, as in the
    LLFF/mip-NeRF convention. ``test`` is empty; a single camera is kept for training.

    Example:
        >>> holdout_split(10, every=4)["val"].tolist()
        [0, 4, 8]
    """
    idx = np.arange(n, dtype=np.int64)
    val = (idx % every == 0) & (n > 1)
    return {"train": idx[~val], "val": idx[val], "test": np.zeros(0, dtype=np.int64)}
