"""NeRF scenes stored in one ``.npz`` file, in two layouts.

* **CS180** (Berkeley course): ``images_train [N,H,W,3]``, ``c2ws_train [N,4,4]``, ``images_val``,
  ``c2ws_val``, ``c2ws_test`` (poses only) and a scalar ``focal``.
* **tiny NeRF** (the original authors' ``tiny_nerf_data.npz``): ``images [N,H,W,3]`` (float in
  [0, 1] or uint8), ``poses [N,4,4]`` or ``[N,3,4]`` and ``focal``. The first
  :data:`TINY_TRAIN` cameras are ``train``, the rest ``val``.

Poses are OpenGL/Blender camera-to-world; they are converted to nerfpipe's OpenCV convention and
the world frame is kept (identity ``world_from_input``). Images are stored in memory as uint8.
The principal point is the image centre. The file is always read with ``allow_pickle=False``.
"""

import zipfile
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras, opengl_to_opencv
from nerfpipe.data.image_file import images_uint8
from nerfpipe.data.scene import ImageSet, SceneData, Similarity
from nerfpipe.data_adapters._common import check_focal, check_world_from_cam, synthetic_bounds
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.registry import AdapterSpec

CS180_KEYS = ("images_train", "c2ws_train", "images_val", "c2ws_val", "c2ws_test", "focal")
TINY_KEYS = ("images", "poses", "focal")
TINY_TRAIN = 100
"""Cameras of a tiny-NeRF npz that are used for training; the rest are validation."""


def _npz_file(path: Path) -> "Path | None":
    """``path`` itself when it is a ``.npz`` file, or the only ``.npz`` in a folder."""
    if path.is_file():
        return path if path.suffix.lower() == ".npz" else None
    found = sorted(path.glob("*.npz")) if path.is_dir() else []
    return found[0] if len(found) == 1 else None


def _keys(file: Path) -> "set[str]":
    with zipfile.ZipFile(file) as zf:
        return {n[:-4] if n.endswith(".npy") else n for n in zf.namelist()}


def detect(path: Path) -> int:
    """10 for a known layout, 1 for another ``.npz`` (so that reading names what is wrong)."""
    file = _npz_file(Path(path))
    if file is None:
        return 0
    try:
        keys = _keys(file)
    except (OSError, zipfile.BadZipFile):
        return 1
    return 10 if set(CS180_KEYS) <= keys or set(TINY_KEYS) <= keys else 1


def _load_arrays(file: Path) -> "dict[str, np.ndarray]":
    try:
        with np.load(file, allow_pickle=False) as data:
            return {k: np.asarray(data[k]) for k in data.files}
    except Exception as exc:  # zipfile, zlib, numpy format and pickle errors all mean "unreadable"
        raise NerfpipeError(f"cannot read npz file ({type(exc).__name__}: {exc})", file) from exc


def _require(arrays: dict, keys: "tuple[str, ...]", layout: str, file: Path) -> None:
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise NerfpipeError(
            f"{layout} npz is missing key(s) {', '.join(missing)} (has: {', '.join(sorted(arrays)) or 'none'})", file
        )


def _world_from_cam(arrays: dict, key: str, count: "int | None", file: Path) -> np.ndarray:
    m = check_world_from_cam(arrays[key], file, key)
    if count is not None and len(m) != count:
        raise NerfpipeError(f"{key} has {len(m)} poses but there are {count} images", file)
    return m


def _read_cs180(arrays: dict, file: Path):
    """(images with has_image mask, OpenGL world_from_cam [N,4,4], split sizes)."""
    _require(arrays, CS180_KEYS, "CS180", file)
    train = images_uint8(arrays["images_train"], file, "images_train")
    val = images_uint8(arrays["images_val"], file, "images_val")
    if train.shape[1:] != val.shape[1:]:
        raise NerfpipeError(f"images_train {list(train.shape[1:])} and images_val {list(val.shape[1:])} differ in size", file)
    poses = [
        _world_from_cam(arrays, "c2ws_train", len(train), file),
        _world_from_cam(arrays, "c2ws_val", len(val), file),
        _world_from_cam(arrays, "c2ws_test", None, file),
    ]
    sizes = [len(p) for p in poses]
    has_image = np.arange(sum(sizes)) < sizes[0] + sizes[1]
    return ImageSet(array=np.concatenate([train, val]), has_image=has_image), np.concatenate(poses), sizes


def _read_tiny(arrays: dict, file: Path):
    _require(arrays, TINY_KEYS, "tiny-NeRF", file)
    images = images_uint8(arrays["images"], file, "images")
    poses = _world_from_cam(arrays, "poses", len(images), file)
    n_train = min(TINY_TRAIN, len(images))
    return ImageSet(array=images), poses, [n_train, len(images) - n_train, 0]


def _splits(sizes: "list[int]") -> "dict[str, np.ndarray]":
    ends = np.cumsum([0, *sizes])
    return {name: np.arange(ends[i], ends[i + 1], dtype=np.int64) for i, name in enumerate(("train", "val", "test"))}


def read(path: Path) -> SceneData:
    """Read a CS180 or tiny-NeRF npz (a file, or a folder holding exactly one ``.npz``)."""
    path = Path(path)
    file = _npz_file(path)
    if file is None:
        raise NerfpipeError("not an .npz file (or a folder with exactly one)", path)
    arrays = _load_arrays(file)
    is_cs180 = any(k.startswith(("images_", "c2ws_")) for k in arrays)
    images, gl_poses, sizes = (_read_cs180 if is_cs180 else _read_tiny)(arrays, file)
    focal = check_focal(arrays["focal"], file)
    h, w = images.array.shape[1:3]
    cameras = Cameras.create(opengl_to_opencv(torch.from_numpy(gl_poses)), focal, focal, w / 2, h / 2, w, h, dtype=torch.float64)
    near, far, aabb = synthetic_bounds(cameras)
    return SceneData(
        cameras=cameras.to(dtype=torch.float32),
        images=images,
        splits=_splits(sizes),
        near=near,
        far=far,
        aabb=aabb,
        world_from_input=Similarity(),
        source=file,
        format="cs180-npz" if is_cs180 else "tiny-nerf-npz",
        has_alpha=images.array.shape[-1] == 4,
        camera_models=["PINHOLE"] * len(cameras),
    )


ADAPTER = AdapterSpec(
    name="npz",
    description="NeRF scenes in one .npz: CS180 layout (images_train, c2ws_*, focal) or tiny NeRF (images, poses, focal)",
    detect=detect,
    read=read,
)
