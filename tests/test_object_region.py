"""The object region: where the cameras look, from the sparse points that are there, with a margin for the
object's parts that carry few points."""

import torch

from nerfpipe.data.normalize import OBJECT_PAD, bounds_from_points, object_region
from test_mesh_clean import ring_cameras


def _object(n: int = 2000, seed: int = 0) -> torch.Tensor:
    """Points on a 1.0 x 0.4 x 0.3 block at the origin whose +x end (the last 15%) has almost no points,
    as a texture-less end of a real object has."""
    gen = torch.Generator().manual_seed(seed)
    xyz = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * torch.tensor([1.0, 0.4, 0.3], dtype=torch.float64)
    textured = xyz[xyz[:, 0] < 0.35]
    plain = xyz[xyz[:, 0] >= 0.35][:10]
    return torch.cat([textured, plain])


def test_far_background_points_do_not_grow_the_region():
    cams = ring_cameras(distance=4.0)
    obj = _object()
    gen = torch.Generator().manual_seed(1)
    wall = torch.rand(3000, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.1, 20.0, 6.0], dtype=torch.float64) + torch.tensor([9.0, -10.0, -3.0], dtype=torch.float64)
    alone, with_wall = object_region(cams, obj), object_region(cams, torch.cat([obj, wall]))
    assert torch.allclose(alone, with_wall, atol=0.05)
    assert float(with_wall[1, 0]) < 1.0  # the wall at x = 9 is background, though it has more points than the object
    # with every point far from the focus, all of them count (nothing else describes the scene)
    assert torch.allclose(object_region(cams, wall), object_region(cams, wall, reach=1e9))


def test_the_margin_keeps_a_sparsely_sampled_end():
    cams = ring_cameras(distance=4.0)
    lo, hi = object_region(cams, _object())
    assert float(hi[0]) >= 0.5 and float(lo[0]) <= -0.5  # the plain end (x in [0.35, 0.5]) is inside
    assert float(hi[0]) < 0.5 + OBJECT_PAD  # and the margin is no larger than it needs to be for that
    near, far, aabb = bounds_from_points(cams, _object().float())
    assert torch.allclose(aabb, torch.stack([lo, hi]).float()) and 0 < near < far
