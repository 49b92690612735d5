"""Helpers shared by the adapters: checking poses and focal lengths read from files, and the
bounds rule for synthetic (Blender/NeRF) scenes.

Glossary:
    world_from_cam  camera-to-world rigid transform ``[N, 4, 4]`` (any camera axes)
    what            the name of the field being checked, as the user wrote it (``c2ws_train``)
"""

from pathlib import Path

import numpy as np

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.normalize import bounds_from_cameras
from nerfpipe.util.errors import NerfpipeError

ROTATION_TOL = 1e-3
"""Largest accepted ``|det R - 1|`` and ``max |RᵀR - I|`` (files store ~7 significant digits)."""

SYNTHETIC_NEAR_FAR = (2.0, 6.0)
"""Near/far of the NeRF synthetic scenes (cameras on a sphere of radius ~4 around the object)."""


def check_world_from_cam(m, path: "str | Path", what: str = "poses") -> np.ndarray:
    """Validate camera-to-world matrices ``[N, 4, 4]`` or ``[N, 3, 4]``; return float64 ``[N, 4, 4]``.

    Raises:
        NerfpipeError: wrong shape, NaN/Inf values, a last row other than ``[0 0 0 1]``,
            or a rotation block that is not a proper rotation (reflection, scale, shear).
    """
    try:
        m = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise NerfpipeError(f"{what} are not numeric 4x4 matrices ({exc})", path) from exc
    if m.ndim != 3 or m.shape[1:] not in ((3, 4), (4, 4)):
        raise NerfpipeError(f"{what} must have shape [N, 4, 4] or [N, 3, 4], not {list(m.shape)}", path)
    bad = np.flatnonzero(~np.isfinite(m).all(axis=(1, 2)))
    if len(bad):
        raise NerfpipeError(f"{what}[{bad[0]}] contains NaN or Inf ({len(bad)} matrices affected)", path)
    if m.shape[1] == 4:
        bad = np.flatnonzero(np.abs(m[:, 3] - [0, 0, 0, 1]).max(axis=1) > ROTATION_TOL)
        if len(bad):
            raise NerfpipeError(f"{what}[{bad[0]}] has last row {m[bad[0], 3].tolist()}, expected [0, 0, 0, 1]", path)
    out = np.tile(np.eye(4), (len(m), 1, 1))
    out[:, :3] = m[:, :3]
    _check_rotations(out[:, :3, :3], path, what)
    return out


def _check_rotations(rot: np.ndarray, path: "str | Path", what: str) -> None:
    det = np.linalg.det(rot)
    ortho = np.abs(rot.transpose(0, 2, 1) @ rot - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((np.abs(det - 1) > ROTATION_TOL) | (ortho > ROTATION_TOL))
    if len(bad):
        i = bad[0]
        raise NerfpipeError(
            f"{what}[{i}] is not a rotation plus translation (det {det[i]:.4g}, max |RᵀR - I| {ortho[i]:.2g}); "
            f"{len(bad)} matrices affected",
            path,
        )


def check_focal(value, path: "str | Path", what: str = "focal") -> float:
    """A finite, positive focal length in pixels, or a :class:`NerfpipeError`."""
    arr = np.asarray(value)
    if arr.size != 1 or not np.issubdtype(arr.dtype, np.number):
        raise NerfpipeError(f"{what} must be one number, got shape {list(arr.shape)} of {arr.dtype}", path)
    f = float(arr.reshape(()))
    if not np.isfinite(f) or f <= 0:
        raise NerfpipeError(f"{what} must be a positive number of pixels, got {f}", path)
    return f


def synthetic_bounds(cameras: Cameras, rel_spread: float = 0.02):
    """Near/far/aabb for a scene kept in its own frame (Blender, NeRF npz).

    When every camera sits at the same distance ~4 from the origin (within ``rel_spread``),
    the scene is NeRF-synthetic-style and gets the conventional near/far 2/6; otherwise
    near/far come from :func:`~nerfpipe.data.normalize.bounds_from_cameras`. The box always does.

    Returns:
        (near, far, aabb ``[2, 3]``)
    """
    near, far, aabb = bounds_from_cameras(cameras)
    dist = cameras.centers.double().reshape(-1, 3).norm(dim=-1)
    same = float(dist.max() - dist.min()) <= rel_spread * float(dist.mean())
    if same and 3.5 <= float(dist.mean()) <= 4.5:
        near, far = SYNTHETIC_NEAR_FAR
    return near, far, aabb

