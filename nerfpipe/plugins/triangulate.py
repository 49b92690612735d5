"""Sparse points for posed photographs that come without them: pycolmap triangulation with the known poses.

instant-ngp and nerfstudio ``transforms.json`` captures (and COLMAP models saved without their points)
give poses but no sparse points. On a real capture the points are what the fast model's real-capture
machinery stands on: the object region (the box) from their robust extent, the field behind the box for
everything beyond it, the depth loss along their tracks, and the mesh stage's region and support plane.
Without them instant-ngp's own fox capture trained a fog box. This module extracts SIFT features from
downscaled copies of the photographs, matches each photograph with its nearest cameras (by viewing
direction and position: the poses are known, so no exhaustive matching), and triangulates with
``pycolmap.triangulate_points``, the poses and intrinsics held fixed. The result is a COLMAP model in
the input's frame, one image per camera named by its index (:func:`image_name`).
"""

import time
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.scene import SceneData
from nerfpipe.util.errors import NerfpipeError, require


def image_name(index: int) -> str:
    """The name of camera ``index``'s photograph in the triangulation (the scene's camera order)."""
    return f"{index:05d}.jpg"


def wants_points(scene: SceneData, flat_border: float = 0.5) -> bool:
    """Whether ``scene`` is a real capture that lacks sparse points: photographs on disk without alpha, no
    points, and borders that are not one flat colour (a synthetic render on black or white has flat
    borders over more than ``flat_border`` of their pixels; a photograph's floor and walls do not)."""
    if scene.points is not None or scene.has_alpha or scene.images.paths is None or len(scene.cameras) < 3:
        return False
    shown = [i for i in range(len(scene.cameras)) if scene.images.has(i)]
    if len(shown) < 3:
        return False
    picks = [shown[int(k)] for k in np.linspace(0, len(shown) - 1, 3).round()]
    return all(flat_border_fraction(scene.images.load(i)) <= flat_border for i in picks)


def flat_border_fraction(image: np.ndarray, band: float = 0.03, tolerance: int = 4) -> float:
    """Fraction of the pixels in the outer ``band`` of ``image`` (``[H, W, C]`` uint8) within ``tolerance``
    levels of their median colour in every channel."""
    h, w = image.shape[:2]
    b = max(1, int(round(band * min(h, w))))
    ring = np.concatenate([image[:b].reshape(-1, image.shape[2]), image[-b:].reshape(-1, image.shape[2]),
                           image[:, :b].reshape(-1, image.shape[2]), image[:, -b:].reshape(-1, image.shape[2])])[:, :3].astype(np.int16)  # fmt: skip
    median = np.median(ring, axis=0)
    return float((np.abs(ring - median) <= tolerance).all(axis=1).mean())


def chosen_photos(count: int, max_photos: int) -> "list[int]":
    """The cameras whose photographs are triangulated: all, or ``max_photos`` spread evenly over the scene's order
    (a video's frames: every k-th) when there are more (0: all)."""
    if max_photos <= 0 or count <= max_photos:
        return list(range(count))
    return sorted({int(round(k)) for k in np.linspace(0, count - 1, max_photos)})


def neighbour_pairs(scene: SceneData, neighbours: int, chosen: "list[int] | None" = None) -> "list[tuple[int, int]]":
    """Pairs of cameras to match (among ``chosen``, default all): each camera with its ``neighbours`` nearest by
    viewing direction and position (each distance over its median, summed), once per pair."""
    chosen = list(range(len(scene.cameras))) if chosen is None else chosen
    c2w = scene.cameras.world_from_cam.double().reshape(-1, 4, 4)[torch.tensor(chosen, dtype=torch.long)]
    centres, axes = c2w[:, :3, 3], c2w[:, :3, 2]
    angle = torch.arccos((axes @ axes.T).clamp(-1, 1))
    dist = torch.cdist(centres, centres)
    score = angle / angle.median().clamp(min=1e-9) + dist / dist.median().clamp(min=1e-9)
    score.fill_diagonal_(float("inf"))
    k = min(neighbours, len(c2w) - 1)
    return sorted({tuple(sorted((chosen[i], chosen[int(j)]))) for i in range(len(c2w)) for j in score[i].argsort()[:k]})


def downscale(scene: SceneData, out: Path, max_size: int, chosen: "list[int]") -> "dict[int, tuple[int, int]]":
    """Write camera ``i``'s photograph as ``out/image_name(i)`` for each ``i`` of ``chosen``, longest side at most
    ``max_size``; return the written sizes by camera."""
    from PIL import Image

    from nerfpipe.outputs.render import capped_size

    out.mkdir(parents=True, exist_ok=True)
    sizes = {}
    for i in chosen:
        pixels = scene.images.load(i)[..., :3]
        size = capped_size(pixels.shape[1], pixels.shape[0], 1.0, max_size if max_size > 0 else None)
        Image.fromarray(pixels).resize(size, Image.LANCZOS).save(out / image_name(i), quality=95)
        sizes[i] = size
    return sizes


def _camera(pycolmap, scene: SceneData, i: int, camera_id: int, size: "tuple[int, int]"):
    """Camera ``i``'s intrinsics scaled to ``size``, as a COLMAP OPENCV (or OPENCV_FISHEYE) camera."""
    from nerfpipe.functional.distortion import Distortion

    cams = scene.cameras
    sx, sy = size[0] / float(cams.width[i]), size[1] / float(cams.height[i])
    fisheye = int(cams.distortion[i]) == int(Distortion.FISHEYE)
    cam = pycolmap.Camera.create_from_model_name(camera_id, "OPENCV_FISHEYE" if fisheye else "OPENCV", 1.0, size[0], size[1])
    dist = [float(v) for v in cams.dist_params[i].tolist()]
    cam.params = [float(cams.fx[i]) * sx, float(cams.fy[i]) * sy, float(cams.cx[i]) * sx, float(cams.cy[i]) * sy, *dist]
    return cam


def triangulate(scene: SceneData, work: Path, max_size: int, max_features: int, neighbours: int, threads: int, max_photos: int = 0, on_step=None):
    """Triangulate sparse points for ``scene`` with its poses and intrinsics fixed, from the photographs of
    :func:`chosen_photos`; return (a ``pycolmap.Reconstruction`` in the input frame, seconds per step). Scratch files
    go to ``work``."""
    pycolmap = require("pycolmap", "colmap")
    step = on_step or (lambda name: None)
    seconds, t = {}, time.monotonic()
    images, db = work / "images", work / "database.db"
    db.unlink(missing_ok=True)
    chosen = chosen_photos(len(scene.cameras), max_photos)
    sizes = downscale(scene, images, max_size, chosen)
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads, ext.sift.max_num_features = threads, max_features
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.PER_IMAGE, extraction_options=ext, device=pycolmap.Device.cpu)
    seconds["features"], t = time.monotonic() - t, time.monotonic()
    step("features")
    pairs = neighbour_pairs(scene, neighbours, chosen)
    (work / "pairs.txt").write_text("".join(f"{image_name(a)} {image_name(b)}\n" for a, b in pairs))
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = threads
    pycolmap.match_image_pairs(db, matching_options=match, pairing_options=pycolmap.ImportedPairingOptions(match_list_path=work / "pairs.txt"),
                               device=pycolmap.Device.cpu)  # fmt: skip
    seconds["matching"], t = time.monotonic() - t, time.monotonic()
    step("matching")
    cam_from_input = torch.linalg.inv(scene.world_from_input.inverse().apply_world_from_cam(scene.cameras.world_from_cam.double())).numpy()
    rec = pycolmap.Reconstruction()
    database = pycolmap.Database.open(db)
    try:
        for image in database.read_all_images():
            i = int(Path(image.name).stem)
            cam = _camera(pycolmap, scene, i, image.camera_id, sizes[i])
            database.update_camera(cam)  # the database's camera is COLMAP's guess; the triangulation uses ours
            rec.add_camera_with_trivial_rig(cam)
            keypoints = database.read_keypoints(image.image_id)[:, :2].astype(np.float64)
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_input[i, :3, :3]), cam_from_input[i, :3, 3])
            rec.add_image_with_trivial_frame(pycolmap.Image(name=image.name, keypoints=keypoints, camera_id=image.camera_id, image_id=image.image_id), pose)
    finally:
        database.close()
    (work / "triangulated").mkdir(exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    rec = pycolmap.triangulate_points(rec, db, images, work / "triangulated", options=options)
    seconds["triangulation"] = time.monotonic() - t
    if rec.num_points3D() == 0:
        raise NerfpipeError("triangulation with the known poses found no points (do the photographs overlap?)", scene.source)
    return rec, seconds
