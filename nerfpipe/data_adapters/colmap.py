"""COLMAP sparse models (binary or text) plus an ``images/`` folder, read with pycolmap.

Layouts recognised (first match wins): ``<root>/sparse/N/`` (of several numbered models, the one with the most
registered images), ``<root>/sparse/``, or the model files ``cameras``, ``images`` and ``points3D`` (``.bin`` or
``.txt``) directly in ``<root>``.
Images are looked up as ``<root>/images/<image name>`` (or ``<root>/<image name>`` where there is no ``images/``
folder: COLMAP run on the photos' own folder); a name (symlinks resolved) must stay inside that folder
(:func:`nerfpipe.util.paths.resolve_inside`), which may itself be a link to the photos. A registered image whose file
is missing (a photograph deleted after the reconstruction) is left out with one warning, as the transforms adapter
skips a frame without its image; all of them missing is an error naming the folder.
An image may be a downscaled copy of what COLMAP saw (the same aspect, to a pixel): its camera and
keypoints are scaled to it.

Only registered images become cameras, sorted by image name; every 8th of them is ``val``
(:func:`nerfpipe.data.scene.holdout_split`). COLMAP already uses nerfpipe's camera convention
(world-to-camera poses, OpenCV axes, top-left pixel centre at (0.5, 0.5)), so poses are only
inverted and then normalised (:func:`nerfpipe.data.normalize.auto_normalization`).

The sparse points carry their tracks (:class:`nerfpipe.data.scene.Points3D` ``track_*``): every
element of every ``point3D.track`` whose image is one of the cameras, ordered by camera and then
by keypoint. ``meta`` keeps ``colmap_mean_reprojection_error`` (pycolmap's figure, recomputed on
load: the mean over points of each track's mean error).
"""

import warnings
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras, invert_rigid
from nerfpipe.data.image_file import image_header
from nerfpipe.data.normalize import auto_normalization, bounds_from_points
from nerfpipe.data.scene import ImageSet, Points3D, SceneData, holdout_split
from nerfpipe.data_adapters._common import check_focal
from nerfpipe.functional.distortion import Distortion
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.util.paths import resolve_inside
from nerfpipe.util.registry import AdapterSpec

MODEL_FILES = ("cameras", "images", "points3D")
IMAGE_SCALE = "colmap_image_scale"
"""``SceneData.meta`` key, when images are downscaled copies: each camera's image width over COLMAP's (its
pixels are that much smaller than the model's, in which ``colmap_mean_reprojection_error`` is measured)."""


def _param_map(model: str, p: "list[float]") -> "tuple[float, float, float, float, Distortion, list[float]] | None":
    """COLMAP params -> (fx, fy, cx, cy, distortion code, 4 distortion params); None if unsupported."""
    if model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2], Distortion.NONE, [0.0] * 4
    if model == "PINHOLE":
        return p[0], p[1], p[2], p[3], Distortion.NONE, [0.0] * 4
    if model == "SIMPLE_RADIAL":
        return p[0], p[0], p[1], p[2], Distortion.OPENCV, [p[3], 0.0, 0.0, 0.0]
    if model == "RADIAL":
        return p[0], p[0], p[1], p[2], Distortion.OPENCV, [p[3], p[4], 0.0, 0.0]
    if model == "OPENCV":
        return p[0], p[1], p[2], p[3], Distortion.OPENCV, list(p[4:8])
    if model == "OPENCV_FISHEYE":
        return p[0], p[1], p[2], p[3], Distortion.FISHEYE, list(p[4:8])
    return None


SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE")


def _model_file(model_dir: Path, stem: str) -> "Path | None":
    for ext in (".bin", ".txt"):
        if (model_dir / f"{stem}{ext}").is_file():
            return model_dir / f"{stem}{ext}"
    return None


def _has_model(folder: Path) -> bool:
    return folder.is_dir() and all(_model_file(folder, s) is not None for s in MODEL_FILES)


def _registered_count(model_dir: Path) -> int:
    """Registered images of the model in ``model_dir`` (-1 where it cannot be read)."""
    try:
        return int(_open(model_dir).num_reg_images())
    except NerfpipeError:
        return -1


def _candidates(root: Path) -> "list[Path]":
    """The folders under ``root`` that hold model files: the numbered models in ``sparse/`` (by number), else
    ``sparse/`` itself, else ``root`` (the first that has one)."""
    if (root / "sparse").is_dir():
        numbered = sorted((d for d in (root / "sparse").iterdir() if d.name.isdigit() and _has_model(d)), key=lambda d: int(d.name))
        if numbered:
            return numbered
    return [c for c in (root / "sparse", root) if _has_model(c)][:1]


def find_model_dir(root: Path) -> "Path | None":
    """The folder holding the model files under ``root``, or None.

    Where ``sparse/`` holds several numbered models (COLMAP's mapper writes one per connected group of photos, and the
    largest is not always ``0``), the one with the most registered images (the lowest number among equals; each is read
    to count them, so only where there are several)."""
    found = _candidates(root)
    if len(found) > 1:
        counts = [_registered_count(d) for d in found]
        return found[counts.index(max(counts))]
    return found[0] if found else None


def detect(path: Path) -> int:
    """A folder with a COLMAP model is a strong match; anything else is not COLMAP (no model is read here)."""
    path = Path(path)
    if not path.is_dir():
        return 0
    return 20 if _candidates(path) else 0


def _records_fit(file: Path) -> "str | None":
    """Walk ``images.bin`` or ``points3D.bin`` by their counts; what is wrong, or None when every record fits.

    pycolmap trusts the counts in a binary model: a truncated or garbled ``points3D.bin`` can make it
    allocate gigabytes and run for minutes before failing. Walking the record sizes first costs a few
    milliseconds per thousand records. Layouts (little-endian): ``images.bin``: count u64, then per image
    id u32, qvec 4 f64, tvec 3 f64, camera id u32, name NUL-terminated, n u64, n x (x, y f64, point id i64);
    ``points3D.bin``: count u64, then per point id u64, xyz 3 f64, rgb 3 u8, error f64, n u64, n x 8 bytes.
    """
    data = file.read_bytes()
    end, pos = len(data), 8
    if end < 8:
        return "file is shorter than its record count"
    fixed, item = (64, 24) if file.stem == "images" else (43, 8)
    for i in range(int.from_bytes(data[:8], "little")):
        if file.stem == "images":
            name_end = data.find(b"\0", pos + 64)
            if name_end < 0:
                return f"image record {i} has no name end (truncated?)"
            pos = name_end + 1
        else:
            pos += fixed
        if pos + 8 > end:
            return f"record {i} runs past the end of the file (truncated?)"
        n = int.from_bytes(data[pos : pos + 8], "little")
        pos += 8 + n * item
        if pos > end:
            return f"record {i} claims {n} entries, past the end of the file (truncated or corrupt)"
    return None


def _check_binary(model_dir: Path) -> None:
    for stem in ("images", "points3D"):
        file = model_dir / f"{stem}.bin"
        problem = _records_fit(file) if file.is_file() else None
        if problem is not None:
            raise NerfpipeError(f"cannot read COLMAP model: {problem}", file)


def _open(model_dir: Path):
    # Load the system zlib before pycolmap's bundled one: with pycolmap first, PNG writing in
    # the same process aborts (free(): invalid pointer in deflateEnd, pycolmap 4.2.1 + Pillow).
    import zlib  # noqa: F401

    pycolmap = require("pycolmap", "colmap")
    _check_binary(model_dir)
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises RuntimeError/ValueError for unreadable models
        raise NerfpipeError(f"cannot read COLMAP model ({type(exc).__name__}: {exc})", model_dir) from exc


def _convert_camera(cam, cameras_file: Path) -> "tuple[tuple, str]":
    model = cam.model.name
    mapped = _param_map(model, [float(v) for v in cam.params])
    if mapped is None:
        raise NerfpipeError(
            f"camera {cam.camera_id} uses COLMAP model {model}, which nerfpipe does not support "
            f"(supported: {', '.join(SUPPORTED_MODELS)}); undistort the images with 'colmap image_undistorter'",
            cameras_file,
        )
    fx, fy, cx, cy, _, dist = mapped
    check_focal(fx, cameras_file, f"camera {cam.camera_id} focal fx")
    check_focal(fy, cameras_file, f"camera {cam.camera_id} focal fy")
    if not np.isfinite([cx, cy, *dist]).all() or cam.width <= 0 or cam.height <= 0:
        raise NerfpipeError(f"camera {cam.camera_id} has a non-finite principal point or distortion, or no pixels", cameras_file)
    return mapped, model


def _image_size(path: Path, cam) -> "tuple[int, int]":
    """The image's ``(width, height)``: its camera's, or the same picture downscaled (``images/`` replaced by
    smaller copies after SfM, as LLFF's and mip-NeRF 360's ``images_N`` folders are): the camera is scaled to it."""
    h, w, _ = image_header(path)
    s = w / cam.width
    if (w, h) != (cam.width, cam.height) and not (1 / 64 <= s < 1 and abs(h - cam.height * s) <= 1):
        raise NerfpipeError(
            f"image is {w}x{h} but its COLMAP camera {cam.camera_id} is {cam.width}x{cam.height} (nor a downscaled copy of that size)", path
        )
    return w, h


def _points(rec, images, cameras: "list[int] | None" = None) -> "Points3D | None":
    """The points, with the track elements whose image is one of ``images`` (by camera, then keypoint); image ``k``
    is camera ``cameras[k]`` of the scene (default ``k``)."""
    if rec.num_points3D() == 0:
        return None
    position = {im.image_id: k for k, im in enumerate(images)}
    pts = [rec.points3D[i] for i in sorted(rec.points3D)]
    obs = [(position[e.image_id], e.point2D_idx, r) for r, p in enumerate(pts) for e in p.track.elements if e.image_id in position]
    image, keypoint, row = np.array(sorted(obs), dtype=np.int64).reshape(-1, 3).T
    keypoints = [np.array([p.xy for p in im.points2D], dtype=np.float64).reshape(-1, 2) for im in images]
    first = np.cumsum([0] + [len(k) for k in keypoints])[:-1]  # row of each image's first keypoint
    cam = image if cameras is None else np.asarray(cameras, dtype=np.int64)[image]
    return Points3D(
        xyz=torch.tensor(np.array([p.xyz for p in pts]), dtype=torch.float64),
        rgb=torch.tensor(np.array([p.color for p in pts]), dtype=torch.uint8),
        error=torch.tensor(np.array([p.error for p in pts]), dtype=torch.float64),
        track_point=torch.from_numpy(row.copy()),
        track_camera=torch.from_numpy(cam.copy()),
        track_xy=torch.from_numpy(np.concatenate(keypoints)[first[image] + keypoint]),
    )


POINTS_MODEL = "points_model"
"""``SceneData.meta`` key: the COLMAP model whose points :func:`with_points` added (a run records it to reload the same scene)."""


def with_points(scene: SceneData, model_dir: Path) -> SceneData:
    """``scene`` with the sparse points of the COLMAP model in ``model_dir`` (in ``scene``'s input frame, its images
    named ``NNNNN.jpg`` by the index of the scene's camera, some or all of them, its cameras possibly downscaled: the
    track pixels are scaled to the scene's images), and the near/far bounds and box that the points give
    (:func:`~nerfpipe.data.normalize.bounds_from_points`), as a COLMAP capture gets them."""
    import dataclasses

    rec = _open(Path(model_dir))
    images = sorted(rec.images.values(), key=lambda im: im.name)
    index = [int(Path(im.name).stem) if Path(im.name).stem.isdigit() else -1 for im in images]
    if not all(0 <= i < len(scene.cameras) for i in index) or len(set(index)) != len(index):
        raise NerfpipeError(f"the points' model names images that are not cameras of the scene ({len(scene.cameras)} cameras)", model_dir)
    points = _points(rec, images, index)
    if points is None:
        return scene
    cams = scene.cameras
    size = torch.ones(len(cams), 2, dtype=torch.float64)
    full = torch.stack([cams.width.double(), cams.height.double()], -1).reshape(-1, 2)
    for i, im in zip(index, images):
        size[i] = torch.tensor([rec.camera(im.camera_id).width, rec.camera(im.camera_id).height], dtype=torch.float64)
    points.track_xy = points.track_xy * (full / size)[points.track_camera]
    points.xyz = scene.world_from_input.apply_points(points.xyz).float()
    near, far, aabb = bounds_from_points(cams, points.xyz)
    meta = scene.meta | {POINTS_MODEL: str(Path(model_dir).resolve())}
    return dataclasses.replace(scene, points=points, near=near, far=far, aabb=aabb, meta=meta)


def _cameras(rec, images, cameras_file: Path, images_file: Path) -> "tuple[Cameras, list[str]]":
    """Cameras in the input frame (float64) and the COLMAP model name per camera."""
    rows, models, w2c = [], [], []
    for im in images:
        cam = rec.camera(im.camera_id)
        mapped, model = _convert_camera(cam, cameras_file)
        rows.append((*mapped, cam.width, cam.height))
        models.append(model)
        cfw = np.eye(4)
        cfw[:3] = im.cam_from_world().matrix()
        if not np.isfinite(cfw).all():
            raise NerfpipeError(f"image '{im.name}' has a non-finite pose", images_file)
        w2c.append(cfw)
    world_from_cam = invert_rigid(torch.tensor(np.stack(w2c), dtype=torch.float64))
    fx, fy, cx, cy, code, params, width, height = zip(*rows)
    cams = Cameras.create(
        world_from_cam, fx, fy, cx, cy, width, height,
        torch.tensor([int(c) for c in code]), torch.tensor(params, dtype=torch.float64), dtype=torch.float64,
    )
    return cams, models


def image_folder(root: Path, names: "list[str]") -> Path:
    """Where the model's image names are relative to: ``root/images``, or ``root`` itself where there is no
    ``images/`` folder and a registered image lies in ``root`` (COLMAP run with the photos' own folder as its
    image path, the model written beside them)."""
    images = root / "images"
    if not images.is_dir() and any((root / name).is_file() for name in names):
        return root
    return images


def _with_files(images: list, folder: Path, images_file: Path) -> "tuple[list, list[Path]]":
    """The registered images whose file exists in ``folder``, and those files. A photograph deleted after the
    reconstruction (a blurred one, say) is left out with one warning, as the transforms adapter and instant-ngp skip a
    frame without its image; none found at all is an error naming the folder."""
    paths = [resolve_inside(folder, im.name, images_file) for im in images]
    found = [p.is_file() for p in paths]
    if not any(found):
        raise NerfpipeError(f"the files of all {len(images)} images registered in the COLMAP model are missing here "
                            f"(first: {images[0].name}); is this the folder the photographs were reconstructed from?", folder)  # fmt: skip
    missing = [p.name for p, f in zip(paths, found) if not f]
    if missing:
        one = len(missing) == 1
        warnings.warn(f"{folder}: {len(missing)} of the {len(images)} images registered in the COLMAP model {'has' if one else 'have'} no "
                      f"file there and {'is' if one else 'are'} left out (first: {', '.join(missing[:3])})", UserWarning, stacklevel=3)  # fmt: skip
    kept = [k for k, f in enumerate(found) if f]
    return [images[k] for k in kept], [paths[k] for k in kept]


def read(path: Path) -> SceneData:
    """Read a COLMAP scene folder; see the module docstring for the layout."""
    root = Path(path)
    model_dir = find_model_dir(root) if root.is_dir() else None
    if model_dir is None:
        raise NerfpipeError(
            "no COLMAP model (cameras/images/points3D .bin or .txt) in sparse/N, sparse or the folder", root
        )
    cameras_file, images_file = _model_file(model_dir, "cameras"), _model_file(model_dir, "images")
    rec = _open(model_dir)
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    if not images:
        raise NerfpipeError("COLMAP model has no registered images", images_file)
    folder = image_folder(root, [im.name for im in images])
    images, paths = _with_files(images, folder, images_file)
    cams, models = _cameras(rec, images, cameras_file, images_file)
    width, height = zip(*(_image_size(p, rec.camera(im.camera_id)) for p, im in zip(paths, images)))
    cams = cams.resized(torch.tensor(width), torch.tensor(height))  # the same cameras unless the images are downscaled copies
    return _assemble(root, rec, images, cams, models, paths)


def _assemble(root, rec, images, cams: Cameras, models, paths) -> SceneData:
    """Normalise cameras and points into nerfpipe's world and build the record."""
    norm = auto_normalization(cams)
    cams.world_from_cam = norm.apply_world_from_cam(cams.world_from_cam)
    points = _points(rec, images)
    model_size = torch.tensor([[rec.camera(im.camera_id).width, rec.camera(im.camera_id).height] for im in images], dtype=torch.float64)
    scale = torch.stack([cams.width, cams.height], -1).double() / model_size  # [n, 2]: 1 unless the images are downscaled copies
    if points is not None:
        points.track_xy = points.track_xy * scale[points.track_camera]
        points.xyz = norm.apply_points(points.xyz).float()
        near, far, aabb = bounds_from_points(cams, points.xyz)
    else:
        from nerfpipe.data.normalize import bounds_from_cameras

        near, far, aabb = bounds_from_cameras(cams)
    rec.update_point_3d_errors()  # recompute with COLMAP's own projection, in case the file's are stale
    meta = {"colmap_mean_reprojection_error": rec.compute_mean_reprojection_error()}
    if bool((scale != 1.0).any()):
        meta[IMAGE_SCALE] = scale[:, 0].tolist()
    return SceneData(
        cameras=cams.to(dtype=torch.float32),
        images=ImageSet(paths=paths),
        splits=holdout_split(len(images)),
        near=near,
        far=far,
        aabb=aabb,
        world_from_input=norm,
        source=root,
        format="colmap",
        points=points,
        camera_models=models,
        meta=meta,
    )


ADAPTER = AdapterSpec(
    name="colmap",
    description="COLMAP sparse model (sparse/N, binary or text) with an images/ folder",
    detect=detect,
    read=read,
)
