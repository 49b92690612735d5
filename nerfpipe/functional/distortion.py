"""Lens distortion on normalised image coordinates, as pure tensor functions.

Glossary:
    xy     undistorted normalised coordinates, ``(X/Z, Y/Z)`` in the OpenCV camera frame
    xy_d   distorted normalised coordinates, ``((u - cx)/fx, (v - cy)/fy)``
    params ``[*bs, 4]``: ``k1 k2 p1 p2`` for OPENCV, ``k1 k2 k3 k4`` for FISHEYE

Models follow COLMAP/OpenCV exactly. SIMPLE_RADIAL (``k``) and RADIAL (``k1 k2``) are
OPENCV with the missing parameters zero; PINHOLE is OPENCV with all zeros.
"""

from enum import IntEnum

import torch

from nerfpipe.util.typing import Float, Int, Tensor


class Distortion(IntEnum):
    """Distortion model of a camera (stored per camera as an int code)."""

    NONE = 0
    OPENCV = 1  # radial-tangential: k1 k2 p1 p2
    FISHEYE = 2  # OpenCV/COLMAP equidistant fisheye: k1 k2 k3 k4


def distort_opencv(xy: Float[Tensor, "*bs 2"], params: Float[Tensor, "*bs 4"]) -> Float[Tensor, "*bs 2"]:
    """Apply OpenCV radial-tangential distortion (k1, k2, p1, p2)."""
    x, y = xy[..., 0], xy[..., 1]
    k1, k2, p1, p2 = params.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + k2 * r2)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def _opencv_residual_and_jacobian(xy, xy_d, params):
    x, y = xy[..., 0], xy[..., 1]
    k1, k2, p1, p2 = params.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + k2 * r2)
    d_radial = 2 * (k1 + 2 * k2 * r2)  # d(radial)/dx = x * d_radial
    fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xy_d[..., 0]
    fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - xy_d[..., 1]
    j00 = radial + x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    j01 = x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    j11 = radial + y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    return fx, fy, j00, j01, j11  # the Jacobian is symmetric: j10 == j01


def undistort_opencv(
    xy_d: Float[Tensor, "*bs 2"], params: Float[Tensor, "*bs 4"], iterations: int = 20
) -> Float[Tensor, "*bs 2"]:
    """Invert :func:`distort_opencv` by Newton's method (no closed form exists).

    Converges quadratically inside the region where the distortion is monotonic, which
    covers every real calibration we have seen; 20 iterations are far more than needed.
    """
    xy = xy_d.clone()
    tol = _tolerance(xy_d)
    for _ in range(iterations):
        fx, fy, j00, j01, j11 = _opencv_residual_and_jacobian(xy, xy_d, params)
        if fx.numel() == 0 or float(torch.maximum(fx.detach().abs().max(), fy.detach().abs().max())) <= tol:
            break  # converged everywhere (usually after 2-4 steps)
        det = j00 * j11 - j01 * j01
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        dx = (j11 * fx - j01 * fy) / det
        dy = (j00 * fy - j01 * fx) / det
        xy = xy - torch.stack([dx, dy], dim=-1)
    return xy


def distort_fisheye(xy: Float[Tensor, "*bs 2"], params: Float[Tensor, "*bs 4"]) -> Float[Tensor, "*bs 2"]:
    """Apply the OpenCV/COLMAP equidistant fisheye model (k1..k4)."""
    r = xy.norm(dim=-1)
    theta = torch.atan(r)
    t2 = theta * theta
    k1, k2, k3, k4 = params.unbind(-1)
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    scale = torch.where(r > 1e-12, theta_d / r.clamp_min(1e-12), torch.ones_like(r))
    return xy * scale[..., None]


def undistort_fisheye(
    xy_d: Float[Tensor, "*bs 2"], params: Float[Tensor, "*bs 4"], iterations: int = 20
) -> Float[Tensor, "*bs 2"]:
    """Invert :func:`distort_fisheye`: Newton on theta, then ``r = tan(theta)``."""
    theta_d = xy_d.norm(dim=-1)
    k1, k2, k3, k4 = params.unbind(-1)
    theta = theta_d.clone()
    tol = _tolerance(xy_d)
    for _ in range(iterations):
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        if f.numel() == 0 or float(f.detach().abs().max()) <= tol:
            break
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + 9 * t2 * k4)))
        theta = theta - f / df.clamp_min(1e-6)
    scale = torch.where(theta_d > 1e-12, torch.tan(theta) / theta_d.clamp_min(1e-12), torch.ones_like(theta))
    return xy_d * scale[..., None]


def _tolerance(x: Tensor) -> float:
    """Residual below which Newton stops: a few ulps of the working precision."""
    return 8 * torch.finfo(x.dtype).eps


def distort(
    xy: Float[Tensor, "*bs 2"], kind: Int[Tensor, "*bs"], params: Float[Tensor, "*bs 4"], present: "tuple[bool, bool] | None" = None
) -> Float[Tensor, "*bs 2"]:
    """Distort normalised coordinates with a per-element model code (see :class:`Distortion`); ``present``:
    :func:`models_present` of ``kind`` or of a batch it was drawn from, when the caller knows it (None: read back)."""
    return _dispatch(xy, kind, params, distort_opencv, distort_fisheye, present)


def undistort(
    xy_d: Float[Tensor, "*bs 2"], kind: Int[Tensor, "*bs"], params: Float[Tensor, "*bs 4"], present: "tuple[bool, bool] | None" = None
) -> Float[Tensor, "*bs 2"]:
    """Undistort normalised coordinates with a per-element model code (see :class:`Distortion`); ``present`` as
    for :func:`distort`."""
    return _dispatch(xy_d, kind, params, undistort_opencv, undistort_fisheye, present)


_MODELS = (Distortion.OPENCV, Distortion.FISHEYE)
"""The distortion models with a formula, in the order of :func:`models_present`."""


def models_present(kind: Int[Tensor, "*bs"]) -> "tuple[bool, bool]":
    """Whether any element has the OpenCV model, and whether any has the fisheye model: read back from the
    device once (a host sync on CUDA). Computed once for a set of cameras, it spares every batch drawn from
    them the read (``present=``)."""
    return tuple(torch.stack([(kind == code).any() for code in _MODELS]).tolist())


def _dispatch(xy, kind, params, opencv_fn, fisheye_fn, present=None):
    # Each model runs only on its own elements, so one model's parameters never reach the
    # other's formula (no NaN in unused branches, hence none in gradients).
    # Which models occur is read back once for both (a host sync on CUDA; two reads were two), unless given.
    out = xy
    present = models_present(kind) if present is None else present
    for code, fn, found in zip(_MODELS, (opencv_fn, fisheye_fn), present):
        if found:
            mask = kind == code
            out = out.clone() if out is xy else out
            out[mask] = fn(xy[mask], params[mask])
    return out
