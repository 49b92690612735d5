"""Occupancy grid: ray-box intersection, marching against a per-sample reference, updates from a density."""

import torch

from nerfpipe.estimators.occupancy import OccupancyGridConfig, ray_aabb_intersect

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def rays(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 3
    target = (torch.rand(n, 3, generator=g) - 0.5) * 1.5
    return origins, torch.nn.functional.normalize(target - origins, dim=-1)


def test_ray_aabb_intersect_axis_and_miss():
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 5.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    t0, t1 = ray_aabb_intersect(o, d, AABB)
    assert torch.allclose(t0[0], torch.tensor(2.0)) and torch.allclose(t1[0], torch.tensor(4.0))
    assert t0[1] > t1[1]


def test_march_keeps_exactly_the_occupied_intervals():
    grid = OccupancyGridConfig(resolution=8).setup(AABB)
    g = torch.Generator().manual_seed(1)
    grid.binary.copy_(torch.rand(8**3, generator=g) < 0.3)
    o, d = rays(40)
    step = 0.05
    packed = grid.march(o, d, near=0.0, far=10.0, step_size=step)
    full = OccupancyGridConfig(resolution=8).setup(AABB).march(o, d, near=0.0, far=10.0, step_size=step)
    t0, t1 = ray_aabb_intersect(o, d, AABB)
    for r in range(40):
        mine = full.ray_indices == r
        starts, ends = full.t_starts[mine], full.t_ends[mine]
        if t1[r] > t0[r]:  # the unpruned intervals tile [t0, t1] exactly
            assert torch.allclose(starts[0], t0[r]) and torch.allclose(ends[-1], t1[r], atol=1e-5)
            assert torch.allclose(starts[1:], ends[:-1])
        expected = []  # reference: one interval at a time, its midpoint's cell looked up by hand
        for s, e in zip(starts.tolist(), ends.tolist()):
            p = o[r] + 0.5 * (s + e) * d[r]
            ijk = ((p + 1) / 2 * 8).long().clamp(0, 7)
            if grid.binary[(ijk[0] * 8 + ijk[1]) * 8 + ijk[2]]:
                expected.append(s)
        got = packed.t_starts[packed.ray_indices == r]
        assert torch.allclose(got, torch.tensor(expected).reshape(-1)), r


def test_jitter_shifts_but_still_tiles():
    grid = OccupancyGridConfig(resolution=4).setup(AABB)
    o, d = rays(10, seed=2)
    p = grid.march(o, d, near=0.0, far=10.0, step_size=0.1, jitter=True)
    t0, t1 = ray_aabb_intersect(o, d, AABB)
    length = torch.zeros(10).index_add_(0, p.ray_indices, p.t_ends - p.t_starts)
    assert torch.allclose(length, (t1 - t0).clamp(min=0), atol=1e-5)


def test_update_from_sphere_density():
    grid = OccupancyGridConfig(resolution=16, threshold=0.01).setup(AABB)
    sphere = lambda x: torch.where(x.norm(dim=-1) < 0.5, 100.0, 0.0)  # noqa: E731
    grid.update(sphere, step_size=0.01)
    centers = grid.cell_centers(jitter=False)
    r = centers.norm(dim=-1)
    half_diag = 3**0.5 / 16
    assert grid.binary[r < 0.5 - half_diag].all()  # cells wholly inside are occupied
    assert not grid.binary[r > 0.5 + half_diag].any()  # cells wholly outside are empty
    box = grid.occupied_aabb()
    assert (box[0] >= -0.5 - 0.125 - 1e-6).all() and (box[1] <= 0.5 + 0.125 + 1e-6).all()
    assert (box[0] <= -0.5 + 1e-6).all() and (box[1] >= 0.5 - 1e-6).all()


def test_update_decays_when_density_vanishes():
    grid = OccupancyGridConfig(resolution=8, ema_decay=0.5).setup(AABB)
    grid.update(lambda x: torch.full(x.shape[:1], 10.0), step_size=0.01)
    assert grid.binary.all()
    for _ in range(12):
        grid.update(lambda x: torch.zeros(x.shape[:1]), step_size=0.01)
    assert grid.density.max() < 10.0 * 0.5**11
