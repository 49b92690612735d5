"""Sparse grid levels (blocks of vertices stored where the occupied space needs them) against the dense layout."""

import copy
import itertools
import math

import pytest
import torch

from nerfpipe.data.rays import RayBundle
from nerfpipe.estimators.occupancy import OccupancyGridConfig
from nerfpipe.fields.grid import (
    BLOCK, DenseGridEncoding, block_row_reference, block_rows, blocks_per_axis, grid_gather, needed_blocks, trilinear_corners,
)
from nerfpipe.models.base import SceneInfo
from nerfpipe.models.fast import FastConfig

RES = (11, 6, 9)  # blocks (3, 2, 3), the last ones partly past the grid


def points(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 1.2 - 0.1  # some outside the cube: clamped
    x[0] = 1.0  # the far corner vertex
    return x


def random_blocks(res, seed, share=0.6):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(blocks_per_axis(res), generator=g) < share


@pytest.mark.parametrize("table_rows", [None, 24 * BLOCK**3])  # not known (float64 sums), known (float32 on the CPU)
def test_block_rows_match_the_one_vertex_reference(table_rows):
    nb = blocks_per_axis(RES)
    g = torch.Generator().manual_seed(1)
    block_map = torch.randperm(24, generator=g)[: nb[0] * nb[1] * nb[2]]
    block_map[torch.rand(block_map.shape, generator=g) < 0.3] = -1
    lo = torch.stack([torch.randint(0, n - 1, (60,), generator=g) for n in RES], -1)
    rows, stored = block_rows(lo.float(), block_map, nb, table_rows)
    ref = [
        [block_row_reference(i + di, j + dj, k + dk, block_map.tolist(), nb) for di, dj, dk in itertools.product((0, 1), repeat=3)]
        for i, j, k in lo.tolist()
    ]
    ref = torch.tensor(ref)
    assert torch.equal(stored, ref >= 0)
    assert torch.equal(rows[stored], ref[stored]) and bool((rows[~stored] < BLOCK**3).all())


def test_needed_blocks_match_a_brute_force_search():
    g = torch.Generator().manual_seed(2)
    occ = torch.rand(7, 9, 5, generator=g) < 0.04
    for dilation in (0, 1):
        got, again = needed_blocks(occ, [RES, RES], dilation)
        assert torch.equal(got, again)
        dil = torch.nn.functional.max_pool3d(occ.float()[None, None], 2 * dilation + 1, 1, padding=dilation)[0, 0] > 0 if dilation else occ
        want = torch.zeros(blocks_per_axis(RES), dtype=torch.bool)
        for b in itertools.product(*(range(n) for n in blocks_per_axis(RES))):
            for c in itertools.product(*(range(max(0, BLOCK * bb - 1), min(BLOCK * bb + BLOCK, n - 1)) for bb, n in zip(b, RES))):
                # level cell c spans [c, c + 1] / (n - 1) per axis: the occupancy cells it overlaps
                span = [range(math.floor(ci / (n - 1) * r), math.ceil((ci + 1) / (n - 1) * r)) for ci, n, r in zip(c, RES, occ.shape)]
                if dil[span[0].start : span[0].stop, span[1].start : span[1].stop, span[2].start : span[2].stop].any():
                    want[b] = True
        assert torch.equal(got, want), dilation


def test_a_sparse_level_reads_and_trains_as_the_dense_level_where_stored(device):
    """Values, and gradients into the table and the weights, of a sparse level equal the dense level's with the
    unstored vertices set to zero; the unstored corners get no gradient."""
    enc = DenseGridEncoding([(3, 3, 3), RES], channels=3, init_scale=1.0).to(device)
    sp = copy.deepcopy(enc)
    blocks = random_blocks(RES, 3)
    sp.sparsify(1, blocks.to(device), headroom=0.5)
    assert sp.sparse(1) and not sp.sparse(0)
    stored_blocks = int(blocks.sum())
    assert sp.tables[1].shape[0] == -(-stored_blocks * 3 // 2) * BLOCK**3 and int(sp.slots_used_1) == stored_blocks
    # the dense reference: vertices of unstored blocks read as zero
    ijk = torch.stack(torch.meshgrid(*(torch.arange(n) for n in RES), indexing="ij"), -1).reshape(-1, 3)
    kept = blocks[ijk[:, 0] // BLOCK, ijk[:, 1] // BLOCK, ijk[:, 2] // BLOCK].to(device)
    with torch.no_grad():
        enc.tables[1].mul_(kept[:, None])
    x = points(200).to(device)
    torch.testing.assert_close(sp(x), enc(x), rtol=1e-6, atol=1e-6)
    assert [len(c) for c in sp.corners_of(2, x)] == [2, 2]
    for (si, sw), (ci, cw) in zip(sp.corners_of(2, x), [sp.corners(0, x), sp.corners(1, x)]):
        assert torch.equal(si, ci) and torch.equal(sw, cw)
    coef = torch.randn(200, 6, generator=torch.Generator().manual_seed(4)).to(device)
    (sp(x) * coef).sum().backward()
    (enc(x) * coef).sum().backward()
    rows, stored = block_rows(ijk.float().to(device), sp.block_map(1), blocks_per_axis(RES))
    rows = rows[:, 0]  # each vertex's own row (corner (0, 0, 0))
    torch.testing.assert_close(sp.tables[1].grad[rows[kept]], enc.tables[1].grad[kept], rtol=1e-5, atol=1e-6)
    used = torch.zeros(sp.tables[1].shape[0], dtype=torch.bool, device=device)
    used[rows[kept]] = True
    assert bool((sp.tables[1].grad[~used] == 0).all())  # free slots and padding rows stay untouched


def test_sparse_levels_read_together_as_each_alone_and_follow_their_growth(device):
    """Sparse levels with a dense one between them read together as each level alone; a map grown in place is read
    anew."""
    res2 = (9, 14, 5)
    enc = DenseGridEncoding([RES, (3, 3, 3), res2], channels=2, init_scale=1.0).to(device)
    enc.sparsify(0, random_blocks(RES, 5).to(device), headroom=1.0)
    enc.sparsify(2, random_blocks(res2, 6, share=0.3).to(device), headroom=4.0)  # room for every block
    x = points(300, seed=7).to(device)
    together = enc.corners_of(3, x)
    for level, (rows, w) in enumerate(together):
        alone = enc.corners(level, x)
        assert torch.equal(rows, alone[0]) and torch.equal(w, alone[1]), level
    assert bool((together[2][1] == 0).any()) and bool((together[2][1] != 0).any())
    enc.grow(2, torch.ones(blocks_per_axis(res2), dtype=torch.bool, device=device))
    assert int(enc.blocks_missing(2)) == 0
    assert torch.equal(enc.corners_of(3, x)[2][1], trilinear_corners(x, res2)[1])  # every corner stored: plain weights


def test_grow_takes_free_slots_on_the_device_and_counts_what_does_not_fit():
    enc = DenseGridEncoding([RES], channels=2, init_scale=1.0)
    first = torch.zeros(blocks_per_axis(RES), dtype=torch.bool)
    first[0, 0, 0] = first[2, 1, 2] = True
    enc.sparsify(0, first, headroom=1.0)  # 2 blocks stored, 2 free
    before = enc.tables[0].detach().clone()
    x = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.0, 0.0]])
    values = enc(x).detach()
    more = first.clone()
    more[1, 0, 0] = more[0, 1, 0] = more[1, 1, 1] = True
    enc.grow(0, more)
    assert int(enc.slots_used_0) == 4 and int(enc.blocks_missing_0) == 1
    assert (enc.block_map(0) >= 0).sum() == 4
    assert torch.equal(enc.tables[0].detach(), before)  # nothing moved; the new blocks' rows are the free zeros
    torch.testing.assert_close(enc(x)[:2], values[:2])
    enc.grow(0, more)  # nothing new fits
    assert int(enc.slots_used_0) == 4 and int(enc.blocks_missing_0) == 1


def test_old_checkpoints_without_block_maps_load_as_dense():
    enc = DenseGridEncoding([(3, 3, 3), RES], channels=2)
    state = {k: v for k, v in enc.state_dict().items() if not k.startswith(("block_map", "slots_used"))}
    fresh = DenseGridEncoding([(3, 3, 3), RES], channels=2)
    fresh.load_state_dict(state)
    assert not fresh.sparse(1) and torch.equal(fresh.tables[1], enc.tables[1])


def tiny_info():
    return SceneInfo(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), near=0.5, far=6.0, num_images=10, pixels_per_image=1024)


def ball_model(sparse_min_vertices, headroom=0.25, thickness=0.03):
    """A model whose field is a spherical shell of density (the occupancy knows it) with random colour features,
    tightened."""
    cfg = FastConfig(
        levels=(8, 64), feature_channels=2, hidden=16, log2_hashmap_size=0, sparse_min_vertices=sparse_min_vertices, sparse_headroom=headroom,
        occupancy=OccupancyGridConfig(resolution=64, warmup_steps=0, update_every=1000),  # no refresh at step 1
    )
    torch.manual_seed(0)
    model = cfg.setup(tiny_info())
    with torch.no_grad():
        for table, res in zip(model.field.density_grid.tables, model.field.density_grid.resolutions):
            ijk = torch.stack(torch.meshgrid(*(torch.linspace(-1, 1, n) for n in res), indexing="ij"), -1).reshape(-1, 3)
            table[:, 0] = torch.where((ijk.norm(dim=-1) - 0.5).abs() < thickness, 8.0, -8.0) + 0.5 * torch.randn(len(ijk))
        for table in model.field.feature_grid.tables:
            table.normal_()
    model.grid.update(model.field.density, model.step_size, full=True)
    model.tighten()
    assert not any(model.field.density_grid.sparse(lv) for lv in range(2))  # at the next step's start
    model._before_step(1)
    return model


def test_a_sparse_field_renders_as_its_dense_field_and_round_trips_through_a_checkpoint():
    dense, sparse = ball_model(0), ball_model(1000)
    assert [sparse.field.density_grid.sparse(lv) for lv in range(2)] == [False, True]
    assert [sparse.field.feature_grid.sparse(lv) for lv in range(2)] == [False, True]
    stats = sparse.stats()
    assert stats["sparse_levels"] == 1 and 0 < stats["sparse_stored_share"] < 1 and stats["sparse_blocks_missing"] == 0
    assert stats["model_mb"] < dense.stats()["model_mb"]
    g = torch.Generator().manual_seed(5)
    origins = torch.randn(300, 3, generator=g)
    origins = 3.0 * origins / origins.norm(dim=-1, keepdim=True)
    directions = torch.nn.functional.normalize(-origins + 0.3 * torch.randn(300, 3, generator=g), dim=-1)
    rays = RayBundle(origins=origins, directions=directions, cam_idx=torch.zeros(300, dtype=torch.long), z_scale=torch.ones(300))
    bg = torch.ones(300, 3)
    dense.eval(), sparse.eval()
    with torch.no_grad():
        a, b = dense.get_outputs(rays, bg), sparse.get_outputs(rays, bg)
    assert float(a.acc.max()) > 0.8  # the rays see the shell
    torch.testing.assert_close(b.rgb, a.rgb, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(b.depth, a.depth, rtol=1e-5, atol=1e-5)
    loaded = FastConfig(**{**vars(sparse.cfg)}).setup(tiny_info())
    loaded.load_state_dict(sparse.state_dict())
    loaded.eval()
    assert loaded.field.density_grid.sparse(1) and loaded.field.feature_grid.sparse(1)
    with torch.no_grad():
        c = loaded.get_outputs(rays, bg)
    assert torch.equal(c.rgb, b.rgb)


def test_a_level_whose_blocks_would_fill_most_of_it_stays_dense():
    model = ball_model(1000, thickness=0.3)  # a thick shell: nearly every block of the tightened box is needed
    assert not model.field.density_grid.sparse(1) and not model.field.feature_grid.sparse(1)


def test_sparse_levels_store_the_blocks_that_newly_occupied_cells_reach():
    model = ball_model(1000)
    grid = model.field.density_grid
    used = int(grid.slots_used_1)
    with torch.no_grad():  # more of the box becomes occupied: its blocks are stored at the next refresh
        model.grid.binary.view(64, 64, 64)[:, :, :2] = True
    model._grow_sparse()
    assert int(grid.slots_used_1) > used
    assert torch.equal(model.field.feature_grid.block_map(1), grid.block_map(1))


def test_a_relaid_out_table_keeps_its_values_optimizer_moments_and_average_with_its_rows():
    from nerfpipe.training.averaging import ParameterAverage
    from nerfpipe.training.trainer import drop_stale_optimizer_state

    enc = DenseGridEncoding([RES], channels=2, init_scale=1.0)
    first = random_blocks(RES, 7)
    enc.sparsify(0, first, headroom=0.0)
    opt = torch.optim.Adam(enc.parameters(), lr=0.1)
    average = ParameterAverage(enc, start=0, decay=0.5)
    x = points(100)
    for step in range(1, 4):
        opt.zero_grad()
        enc(x).square().sum().backward()
        opt.step()
        average.update(step)
    table = enc.tables[0]
    rows = table.shape[0]
    nb = blocks_per_axis(RES)
    ijk = torch.stack(torch.meshgrid(*(torch.arange(n) for n in RES), indexing="ij"), -1).reshape(-1, 3)

    def vertex_rows(e):
        r, stored = block_rows(ijk.float(), e.block_map(0), nb)
        return r[:, 0], stored[:, 0]

    before_rows, before_stored = vertex_rows(enc)
    values = table.detach()[before_rows]
    moments = {k: v[before_rows] for k, v in opt.state[table].items() if v.ndim}
    averaged = average.values["tables.0"][before_rows]
    second = first.clone()
    second.view(-1)[torch.nonzero(first.view(-1))[0]] = False  # one block dropped
    second.view(-1)[torch.nonzero(~first.view(-1))[:2, 0]] = True  # two added
    enc.relayout(0, second, headroom=0.5)
    assert enc.capacity(0) == -(-int(second.sum()) * 3 // 2) and int(enc.slots_used(0)) == int(second.sum())
    after_rows, after_stored = vertex_rows(enc)
    both = before_stored & after_stored
    assert torch.equal(table.detach()[after_rows[both]], values[both])  # the kept blocks' values, moved
    new = after_stored & ~before_stored
    assert bool(new.any()) and bool((table.detach()[after_rows[new]] == 0).all())
    drop_stale_optimizer_state(opt)
    for k, v in moments.items():
        assert torch.equal(opt.state[table][k][after_rows[both]], v[both])
        assert bool((opt.state[table][k][after_rows[new]] == 0).all())
    opt.zero_grad()
    enc(x).square().sum().backward()
    opt.step()  # free rows get no gradient and stay zero
    used = torch.zeros(table.shape[0], dtype=torch.bool)
    used[after_rows[after_stored]] = True
    assert bool((table.detach()[~used] == 0).all())
    average.update(4)
    assert average.count == 4  # not restarted
    torch.testing.assert_close(average.values["tables.0"][after_rows[both]], torch.lerp(averaged[both], table.detach()[after_rows[both]], 0.5))
    # a resampled table (not re-laid out) still drops its state
    table.data = torch.zeros(rows - 64, 2)
    drop_stale_optimizer_state(opt)
    assert opt.state[table] == {}


def test_a_sparse_level_out_of_free_blocks_is_laid_out_again_at_a_check():
    model = ball_model(1000, headroom=0.0)
    grid = model.field.density_grid
    capacity = grid.capacity(1)
    with torch.no_grad():
        model.grid.binary.view(64, 64, 64)[:, :, :3] = True
    model._grow_sparse()  # what does not fit is counted, read as zeros
    assert int(grid.blocks_missing(1)) > 0 and grid.capacity(1) == capacity
    model._relayout_sparse()  # at the next check: every needed block stored
    assert grid.capacity(1) > capacity and int(grid.blocks_missing(1)) == 0
    assert model.field.feature_grid.capacity(1) == grid.capacity(1)
    assert torch.equal(model.field.feature_grid.block_map(1), grid.block_map(1))
    with torch.no_grad():  # the added slab empties again: its blocks are dropped at the next check
        model.grid.binary.view(64, 64, 64)[:, :, :3] = False
    model._relayout_sparse()
    assert grid.capacity(1) == capacity


def test_block_rows_stay_exact_when_float32_products_may_lose_precision(monkeypatch):
    """Where float32 matrix products may run in reduced precision, the corner sums run in float64: the same rows."""
    import nerfpipe.fields.grid as grid

    nb = (300, 300, 300)  # block indices up to 2.7e7: beyond float32's whole numbers, so float64 is used here anyway
    g = torch.Generator().manual_seed(8)
    lo = torch.stack([torch.randint(0, 4 * n - 1, (50,), generator=g) for n in nb], -1).float()
    block_map = torch.arange(nb[0] * nb[1] * nb[2]) * BLOCK**3
    rows, _ = block_rows(lo.double(), block_map, nb)
    b = BLOCK  # block_map holds block n's first row at n * b^3: the row of a vertex written out
    ref = [(((i // b) * nb[1] + j // b) * nb[2] + k // b) * b**3 + ((i % b) * b + j % b) * b + k % b for i, j, k in lo.long().tolist()]
    assert rows[:, 0].tolist() == ref
    small = (3, 2, 3)
    lo = torch.stack([torch.randint(0, 4 * n - 1, (50,), generator=g) for n in small], -1).float()
    block_map = torch.arange(18) * BLOCK**3
    exact, _ = block_rows(lo, block_map, small, rows=18 * BLOCK**3)  # float32
    assert torch.equal(exact, block_rows(lo, block_map, small)[0])  # the table's rows not known: float64
    monkeypatch.setattr(grid, "_exact_float32", lambda device: False)
    assert torch.equal(block_rows(lo, block_map, small, rows=18 * BLOCK**3)[0], exact)


def test_a_checkpoint_taken_between_the_tightening_and_the_next_step_makes_its_levels_sparse_when_resumed():
    cfg = FastConfig(
        levels=(8, 64), feature_channels=2, hidden=16, log2_hashmap_size=0, sparse_min_vertices=1000,
        occupancy=OccupancyGridConfig(resolution=64, warmup_steps=0, update_every=1000),
    )
    straight = ball_model(1000)
    model = cfg.setup(tiny_info())
    with torch.no_grad():
        for table, res in zip(model.field.density_grid.tables, model.field.density_grid.resolutions):
            ijk = torch.stack(torch.meshgrid(*(torch.linspace(-1, 1, n) for n in res), indexing="ij"), -1).reshape(-1, 3)
            table[:, 0] = torch.where((ijk.norm(dim=-1) - 0.5).abs() < 0.03, 8.0, -8.0)
    model.grid.update(model.field.density, model.step_size, full=True)
    model.tighten()
    resumed = cfg.setup(tiny_info())
    resumed.load_state_dict(model.state_dict())
    assert not resumed.field.density_grid.sparse(1)
    resumed._before_step(1)
    assert resumed.field.density_grid.sparse(1) and straight.field.density_grid.sparse(1)
