"""Stage ``export``: the cameras for the ecosystem, in the input frame.

* ``export/transforms.json`` in nerfstudio's format: ``transform_matrix`` is the OpenGL
  camera-to-world matrix (camera +y up, looking along -z) in the input's own frame (nerfpipe's
  normalisation undone), with per-frame intrinsics ``fl_x fl_y cx cy w h``, ``camera_model`` and
  distortion (``k1 k2 p1 p2`` for OPENCV, ``k1..k4`` for OPENCV_FISHEYE). ``cx cy`` keep the
  COLMAP/nerfstudio convention (top-left pixel centre at 0.5). ``file_path`` points into
  ``export/images/``: hard links to the input images where the file system allows (copies with
  ``copy_images``, or across file systems; not symlinks, which readers refuse as paths out of the
  dataset); in-memory
  images (npz) are written as PNG. Cameras without an image (test poses) are left out here.
* ``export/trajectory.json``: every camera as an Open3D ``PinholeCameraTrajectory``
  (``open3d.io.read_pinhole_camera_trajectory``). Open3D's extrinsic is world-to-camera with
  the same camera axes as nerfpipe; its principal point counts from the top-left pixel centre,
  so ``cx_open3d = cx - 0.5``. Open3D's pinhole intrinsic has no distortion: distorted cameras
  are written with their pinhole part only.
"""

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.scene import SceneData
from nerfpipe.functional.distortion import Distortion
from nerfpipe.pipeline.stages import StageContext, StageSpec, atomic_path
from nerfpipe.util.errors import NerfpipeError, require

EXPORT_DIR = "export"
TRANSFORMS = f"{EXPORT_DIR}/transforms.json"
TRAJECTORY = f"{EXPORT_DIR}/trajectory.json"
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class ExportConfig:
    """Options of the ``export`` stage."""

    copy_images: bool = False
    """Always copy the input images into ``export/images`` (portable) instead of hard-linking them where possible."""


def input_frame_cameras(scene: SceneData) -> Cameras:
    """The scene's cameras mapped back to the input frame (float64)."""
    cams = scene.cameras.to(dtype=torch.float64)
    cams.world_from_cam = scene.world_from_input.inverse().apply_world_from_cam(cams.world_from_cam)
    return cams


def _camera_model(cams: Cameras) -> str:
    codes = set(cams.distortion.tolist())
    if codes <= {int(Distortion.NONE)}:
        return "PINHOLE"
    if int(Distortion.FISHEYE) in codes:
        if int(Distortion.OPENCV) in codes:
            raise NerfpipeError("cannot export a mix of fisheye and OPENCV cameras in one nerfstudio file")
        return "OPENCV_FISHEYE"
    return "OPENCV"


def _frame(cams: Cameras, i: int, file_path: str, model: str) -> dict:
    c = cams[i]
    p = [float(v) for v in c.dist_params]
    frame = {
        "file_path": file_path,
        "transform_matrix": (c.world_from_cam.numpy() @ _GL_FROM_CV).tolist(),
        "fl_x": float(c.fx), "fl_y": float(c.fy), "cx": float(c.cx), "cy": float(c.cy),
        "w": int(c.width), "h": int(c.height), "camera_model": model,
    }  # fmt: skip
    if model == "OPENCV":
        frame.update(k1=p[0], k2=p[1], p1=p[2], p2=p[3])
    elif model == "OPENCV_FISHEYE":
        frame.update(k1=p[0], k2=p[1], k3=p[2], k4=p[3])
    return frame


def _place_image(scene: SceneData, i: int, folder: Path, copy: bool) -> str:
    """Put image ``i`` into ``folder``; return its name (indexed, so file order is camera order)."""
    if scene.images.paths is None:
        import imageio.v3 as iio

        name = f"{i:05d}.png"
        iio.imwrite(folder / name, scene.images.load(i))
        return name
    src = Path(scene.images.paths[i]).resolve()
    name = f"{i:05d}_{src.name}"
    if not copy:
        try:
            os.link(src, folder / name)  # a hard link is a file of the export (readers refuse symlinks out of a dataset)
            return name
        except OSError:  # another file system, or links not allowed: copy
            pass
    shutil.copy2(src, folder / name)
    return name


def nerfstudio_transforms(scene: SceneData, folder: Path, copy_images: bool = False) -> dict:
    """Write the images into ``folder/images`` and return the transforms.json document."""
    cams = input_frame_cameras(scene)
    model = _camera_model(cams)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames, split_names = [], {s: [] for s in scene.splits}
    split_of = {int(i): s for s, idx in scene.splits.items() for i in idx}
    for i in range(len(cams)):
        if not scene.images.has(i):
            continue
        path = "images/" + _place_image(scene, i, folder / "images", copy_images)
        frames.append(_frame(cams, i, path, model))
        if i in split_of:
            split_names[split_of[i]].append(path)
    doc = {"camera_model": model, "frames": frames}
    doc.update({f"{s}_filenames": names for s, names in split_names.items() if names})
    return doc


def open3d_trajectory(cams: Cameras):
    """An ``open3d.camera.PinholeCameraTrajectory`` of the cameras (see the module docstring)."""
    o3d = require("open3d", "mesh")
    traj = o3d.camera.PinholeCameraTrajectory()
    params = []
    cam_from_world = cams.cam_from_world.numpy()
    for i in range(len(cams)):
        c = cams[i]
        p = o3d.camera.PinholeCameraParameters()
        p.intrinsic = o3d.camera.PinholeCameraIntrinsic(
            int(c.width), int(c.height), float(c.fx), float(c.fy), float(c.cx) - 0.5, float(c.cy) - 0.5
        )
        p.extrinsic = cam_from_world[i]
        params.append(p)
    traj.parameters = params
    return traj


def run(config: ExportConfig, ctx: StageContext) -> "dict[str, object]":
    o3d = require("open3d", "mesh")
    scene = ctx.get("scene")
    with atomic_path(ctx.path(EXPORT_DIR)) as tmp:
        doc = nerfstudio_transforms(scene, tmp, config.copy_images)
        (tmp / "transforms.json").write_text(json.dumps(doc, indent=2) + "\n")
        traj = open3d_trajectory(input_frame_cameras(scene))
        if not o3d.io.write_pinhole_camera_trajectory(str(tmp / "trajectory.json"), traj):
            raise NerfpipeError("Open3D could not write the camera trajectory", tmp / "trajectory.json")
    ctx.log.info("exported %d frames (nerfstudio) and %d cameras (Open3D)", len(doc["frames"]), len(traj.parameters))
    return {TRANSFORMS: ctx.path(TRANSFORMS), TRAJECTORY: ctx.path(TRAJECTORY)}


STAGE = StageSpec(
    name="export",
    description="cameras for the ecosystem: nerfstudio transforms.json and an Open3D camera trajectory",
    config=ExportConfig,
    run=run,
    light=True,
    requires=("scene",),
    produces=(TRANSFORMS, TRAJECTORY),
    dependencies=(("open3d", "mesh"),),
)
