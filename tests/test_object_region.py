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


def _block(gen: torch.Generator, n: int = 2000) -> torch.Tensor:
    """Points spread evenly over a 1.0 x 0.4 x 0.3 block at the origin."""
    return (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * torch.tensor([1.0, 0.4, 0.3], dtype=torch.float64)


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


def test_a_part_with_few_points_stays_inside_and_single_outliers_stay_out():
    """An arm of the object carrying 0.7 % of its points (a plain side that few photos show: session 75's 23-photo cut
    of colmap_mouse, whose lilac side the 2 % quantile's box cut flat) lies inside the region; points
    scattered far and alone (mismatches) do not stretch it."""
    from nerfpipe.data.normalize import isolated

    cams = ring_cameras(distance=4.0)
    gen = torch.Generator().manual_seed(2)
    body = _block(gen)
    arm = torch.rand(15, 3, generator=gen, dtype=torch.float64) * 0.1 + torch.tensor([0.8, -0.05, -0.05], dtype=torch.float64)
    strays = torch.rand(10, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 2.0, 2.0], dtype=torch.float64) + torch.tensor([1.5, -1.0, -1.0], dtype=torch.float64)
    xyz = torch.cat([body, arm, strays])
    flagged = isolated(xyz)
    assert bool(flagged[-10:].all()) and int(flagged[:-10].sum()) <= 0.01 * len(body)  # the strays, hardly any other
    lo, hi = object_region(cams, xyz)
    assert float(hi[0]) >= 0.9 and float(hi[0]) < 1.5, hi  # the arm inside, the strays (x >= 1.5) outside
    assert float(lo[0]) <= -0.5 and float(hi[1]) >= 0.2 and float(hi[2]) >= 0.15
    assert float(object_region(cams, xyz, cover=None)[1, 0]) < 0.9  # the robust extent alone (the rule until session 75) cuts it off
    assert torch.equal(object_region(cams, body), object_region(cams, body, cover=None))  # points all inside: as it was
    assert not isolated(xyz[:5]).any()  # too few to say


def test_points_level_with_the_base_or_below_do_not_move_the_region():
    """A patch of textured table beyond the robust extent (as dense as the arm above, level with the object's base) and a
    patch of floor below it are the surroundings: the region is what the robust extent gives."""
    cams = ring_cameras(distance=4.0)
    gen = torch.Generator().manual_seed(3)
    body = _block(gen)
    table = torch.rand(15, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.1, 0.1, 0.01], dtype=torch.float64) + torch.tensor([0.8, -0.05, -0.15], dtype=torch.float64)
    floor = torch.rand(15, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.1, 0.1, 0.01], dtype=torch.float64) + torch.tensor([0.0, -0.05, -0.9], dtype=torch.float64)
    xyz = torch.cat([body, table, floor])
    assert torch.equal(object_region(cams, xyz), object_region(cams, xyz, cover=None))
    raised = torch.cat([body, table + torch.tensor([0.0, 0.0, 0.15], dtype=torch.float64)])  # the same patch half-way up: a part
    assert float(object_region(cams, raised)[1, 0]) > float(object_region(cams, raised, cover=None)[1, 0]) + 0.1
