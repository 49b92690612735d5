"""The target image of a 2D fit: read, checked, made RGB and kept to a workable size."""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfpipe.data.image_file import read_image_uint8
from nerfpipe.util.errors import NerfpipeError

DEFAULT_IMAGE = "skimage:astronaut"
"""Used when no image is given: a photograph shipped inside scikit-image (no download)."""


@dataclass
class TargetImage:
    """An RGB uint8 image ``[H, W, 3]`` plus what was done to it on the way in."""

    pixels: np.ndarray
    source: str
    notes: "list[str]" = field(default_factory=list)
    """Warnings for the user (alpha dropped, image downscaled, ...)."""


def load_target(path: "str | Path | None", max_pixels: int = 2048 * 2048) -> TargetImage:
    """Read ``path`` (or the default skimage photograph) as RGB uint8, downscaling huge images.

    Raises:
        NerfpipeError: unreadable or non-image file, or an image smaller than 2×2.
    """
    if path is None:
        img, source = _skimage_photo(DEFAULT_IMAGE.split(":", 1)[1]), DEFAULT_IMAGE
    else:
        img, source = read_image_uint8(Path(path)), str(path)
    notes: "list[str]" = []
    if img.shape[0] < 2 or img.shape[1] < 2:
        raise NerfpipeError(f"image is {img.shape[1]}×{img.shape[0]} pixels; fitting needs at least 2×2", path)
    if img.shape[-1] == 4:
        img = _over_white(img)
        notes.append("the alpha channel was composited over white")
    if img.shape[0] * img.shape[1] > max_pixels:
        h, w = img.shape[:2]
        img = _downscale(img, max_pixels)
        notes.append(f"downscaled {w}×{h} to {img.shape[1]}×{img.shape[0]} (limit --max-pixels {max_pixels})")
    return TargetImage(np.require(img, np.uint8, ["C_CONTIGUOUS", "WRITEABLE"]), source, notes)


def _skimage_photo(name: str) -> np.ndarray:
    from nerfpipe.util.errors import require

    data = require("skimage.data", "plot")
    return np.asarray(getattr(data, name)())[..., :3].astype(np.uint8)


def _over_white(img: np.ndarray) -> np.ndarray:
    alpha = img[..., 3:].astype(np.float32) / 255.0
    rgb = img[..., :3].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)
    return (rgb + 0.5).astype(np.uint8)


def _downscale(img: np.ndarray, max_pixels: int) -> np.ndarray:
    from PIL import Image

    h, w = img.shape[:2]
    scale = (max_pixels / (h * w)) ** 0.5
    size = (max(2, int(w * scale)), max(2, int(h * scale)))
    return np.asarray(Image.fromarray(img).resize(size, Image.Resampling.BOX))
