"""Small synthetic COLMAP scenes for tests, made with ``pycolmap.synthesize_dataset``."""

import zlib  # noqa: F401  (system zlib before pycolmap's, see nerfpipe.data_adapters.colmap._open)
from pathlib import Path

import imageio.v3 as iio
import numpy as np

WIDTH, HEIGHT = 64, 48

# COLMAP model -> parameters for a 64x48 camera (fx/f, [fy], cx, cy, extra).
PARAMS = {
    "SIMPLE_PINHOLE": [60.0, 32.0, 24.0],
    "PINHOLE": [60.0, 58.0, 32.0, 24.0],
    "SIMPLE_RADIAL": [60.0, 32.0, 24.0, -0.05],
    "RADIAL": [60.0, 32.0, 24.0, -0.05, 0.01],
    "OPENCV": [60.0, 58.0, 32.0, 24.0, -0.1, 0.02, 0.003, -0.002],
    "OPENCV_FISHEYE": [60.0, 58.0, 32.0, 24.0, 0.05, -0.01, 0.002, -0.001],
    "FULL_OPENCV": [60.0, 58.0, 32.0, 24.0, -0.1, 0.02, 0.003, -0.002, 0.0, 0.0, 0.0, 0.0],
}


def synthesize(model: str = "PINHOLE", frames: int = 10, points: int = 200, seed: int = 0):
    """An in-memory reconstruction with one camera of ``model`` and ``frames`` registered images."""
    import pycolmap

    pycolmap.set_random_seed(seed)
    opt = pycolmap.SyntheticDatasetOptions()
    opt.num_rigs, opt.num_cameras_per_rig, opt.num_frames_per_rig = 1, 1, frames
    opt.num_points3D = points
    opt.camera_width, opt.camera_height = WIDTH, HEIGHT
    opt.camera_model_id = getattr(pycolmap.CameraModelId, model)
    opt.camera_params = PARAMS[model]
    return pycolmap.synthesize_dataset(opt)


def write_scene(rec, root: Path, text: bool = False, model_dir: str = "sparse/0") -> Path:
    """Write ``rec`` under ``root/model_dir`` plus a black image per registered image."""
    root = Path(root)
    out = root / model_dir
    out.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(out))
    (root / "images").mkdir(exist_ok=True)
    for i in rec.reg_image_ids():
        im = rec.image(i)
        cam = rec.camera(im.camera_id)
        iio.imwrite(root / "images" / im.name, np.zeros((cam.height, cam.width, 3), np.uint8))
    return root


def make_scene(root: Path, model: str = "PINHOLE", text: bool = False, **kw) -> Path:
    return write_scene(synthesize(model, **kw), root, text=text)
