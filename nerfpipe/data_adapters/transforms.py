"""``transforms.json`` datasets in their three flavours.

* **Blender / NeRF synthetic**: ``transforms_{train,val,test}.json`` side by side; the splits come
  from the file names. ``camera_angle_x`` gives the focal length ``0.5 * W / tan(0.5 * angle)``;
  ``file_path`` usually has no extension (``.png`` is appended). The frame is kept (identity
  ``world_from_input``). A missing image is an error.
* **instant-ngp** ``transforms.json``: global ``fl_x fl_y cx cy w h`` (floats allowed),
  ``k1 k2 p1 p2`` (OPENCV distortion), ``camera_angle_x/y`` as fallbacks, ``aabb_scale``
  (kept in ``meta``). Frames whose image is missing are skipped with a warning, as instant-ngp does.
* **nerfstudio** ``transforms.json``: as instant-ngp plus ``camera_model`` (PINHOLE, OPENCV,
  OPENCV_FISHEYE), per-frame intrinsics that override the global ones, ``applied_transform``
  (kept in ``meta``) and ``ply_file_path`` (sparse points with colours).

Single-file captures (instant-ngp, nerfstudio) are ordered by image file name and normalised
with :func:`~nerfpipe.data.normalize.auto_normalization` (applied to poses and points); every 8th
camera, starting with the first, is ``val`` (:func:`~nerfpipe.data.scene.holdout_split`), there is
no ``test``. ``transform_matrix`` is OpenGL camera-to-world in every flavour.

Image sizes are checked against the cameras from the file headers only (nothing is decoded).
"""

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras, opengl_to_opencv
from nerfpipe.data.image_file import image_header
from nerfpipe.data.normalize import auto_normalization, bounds_from_cameras, bounds_from_points
from nerfpipe.data.scene import SPLITS, ImageSet, Points3D, SceneData, Similarity, holdout_split
from nerfpipe.data_adapters._common import check_focal, check_world_from_cam, synthetic_bounds
from nerfpipe.functional.distortion import Distortion
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.util.paths import resolve_inside
from nerfpipe.util.registry import AdapterSpec

SPLIT_FILES = {split: f"transforms_{split}.json" for split in SPLITS}
CAPTURE_FILE = "transforms.json"
VAL_EVERY = 8
"""Single-file captures: camera ``i`` (in file-name order) is ``val`` when ``i % VAL_EVERY == 0``."""
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "camera_model",
                  "is_fisheye", "k1", "k2", "k3", "k4", "p1", "p2")  # fmt: skip


@dataclass
class _Frame:
    """One frame of a transforms file, before conversion."""

    image: Path
    gl_matrix: object
    """``transform_matrix`` as read (validated later, with all frames)."""
    intrinsics: dict
    """Global intrinsics updated with the frame's own."""


# ---------------------------------------------------------------- detection


def detect(path: Path) -> int:
    """10 for a ``transforms*.json`` file, or a folder holding ``transforms.json``/``transforms_train.json``."""
    path = Path(path)
    if path.is_file():
        return 10 if path.name.startswith("transforms") and path.suffix == ".json" else 0
    if path.is_dir():
        return 10 if (path / CAPTURE_FILE).is_file() or (path / SPLIT_FILES["train"]).is_file() else 0
    return 0


def _dataset_files(path: Path) -> "dict[str, Path]":
    """``{split: file}`` for a Blender set, or ``{"capture": file}`` for a single-file capture.

    A ``transforms_<split>.json`` file stands for its folder's whole Blender set; a folder with
    split files is a Blender set even when it also holds ``transforms.json``.
    """
    folder = path if path.is_dir() else path.parent
    if path.is_file() and path.name not in SPLIT_FILES.values():
        return {"capture": path}
    splits = {s: folder / name for s, name in SPLIT_FILES.items() if (folder / name).is_file()}
    if splits:
        return splits
    if (folder / CAPTURE_FILE).is_file():
        return {"capture": folder / CAPTURE_FILE}
    raise NerfpipeError(f"no {CAPTURE_FILE} or {SPLIT_FILES['train']} here", path)


# ---------------------------------------------------------------- parsing


def _load_json(file: Path) -> dict:
    try:
        doc = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise NerfpipeError(f"cannot read JSON ({type(exc).__name__}: {exc})", file) from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
        raise NerfpipeError("not a transforms file: no 'frames' list at the top level", file)
    return doc


def _image_path(root: Path, frame: dict, json_file: Path) -> Path:
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise NerfpipeError("a frame has no 'file_path' string", json_file)
    name = frame["file_path"].replace("\\", "/")  # paths written on Windows
    full = resolve_inside(root, name, json_file)
    if not full.suffix and not full.is_file():  # Blender writes paths without the extension
        full = resolve_inside(root, name + ".png", json_file)
    return full


def _frames(doc: dict, json_file: Path, skip_missing: bool) -> "list[_Frame]":
    """Frames with an existing image; missing ones raise, or are skipped with one warning."""
    root = json_file.parent
    glob = {k: doc[k] for k in INTRINSIC_KEYS if k in doc}
    frames, missing = [], []
    for fr in doc["frames"]:
        image = _image_path(root, fr, json_file)
        if "transform_matrix" not in fr:
            raise NerfpipeError(f"frame '{fr['file_path']}' has no transform_matrix", json_file)
        if not image.is_file():
            if not skip_missing:
                raise NerfpipeError(f"image file is missing (listed in {json_file.name})", image)
            missing.append(image.name)
            continue
        own = {k: fr[k] for k in INTRINSIC_KEYS if k in fr}
        frames.append(_Frame(image, fr["transform_matrix"], {**glob, **own}))
    if not frames:  # an error, and no warning besides it: the user reads one line
        raise NerfpipeError(f"none of the {len(doc['frames'])} frames has an existing image file", json_file)
    if missing:
        warnings.warn(f"{json_file}: {len(missing)} of {len(doc['frames'])} frames have no image file and are "
                      f"skipped (first: {', '.join(missing[:3])})", UserWarning, stacklevel=3)  # fmt: skip
    return frames


# ---------------------------------------------------------------- intrinsics


def _size(intr: dict, shape: "tuple[int, int, int]", image: Path) -> "tuple[int, int]":
    """Camera ``(w, h)``: from the file when given (and checked against the image), else the image."""
    h_img, w_img = shape[:2]
    w = round(float(intr["w"])) if "w" in intr else w_img
    h = round(float(intr["h"])) if "h" in intr else h_img
    if (w, h) != (w_img, h_img):
        raise NerfpipeError(f"image is {w_img}x{h_img} but its camera says w={w}, h={h}", image)
    return w, h


def _focals(intr: dict, w: int, h: int, file: Path) -> "tuple[float, float]":
    """``fl_x``/``fl_y``, else from ``camera_angle_x``/``camera_angle_y``; ``fl_y`` defaults to ``fl_x``."""
    if "fl_x" in intr:
        fx = check_focal(intr["fl_x"], file, "fl_x")
    elif "camera_angle_x" in intr:
        fx = check_focal(0.5 * w / math.tan(0.5 * _angle(intr, "camera_angle_x", file)), file, "focal from camera_angle_x")
    else:
        raise NerfpipeError("no focal length: give fl_x or camera_angle_x", file)
    if "fl_y" in intr:
        return fx, check_focal(intr["fl_y"], file, "fl_y")
    if "camera_angle_y" in intr:
        return fx, check_focal(0.5 * h / math.tan(0.5 * _angle(intr, "camera_angle_y", file)), file, "focal from camera_angle_y")
    return fx, fx


def _angle(intr: dict, key: str, file: Path) -> float:
    """A field of view in radians, strictly between 0 and pi (0 would divide by zero, pi or more is no lens)."""
    angle = float(intr[key])
    if not 0 < angle < math.pi:
        raise NerfpipeError(f"{key} must be a field of view in radians between 0 and pi, got {angle}", file)
    return angle


def _distortion(intr: dict, file: Path) -> "tuple[str, Distortion, list[float]]":
    """(camera model name, distortion code, four parameters)."""
    k = {name: float(intr.get(name, 0.0)) for name in ("k1", "k2", "k3", "k4", "p1", "p2")}
    model = str(intr.get("camera_model", "OPENCV_FISHEYE" if intr.get("is_fisheye") else "OPENCV")).upper()
    if model == "OPENCV_FISHEYE":
        return model, Distortion.FISHEYE, [k["k1"], k["k2"], k["k3"], k["k4"]]
    if model == "PINHOLE":
        return model, Distortion.NONE, [0.0] * 4
    if model != "OPENCV":
        raise NerfpipeError(f"camera_model '{model}' is not supported (PINHOLE, OPENCV, OPENCV_FISHEYE)", file)
    if k["k3"] or k["k4"]:
        raise NerfpipeError("k3/k4 with the OPENCV model are not supported (nerfpipe's OPENCV is k1 k2 p1 p2)", file)
    params = [k["k1"], k["k2"], k["p1"], k["p2"]]
    return ("OPENCV", Distortion.OPENCV, params) if any(params) else ("PINHOLE", Distortion.NONE, params)


def _cameras(frames: "list[_Frame]", file: Path) -> "tuple[Cameras, list[str], bool]":
    """float64 cameras in the OpenCV convention (input frame), model names, and whether all images are RGBA."""
    gl = check_world_from_cam([f.gl_matrix for f in frames], file, "transform_matrix")
    cols: dict[str, list] = {k: [] for k in ("fx", "fy", "cx", "cy", "width", "height", "distortion", "dist_params")}
    models, channels = [], []
    for f in frames:
        shape = image_header(f.image)
        try:
            w, h = _size(f.intrinsics, shape, f.image)
            fx, fy = _focals(f.intrinsics, w, h, file)
            model, code, params = _distortion(f.intrinsics, file)
            cx, cy = float(f.intrinsics.get("cx", w / 2)), float(f.intrinsics.get("cy", h / 2))
        except (TypeError, ValueError) as exc:
            raise NerfpipeError(f"non-numeric intrinsics for {f.image.name} ({exc})", file) from exc
        for key, v in zip(cols, (fx, fy, cx, cy, w, h, int(code), params)):
            cols[key].append(v)
        models.append(model)
        channels.append(shape[2])
    cams = Cameras.create(opengl_to_opencv(torch.from_numpy(gl)), **cols, dtype=torch.float64)
    return cams, models, all(c == 4 for c in channels)


# ---------------------------------------------------------------- the two dataset kinds


def _read_blender(files: "dict[str, Path]") -> SceneData:
    cams, images, models, alpha, splits, start = [], [], [], [], {}, 0
    for split, file in files.items():
        frames = _frames(_load_json(file), file, skip_missing=False)
        c, m, a = _cameras(frames, file)
        cams.append(c)
        models += m
        alpha.append(a)
        images += [f.image for f in frames]
        splits[split] = np.arange(start, start + len(frames), dtype=np.int64)
        start += len(frames)
    cameras = Cameras.cat(cams)
    near, far, aabb = synthetic_bounds(cameras)
    return SceneData(
        cameras=cameras.to(dtype=torch.float32),
        images=ImageSet(paths=images),
        splits=splits,
        near=near,
        far=far,
        aabb=aabb,
        world_from_input=Similarity(),
        source=next(iter(files.values())).parent,
        format="blender",
        has_alpha=all(alpha),
        camera_models=models,
    )


def _read_points(doc: dict, file: Path) -> "Points3D | None":
    """The nerfstudio ``ply_file_path`` point cloud (input frame), if any."""
    if "ply_file_path" not in doc:
        return None
    ply = resolve_inside(file.parent, doc["ply_file_path"], file)
    if not ply.is_file():
        raise NerfpipeError(f"point cloud file is missing (ply_file_path in {file.name})", ply)
    trimesh = require("trimesh", "mesh")
    try:
        cloud = trimesh.load(ply, process=False)
        xyz = np.asarray(cloud.vertices, dtype=np.float64)
        colors = getattr(cloud, "colors", None)
        if colors is None or len(colors) != len(xyz):
            colors = getattr(getattr(cloud, "visual", None), "vertex_colors", None)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise NerfpipeError(f"cannot read point cloud ({type(exc).__name__}: {exc})", ply) from exc
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0 or not np.isfinite(xyz).all():
        raise NerfpipeError(f"point cloud has no finite xyz points (shape {list(xyz.shape)})", ply)
    rgb = np.full((len(xyz), 3), 128, np.uint8) if colors is None or len(colors) != len(xyz) else np.asarray(colors)[:, :3]
    return Points3D(xyz=torch.from_numpy(xyz), rgb=torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.uint8)))


def _capture_meta(doc: dict) -> dict:
    meta = {k: doc[k] for k in ("aabb_scale", "applied_transform", "camera_model", "ply_file_path") if k in doc}
    meta["split_rule"] = f"every {VAL_EVERY}th camera in file-name order is val (i % {VAL_EVERY} == 0), no test"
    return meta


def _read_capture(file: Path) -> SceneData:
    doc = _load_json(file)
    frames = sorted(_frames(doc, file, skip_missing=True), key=lambda f: str(f.image))
    cameras, models, alpha = _cameras(frames, file)
    sim = auto_normalization(cameras)
    cameras.world_from_cam = sim.apply_world_from_cam(cameras.world_from_cam)
    points = _read_points(doc, file)
    if points is not None:
        points.xyz = sim.apply_points(points.xyz).float()
    near, far, aabb = bounds_from_points(cameras, points.xyz) if points is not None else bounds_from_cameras(cameras)
    return SceneData(
        cameras=cameras.to(dtype=torch.float32),
        images=ImageSet(paths=[f.image for f in frames]),
        splits=holdout_split(len(frames), VAL_EVERY),
        near=near,
        far=far,
        aabb=aabb,
        world_from_input=sim,
        source=file,
        format="nerfstudio" if {"camera_model", "applied_transform", "ply_file_path"} & doc.keys() else "instant-ngp",
        points=points,
        has_alpha=alpha,
        camera_models=models,
        meta=_capture_meta(doc),
    )


def read(path: Path) -> SceneData:
    """Read a Blender set, an instant-ngp or a nerfstudio ``transforms.json`` (file or folder)."""
    path = Path(path)
    if not path.exists():
        raise NerfpipeError("no such file or folder", path)
    files = _dataset_files(path)
    return _read_capture(files["capture"]) if "capture" in files else _read_blender(files)


ADAPTER = AdapterSpec(
    name="transforms",
    description="transforms.json: Blender transforms_{train,val,test}.json, instant-ngp or nerfstudio captures",
    detect=detect,
    read=read,
)
