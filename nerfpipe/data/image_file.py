"""Image files and image arrays in, as uint8 ``[H, W, 3|4]``: one reader, one check, one-line errors.

Every image nerfpipe takes in passes through here: dataset images (:class:`~nerfpipe.data.scene.ImageSet`),
image headers for the size checks of the adapters, photos for SfM, ``fit2d``'s target, and
in-memory arrays (npz scenes, images handed to the load stage). A file that is empty, text,
truncated or otherwise undecodable, and an array of the wrong shape, dtype or range (float
values outside [0, 1], NaN), is one :class:`~nerfpipe.util.errors.NerfpipeError` naming the file or
array, never a decoder's traceback or its list of plugins.

Files are decoded with Pillow directly (imageio's v3 reader probes every plugin on a bad file,
prints their list and leaks file handles). Decoder warnings are silenced: a user reads the
error, not the decoder's notes.

Glossary:
    header   size and channel count, read without decoding the pixels
    C        channels: 3 (RGB) or 4 (RGBA); grey is expanded, grey+alpha becomes RGBA
"""

import contextlib
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from nerfpipe.util.errors import NerfpipeError, require

HEIF_SUFFIXES = (".heic", ".heif")
"""Photographs in HEIF (HEVC-coded: an iPhone's default), read with pillow-heif (the ``colmap`` extra, with the SfM that
photographs go through), its rotation applied as the file says."""

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", *HEIF_SUFFIXES)
"""The photographs a folder of photos (the ``sfm`` stage's input) is made of."""

OTHER_PHOTO_SUFFIXES = (".avif", ".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".tif", ".tiff", ".webp")
"""Photographs nerfpipe does not read (a camera's raw files, TIFF, WebP): a folder of them is named as such
(:func:`unread_photos`), not as an unknown dataset."""


def photo_folder(path: "str | Path | None") -> "Path | None":
    """``path/images`` or ``path`` when it holds photographs of :data:`PHOTO_SUFFIXES`, else None."""
    if path is None or not Path(path).is_dir():
        return None
    for folder in (Path(path) / "images", Path(path)):
        if folder.is_dir() and any(p.suffix.lower() in PHOTO_SUFFIXES for p in folder.iterdir()):
            return folder
    return None


def unread_photos(path: "str | Path") -> "list[Path]":
    """The photographs of :data:`OTHER_PHOTO_SUFFIXES` in ``path`` (or ``path/images``) where it holds none of
    :data:`PHOTO_SUFFIXES`; empty otherwise."""
    for folder in (Path(path) / "images", Path(path)):
        if folder.is_dir():
            files = [p for p in folder.iterdir() if p.is_file()]
            if any(p.suffix.lower() in PHOTO_SUFFIXES for p in files):
                return []
            other = sorted(p for p in files if p.suffix.lower() in OTHER_PHOTO_SUFFIXES)
            if other:
                return other
    return []


FLOAT_SLACK = 1e-3
"""Float images may stray this far outside [0, 1] (rounding in the writer) and are clipped."""
_AS_RGB = {"CMYK", "YCbCr", "LAB", "HSV", "1"}
"""Pillow modes converted to RGB before use (no alpha, not grey)."""


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [""])[0]


@contextlib.contextmanager
def open_image(path: "str | Path", decode: bool = True, draft: "tuple[int, int] | None" = None) -> Iterator["object"]:
    """A Pillow image of ``path``, its pixels decoded (``decode``) or only its header read.

    ``draft`` (width, height): let a JPEG decode at a reduced scale no smaller than this (much
    faster for photos that are downscaled anyway).

    Raises:
        NerfpipeError: missing, empty, not an image, truncated or corrupt.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise NerfpipeError("is a folder, not an image file" if path.is_dir() else "image file is missing", path)
    if path.stat().st_size == 0:
        raise NerfpipeError("image file is empty", path)
    if path.suffix.lower() in HEIF_SUFFIXES:
        yield _open_heif(path, decode)
        return
    with contextlib.ExitStack() as stack:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                im = stack.enter_context(Image.open(path))
                if draft is not None:
                    im.draft("RGB", draft)
                if decode:
                    im.load()
        except UnidentifiedImageError as exc:
            raise NerfpipeError("not an image file (no PNG, JPEG or other image format recognised)", path) from exc
        except Exception as exc:  # Pillow raises OSError, SyntaxError, ValueError... for broken files
            raise NerfpipeError(f"cannot decode image, truncated or corrupt ({type(exc).__name__}: {_first_line(exc)})", path) from exc
        yield im


class _HeifHeader:
    """What :func:`image_header` reads of a HEIF file without decoding it: its size (rotation applied) and mode."""

    def __init__(self, heif) -> None:
        self.size, self.mode, self.info = tuple(heif.size), heif.mode, {}

    def getbands(self) -> "tuple[str, ...]":
        return tuple(self.mode)


def _open_heif(path: Path, decode: bool):
    """A HEIF photo (:data:`HEIF_SUFFIXES`) as a Pillow image (its EXIF kept, the rotation applied by libheif and the
    EXIF orientation reset to upright), or only its header; one error line naming it where it cannot be decoded."""
    pillow_heif = require("pillow_heif", "colmap")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            heif = pillow_heif.open_heif(path, convert_hdr_to_8bit=True)
            return heif.to_pillow() if decode else _HeifHeader(heif)
    except Exception as exc:  # libheif's errors for a file that is not HEIF or is broken
        raise NerfpipeError(f"cannot decode HEIF image, truncated or corrupt ({type(exc).__name__}: {_first_line(exc)})", path) from exc


def image_header(path: "str | Path") -> "tuple[int, int, int]":
    """``(H, W, C)`` of an image file from its header (C as :func:`read_image_uint8` returns it)."""
    with open_image(path, decode=False) as im:
        w, h = im.size
        alpha = "A" in im.getbands() or (im.mode == "P" and "transparency" in im.info)
    if w <= 0 or h <= 0:
        raise NerfpipeError(f"image has no pixels ({w}x{h})", path)
    return h, w, 4 if alpha else 3


def read_image_uint8(path: "str | Path") -> np.ndarray:
    """Decode an image file as uint8 ``[H, W, 3|4]``: 16-bit is scaled, grey expanded, float checked."""
    with open_image(path) as im:
        if im.mode == "P":
            im = im.convert("RGBA" if "transparency" in im.info else "RGB")
        elif im.mode in _AS_RGB:
            im = im.convert("RGB")
        elif im.mode == "PA":
            im = im.convert("RGBA")
        img = np.array(im)  # writable (np.asarray of a Pillow image is read-only; torch.from_numpy warns on it)
    if im.mode == "I" and img.size and 0 <= img.min() and img.max() <= 65535:  # 16-bit grey that Pillow widened
        img = img.astype(np.uint16)
    return image_uint8(img, path)


def image_uint8(img: np.ndarray, source: "str | Path", what: str = "image") -> np.ndarray:
    """One image array ``[H, W]`` or ``[H, W, 1|2|3|4]`` as uint8 ``[H, W, 3|4]``.

    uint8 is kept, uint16 scaled by 1/257, floats must be finite and in [0, 1]; any other
    dtype or shape is refused, naming ``source`` (the file, or the array's container).
    """
    img = np.asarray(img)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 2, 3, 4) or min(img.shape[:2]) == 0:
        raise NerfpipeError(f"{what} must have shape [H, W] or [H, W, 1-4] with pixels, not {list(img.shape)}", source)
    img = _values_uint8(img, source, what)
    if img.shape[-1] <= 2:  # grey, grey + alpha
        img = np.concatenate([np.repeat(img[..., :1], 3, axis=-1), img[..., 1:]], axis=-1)
    return img


def images_uint8(images: np.ndarray, source: "str | Path", what: str = "images") -> np.ndarray:
    """A stack ``[N, H, W, 3|4]`` of images as uint8, with the dtype and range rules of :func:`image_uint8`."""
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] not in (3, 4) or min(images.shape[:3]) == 0:
        raise NerfpipeError(f"{what} must have shape [N, H, W, 3|4], not {list(images.shape)}", source)
    return _values_uint8(images, source, what)


def _values_uint8(img: np.ndarray, source: "str | Path", what: str) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    if img.dtype == np.bool_:
        return img.astype(np.uint8) * 255
    if not np.issubdtype(img.dtype, np.floating):
        raise NerfpipeError(f"{what} has dtype {img.dtype}; nerfpipe reads uint8, uint16 or float in [0, 1]", source)
    if not np.isfinite(img).all():
        raise NerfpipeError(f"{what} contains NaN or Inf values", source)
    lo, hi = float(img.min()), float(img.max())
    if lo < -FLOAT_SLACK or hi > 1 + FLOAT_SLACK:
        raise NerfpipeError(f"{what} has float values outside [0, 1] (from {lo:.4g} to {hi:.4g})", source)
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
