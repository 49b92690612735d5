"""Occupancy grid: ray-box intersection, marching against a per-sample reference, updates from a density."""

import pytest
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
        grid.update(lambda x: torch.zeros(x.shape[:1]), step_size=0.01, full=True)
    assert grid.density.max() < 10.0 * 0.5**11


def test_partial_refresh_covers_the_occupied_cells_and_a_random_fraction():
    torch.manual_seed(0)
    grid = OccupancyGridConfig(resolution=16, ema_decay=0.5, update_fraction=0.25).setup(AABB)
    grid.update(lambda x: torch.where(x[:, 0] < -0.5, 10.0, 1e-6), step_size=0.01)  # first refresh: every cell
    before = grid.density.clone()
    assert (before > 0).all() and grid.binary.float().mean() == 0.25
    grid.update(lambda x: torch.zeros(x.shape[:1]), step_size=0.01)  # later ones: part of the cells
    refreshed = grid.density != before
    occupied = before * 0.01 > 0.01
    assert refreshed[occupied].all()  # 1024 occupied cells <= 1024 drawn: all of them refreshed
    assert torch.allclose(grid.density[refreshed], before[refreshed] * 0.5)
    fraction = refreshed[~occupied].float().mean()  # 1024 uniform draws over 4096 cells, with repeats
    assert 0.15 < fraction < 0.3


def test_partial_refreshes_reach_every_occupied_cell_in_turn_without_reading_back():
    """More occupied cells than one refresh draws: taken in round robin, every one is refreshed within
    ``1 / update_fraction`` refreshes, and a refresh reads nothing back from the device."""
    from nerfpipe.training.opcount import DispatchCounter

    torch.manual_seed(0)
    grid = OccupancyGridConfig(resolution=16, ema_decay=0.5, update_fraction=0.25).setup(AABB)
    grid.update(lambda x: torch.where(x[:, 0] < 0.2, 10.0, 1e-6), step_size=0.01)  # 60 % of the cells occupied
    occupied = grid.binary.clone()
    assert occupied.sum() > 1024
    before = grid.density.clone()
    seen = torch.zeros_like(occupied)
    for rotation in range(4):
        value = 100.0 + rotation  # above every decayed density: a refreshed cell holds exactly this
        with DispatchCounter() as c:
            grid.update(lambda x: torch.full(x.shape[:1], value), step_size=0.01, rotation=rotation)
        assert c.syncs == 0, dict(c.sync_ops)
        refreshed = grid.density == value
        assert refreshed.sum() <= 2 * 1024 and not refreshed[occupied].all()  # a refresh draws 2 x 1024 rows
        seen |= refreshed
    assert seen[occupied].all()


def sparse_grid(skip_factor, seed=3):
    """A non-cubic box with sparse occupancy: a small cloud of cells, one corner cell, one cell on a face."""
    aabb = torch.tensor([[-1.0, -0.5, -1.0], [1.0, 0.5, 0.25]])
    grid = OccupancyGridConfig(resolution=32, skip_factor=skip_factor).setup(aabb)
    g = torch.Generator().manual_seed(seed)
    occ = torch.zeros(32, 32, 32, dtype=torch.bool)
    occ[12:20, 10:18, 14:22] = torch.rand(8, 8, 8, generator=g) < 0.3
    occ[31, 31, 31] = occ[0, 7, 9] = True
    grid.binary.copy_(occ.reshape(-1))
    return grid


@pytest.mark.parametrize("jitter", [False, True])
@pytest.mark.parametrize("skip_factor", [3, 4])
def test_two_level_skipping_keeps_exactly_the_same_intervals(jitter, skip_factor):
    """The coarse pass only skips intervals the fine test would drop: same samples, far fewer marched (a skip factor
    of 3 leaves a partial coarse cell at the end of the 32 cells)."""
    o, d = rays(600, seed=4)
    d[::5] = torch.nn.functional.normalize(torch.randn(120, 3, generator=torch.Generator().manual_seed(5)), dim=-1)
    fast, slow = sparse_grid(skip_factor=skip_factor), sparse_grid(skip_factor=0)
    torch.manual_seed(7)
    got = fast.march(o, d, near=0.0, far=10.0, step_size=0.02, jitter=jitter)
    torch.manual_seed(7)
    ref = slow.march(o, d, near=0.0, far=10.0, step_size=0.02, jitter=jitter)
    assert len(ref) > 100
    assert torch.equal(got.ray_indices, ref.ray_indices)
    assert torch.equal(got.t_starts, ref.t_starts) and torch.equal(got.t_ends, ref.t_ends)
    lim, lim_ref = (g._limits(o, d, 0.0, 10.0, 0.02, False, None) for g in (fast, slow))
    marched = (lim.last - lim.first + 1).clamp(min=0).sum()
    assert marched < 0.5 * (lim_ref.last - lim_ref.first + 1).clamp(min=0).sum()


def test_coarse_occupancy_follows_changes_of_the_mask():
    grid = sparse_grid(skip_factor=4)
    o, d = rays(50, seed=6)
    before = grid._limits(o, d, 0.0, 10.0, 0.02, False, None)
    grid.binary.fill_(True)  # edited in place: the cached coarse grid must not be used
    after = grid._limits(o, d, 0.0, 10.0, 0.02, False, None)
    unskipped = sparse_grid(skip_factor=0)._limits(o, d, 0.0, 10.0, 0.02, False, None)
    hit = unskipped.t0 < unskipped.t1  # rays that miss the box march nothing either way
    assert 0 < hit.sum() < 50
    assert torch.equal(after.first[hit], unskipped.first[hit]) and torch.equal(after.last[hit], unskipped.last[hit])
    assert (before.first[hit] > after.first[hit]).any()


def test_two_level_skipping_in_rounds_keeps_the_same_samples():
    """Early-terminated marching (rounds) with and without the coarse pass: the same samples and densities."""
    o, d = rays(600, seed=8)
    fast, slow = sparse_grid(skip_factor=4), sparse_grid(skip_factor=0)
    density = lambda s: 30.0 * (s.points(o, d)[:, 0] + 1.0)  # noqa: E731 - opaque towards +x
    out = []
    for grid in (fast, slow):
        torch.manual_seed(9)
        out.append(grid.march_until_opaque(o, d, 0.0, 10.0, 0.02, density, 1e-4, 1e-4, jitter=True))
    (got, sigma), (ref, ref_sigma) = out
    assert len(ref) > 100
    assert torch.equal(got.ray_indices, ref.ray_indices) and torch.equal(got.t_starts, ref.t_starts)
    assert torch.equal(sigma, ref_sigma)


@pytest.mark.parametrize("resolution", [8, 255])
def test_occupied_along_rays_matches_a_cell_looked_up_by_hand(resolution, device):
    """Points in, outside and on the far side of the box, and NaN ones: each read as its cell by hand (outside and NaN:
    empty); then after the mask is edited in place and after a refresh (the bordered copy follows both). 255 cells
    per axis: the bordered mask's rows exceed what float32 holds exactly."""
    box = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 2.0, 0.7]])
    grid = OccupancyGridConfig(resolution=resolution).setup(box).to(device)
    gen = torch.Generator().manual_seed(resolution)
    o, d = rays(64, seed=resolution)
    t = torch.rand(64, 40, generator=gen) * 7.0
    t[0, :3] = float("nan")

    def by_hand():
        pts = (o[:, None, :] + t[..., None] * d[:, None, :]).double()
        u = (pts - box[0].double()) / (box[1] - box[0]).double() * resolution
        ijk = u.floor().nan_to_num(-1.0).long()
        inside = ((ijk >= 0) & (ijk < resolution)).all(-1)
        rows = ((ijk[..., 0] * resolution + ijk[..., 1]) * resolution + ijk[..., 2]).clamp(0, resolution**3 - 1)
        return grid.binary.cpu()[rows] & inside

    def got():
        return grid.occupied_along(o.to(device), d.to(device), t.to(device)).cpu()

    for edit in ("random", "in place", "refresh"):
        if edit == "random":
            grid.binary.copy_((torch.rand(resolution**3, generator=gen) < 0.3).to(device))
        elif edit == "in place":
            grid.binary[: resolution**3 // 2] = True
        else:
            grid.update(lambda p: (p[:, 0] > 0.2).float() * 1e3, step_size=0.01, full=True)
        ref = by_hand()
        assert 30 < ref.sum() < ref.numel() - 30 and not ref[0, :3].any()
        # a point within float rounding of a cell boundary may fall in either cell
        assert (got() != ref).float().mean() < 1e-3, edit
        pts = (o[:, None, :] + t[..., None] * d[:, None, :]).reshape(-1, 3)
        assert (grid.occupied(pts.to(device)).cpu().view(64, 40) != ref).float().mean() < 1e-3, edit


def _occupied_aabb_reference(grid) -> torch.Tensor:
    """The box of the occupied cells, from their list (the whole box when none is)."""
    r = grid.cfg.resolution
    ijk = grid.binary.view(r, r, r).nonzero()
    if not len(ijk):
        return grid.aabb.clone()
    cell = (grid.aabb[1] - grid.aabb[0]) / r
    return torch.stack([grid.aabb[0] + ijk.min(0).values * cell, grid.aabb[0] + (ijk.max(0).values + 1) * cell])


@pytest.mark.parametrize("fraction", [0.0, 0.0005, 0.02, 1.0])
def test_occupied_aabb_on_the_device_matches_the_list_of_occupied_cells(fraction, device):
    grid = OccupancyGridConfig(resolution=12).setup(torch.tensor([[-1.0, -0.5, 0.0], [1.0, 2.0, 0.7]])).to(device)
    gen = torch.Generator().manual_seed(int(fraction * 1e4))
    grid.binary.copy_(torch.rand(12**3, generator=gen) < fraction)
    assert torch.equal(grid.occupied_aabb(), _occupied_aabb_reference(grid))


@pytest.mark.parametrize("fraction", [0.05, 0.2, 0.4])
def test_connected_components_match_scipy(fraction, device):
    """Label propagation gives the same partition as scipy's 26-connected labelling."""
    ndi = pytest.importorskip("scipy.ndimage")
    import numpy as np

    from nerfpipe.functional.components import connected_components

    mask = torch.rand(17, 9, 12, generator=torch.Generator().manual_seed(int(fraction * 100))) < fraction
    labels = connected_components(mask.to(device)).cpu()
    assert torch.equal(labels > 0, mask)
    ref, count = ndi.label(mask.numpy(), structure=np.ones((3, 3, 3)))
    ours, theirs = labels[mask].tolist(), ref[mask.numpy()].tolist()
    assert len(set(ours)) == count and len(set(zip(ours, theirs))) == count  # one-to-one: the same pieces


def test_supported_aabb_leaves_out_floaters_but_keeps_every_large_piece(device):
    """Two objects (the smaller 9 % of the occupied cells) and scattered single-cell floaters: the box holds both
    objects and no floater; with no floater it is the occupied box."""
    r = 32
    grid = OccupancyGridConfig(resolution=r).setup(AABB).to(device)
    occ = torch.zeros(r, r, r, dtype=torch.bool)
    occ[10:20, 8:22, 12:18] = True  # the object
    occ[22:26, 14:18, 12:17] = True  # a second, separate one (two cells away)
    grid.binary.copy_(occ.reshape(-1))
    objects = grid.occupied_aabb()
    assert torch.equal(grid.supported_aabb(), objects)
    for ijk in [(0, 0, 0), (31, 31, 31), (2, 28, 5), (30, 3, 25)]:  # floaters: 4 cells of 924
        occ[ijk] = True
    grid.binary.copy_(occ.reshape(-1))
    assert torch.equal(grid.occupied_aabb(), grid.aabb)
    assert torch.equal(grid.supported_aabb(), objects)
    assert torch.equal(grid.supported_aabb(min_share=0.0), grid.aabb)
