"""Per-photo exposure measured on the sparse points' tracks: how much brighter or darker each photograph shows the same
surfaces than the others (auto-exposure on a phone, a window or a lamp coming into view).

Every track observation gives the brightness (linear-light luminance, a small patch's mean) of one 3D point in one
photo. With ``log value = a_point + g_photo`` for all of them, each photo's log gain ``g`` is what its observations share,
found by alternating weighted means with a robust (Cauchy) weight, since specular highlights and wrong matches do not
follow it. A spread of these gains across the photos means that the captures differ in exposure, which a field without
per-image colour corrections explains with fog (:data:`nerfpipe.models.fast.APPEARANCE_EXPOSURE_SPREAD`).
"""

from __future__ import annotations

import numpy as np
import torch
from nerfpipe.data.scene import ImageSet, Points3D
from nerfpipe.util.typing import Float, Tensor

EXPOSURE_PATCH = 2
"""Half-size of the square patch averaged at each observation (5 x 5 pixels): a keypoint sits on an edge or a corner,
where one pixel's value depends on sub-pixel placement."""
SATURATED = 0.98
"""An observation whose patch holds a channel above this (0..1, as stored) is clipped and says nothing of the gain."""
DARK = 0.03
"""Nor does one whose patch's mean luminance is below this (as stored, sRGB): noise and compression dominate."""
CAUCHY_SCALE = 0.1
"""Residual (log units) at which an observation's weight halves in the robust fit."""
ITERATIONS = 20
LUMA = np.array([0.2126, 0.7152, 0.0722])
"""Rec. 709 luminance weights of linear RGB."""


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve inverted (values 0..1)."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def track_log_luminance(points: Points3D, images: ImageSet, cameras: "np.ndarray | None" = None) -> Float[Tensor, "num_obs"]:
    """The log linear luminance of every track observation (float64): its photo's mean over a (2 :data:`EXPOSURE_PATCH` + 1)²
    patch around the keypoint; NaN where the photo is not among ``cameras`` (default: all that have an image), or the patch is
    clipped (:data:`SATURATED`) or dark (:data:`DARK`)."""
    if not points.has_tracks:
        raise ValueError("exposure needs the points' tracks")
    cam = points.track_camera.cpu().numpy()
    xy = points.track_xy.double().cpu().numpy()
    out = np.full(len(cam), np.nan)
    wanted = np.unique(cam) if cameras is None else np.intersect1d(np.unique(cam), np.asarray(cameras))
    half, dark = EXPOSURE_PATCH, float(srgb_to_linear(np.array(DARK)))
    for c in wanted:
        if not images.has(int(c)):
            continue
        img = images.load(int(c))[..., :3].astype(np.float32) / 255.0
        h, w = img.shape[:2]
        rows = np.nonzero(cam == c)[0]
        x = np.clip(np.floor(xy[rows, 0]).astype(np.int64), half, w - 1 - half)
        y = np.clip(np.floor(xy[rows, 1]).astype(np.int64), half, h - 1 - half)
        total, clipped = np.zeros((len(rows), 3)), np.zeros(len(rows), dtype=bool)
        for dy in range(-half, half + 1):
            for dx in range(-half, half + 1):
                v = img[y + dy, x + dx]
                clipped |= v.max(1) > SATURATED
                total += srgb_to_linear(v)
        lum = (total / (2 * half + 1) ** 2) @ LUMA
        ok = ~clipped & (lum >= dark)
        out[rows[ok]] = np.log(lum[ok])
    return torch.from_numpy(out)


def exposure_gains(points: Points3D, images: ImageSet, num_cameras: int, cameras: "np.ndarray | None" = None) -> Float[Tensor, "num_cameras"]:
    """Each photo's log exposure gain relative to the median photo (float64; 0.69: twice as bright), fitted robustly to
    :func:`track_log_luminance` over the points seen at least twice among ``cameras`` (default: all). NaN for photos
    without such observations.

    Example:
        A photo twice as bright as the others has a gain of log 2 (see ``tests/test_exposure.py``).
    """
    v = track_log_luminance(points, images, cameras).numpy()
    pt, cam = points.track_point.cpu().numpy(), points.track_camera.cpu().numpy()
    ok = np.isfinite(v)
    ok &= np.bincount(pt[ok], minlength=len(points.xyz))[pt] >= 2
    v, pt, cam = v[ok], pt[ok], cam[ok]
    npt = len(points.xyz)
    seen = np.bincount(cam, minlength=num_cameras) > 0
    g, w = np.zeros(num_cameras), np.ones(len(v))
    for _ in range(ITERATIONS):
        a = np.bincount(pt, w * (v - g[cam]), npt) / np.maximum(np.bincount(pt, w, npt), 1e-12)
        g = np.bincount(cam, w * (v - a[pt]), num_cameras) / np.maximum(np.bincount(cam, w, num_cameras), 1e-12)
        if seen.any():
            g[seen] -= np.median(g[seen])
        w = 1.0 / (1.0 + ((v - a[pt] - g[cam]) / CAUCHY_SCALE) ** 2)
    g[~seen] = np.nan
    return torch.from_numpy(g)


def exposure_spread(gains: Float[Tensor, "num_cameras"]) -> float:
    """The standard deviation of the finite log gains (0 with fewer than two)."""
    g = gains[torch.isfinite(gains)]
    return float(g.std(correction=0)) if len(g) > 1 else 0.0
