"""Distortion models: golden values from kornia (an independent implementation), inverses
against a slow per-point root finder (scipy), round trips and float64 gradcheck."""

import numpy as np
import pytest
import torch
from scipy.optimize import fsolve

from nerfpipe.functional.distortion import (
    Distortion,
    distort,
    distort_fisheye,
    distort_opencv,
    models_present,
    undistort,
    undistort_fisheye,
    undistort_opencv,
)

# Real calibrations: nerfstudio_lego (COLMAP OPENCV) and ngp_fox (instant-ngp k1 k2 p1 p2).
OPENCV_PARAMS = [
    [-0.05645860090696464, 0.20541566433871192, 0.0008393130742329684, -2.2436928521872634e-05],
    [0.0578421, -0.0805099, -0.000980296, 0.00015575],
    [-0.3, 0.1, 0.01, -0.005],  # strong barrel distortion
]
FISHEYE_PARAMS = [[0.05, -0.01, 0.002, -0.0005], [-0.02, 0.003, 0.0, 0.0]]


def _grid(n=15, extent=0.6, dtype=torch.float64):
    g = torch.linspace(-extent, extent, n, dtype=dtype)
    return torch.stack(torch.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)


@pytest.mark.parametrize("params", OPENCV_PARAMS)
def test_opencv_matches_kornia(params):
    kornia_cal = pytest.importorskip("kornia.geometry.calibration")
    xy = _grid()
    p = torch.tensor(params, dtype=torch.float64)
    ours = distort_opencv(xy, p.expand(len(xy), 4))
    K = torch.eye(3, dtype=torch.float64)  # identity K: pixels == normalised coordinates
    ref = kornia_cal.distort_points(xy[None], K[None], p[None])[0]
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("params", FISHEYE_PARAMS)
def test_fisheye_matches_kornia_kannala_brandt(params):
    kc = pytest.importorskip("kornia.geometry.camera")
    xy = _grid(extent=1.5)
    p = torch.tensor(params, dtype=torch.float64)
    ours = distort_fisheye(xy, p.expand(len(xy), 4))
    kb = torch.cat([torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64), p])
    ref = kc.distort_points_kannala_brandt(xy, kb.expand(len(xy), 8))
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)


def _slow_undistort(xy_d: np.ndarray, fn, params: torch.Tensor) -> np.ndarray:
    """Per-point root finding: the obvious, slow reference."""
    out = []
    for pt in xy_d:
        f = lambda q: fn(torch.tensor(q)[None], params[None])[0].numpy() - pt  # noqa: E731
        out.append(fsolve(f, pt, xtol=1e-12))
    return np.array(out)


@pytest.mark.parametrize(
    "fn,inv,params",
    [(distort_opencv, undistort_opencv, p) for p in OPENCV_PARAMS] + [(distort_fisheye, undistort_fisheye, p) for p in FISHEYE_PARAMS],
)
def test_undistort_matches_root_finder(fn, inv, params):
    p = torch.tensor(params, dtype=torch.float64)
    xy_d = _grid(n=7, extent=0.5)
    ours = inv(xy_d, p.expand(len(xy_d), 4))
    ref = _slow_undistort(xy_d.numpy(), fn, p)
    np.testing.assert_allclose(ours.numpy(), ref, atol=1e-10)


@pytest.mark.parametrize("kind,params", [(Distortion.OPENCV, OPENCV_PARAMS[0]), (Distortion.FISHEYE, FISHEYE_PARAMS[0])])
def test_round_trip_float32(kind, params):
    xy = _grid(n=21, extent=0.7, dtype=torch.float32)
    k = torch.full((len(xy),), int(kind))
    p = torch.tensor(params, dtype=torch.float32).expand(len(xy), 4)
    back = undistort(distort(xy, k, p), k, p)
    torch.testing.assert_close(back, xy, rtol=0, atol=2e-6)


def test_dispatch_mixed_models_and_none():
    xy = _grid(n=5, dtype=torch.float64)
    n = len(xy)
    kind = torch.tensor([int(Distortion.NONE), int(Distortion.OPENCV), int(Distortion.FISHEYE)] * n)[:n]
    params = torch.zeros(n, 4, dtype=torch.float64)
    params[kind == Distortion.OPENCV] = torch.tensor(OPENCV_PARAMS[2], dtype=torch.float64)
    params[kind == Distortion.FISHEYE] = torch.tensor(FISHEYE_PARAMS[0], dtype=torch.float64)
    out = distort(xy, kind, params)
    none = kind == Distortion.NONE
    torch.testing.assert_close(out[none], xy[none])
    cv = kind == Distortion.OPENCV
    torch.testing.assert_close(out[cv], distort_opencv(xy[cv], params[cv]))
    fe = kind == Distortion.FISHEYE
    torch.testing.assert_close(out[fe], distort_fisheye(xy[fe], params[fe]))
    assert models_present(kind) == (True, True) and models_present(kind[none]) == (False, False)
    assert models_present(kind[cv]) == (True, False) and models_present(kind[fe]) == (False, True)
    # the models given by the caller (known on the host): the same values, nothing read back for them
    from nerfpipe.training.opcount import DispatchCounter

    for sub in (slice(None), none, cv):
        present = models_present(kind[sub])
        with DispatchCounter() as c:
            given = distort(xy[sub], kind[sub], params[sub], present)
        torch.testing.assert_close(given, distort(xy[sub], kind[sub], params[sub]))
        assert "Tensor.tolist" not in c.sync_ops, dict(c.sync_ops)
    torch.testing.assert_close(undistort(out, kind, params, (True, True)), undistort(out, kind, params))


@pytest.mark.parametrize("shape", [(), (1,), (2, 3)])
def test_batch_shapes(shape):
    xy = torch.rand(*shape, 2, dtype=torch.float64) - 0.5
    p = torch.tensor(OPENCV_PARAMS[1], dtype=torch.float64).expand(*shape, 4)
    k = torch.full(shape, int(Distortion.OPENCV))
    assert distort(xy, k, p).shape == (*shape, 2)
    assert undistort(xy, k, p).shape == (*shape, 2)


def test_gradcheck_float64():
    xy = (torch.rand(6, 2, dtype=torch.float64) - 0.5).requires_grad_()
    p = torch.tensor(OPENCV_PARAMS[0], dtype=torch.float64).expand(6, 4).clone().requires_grad_()
    assert torch.autograd.gradcheck(distort_opencv, (xy, p))
    pf = torch.tensor(FISHEYE_PARAMS[0], dtype=torch.float64).expand(6, 4).clone().requires_grad_()
    assert torch.autograd.gradcheck(distort_fisheye, (xy, pf))
    # The Newton inverse is differentiable too, and its gradient is the inverse Jacobian's.
    assert torch.autograd.gradcheck(lambda a: undistort_opencv(a, p.detach()), (xy,))


def test_centre_is_fixed_point():
    z = torch.zeros(1, 2, dtype=torch.float64)
    for fn, p in ((distort_opencv, OPENCV_PARAMS[2]), (distort_fisheye, FISHEYE_PARAMS[0])):
        torch.testing.assert_close(fn(z, torch.tensor([p], dtype=torch.float64)), z)
