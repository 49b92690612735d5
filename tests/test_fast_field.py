"""The fast grid field: trilinear gathers against a loop reference (values, float64 gradcheck),
resampling on box tightening, checkpoint round trip, and a tiny training run that learns."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nerfpipe.data.rays import RayBundle
from nerfpipe.data_adapters import load
from nerfpipe.estimators.occupancy import OccupancyGridConfig
from nerfpipe.functional.gather import gather_rows_sum, row_dot
from nerfpipe.fields.grid import DenseGridEncoding, grid_gather, hashed_row_reference, trilinear, trilinear_corners
from nerfpipe.models.base import SceneInfo
from nerfpipe.models.fast import (
    LR_DECAY_STEPS,
    LR_DECAY_STEPS_REAL,
    MAX_FINEST,
    MAX_FINEST_BOUNDED,
    MAX_LEVELS,
    FastConfig,
    auto_preset,
    compact_capacity,
)
from nerfpipe.training.trainer import Trainer, TrainerConfig
from reference import trilinear_loop

RES = (5, 4, 6)


def points(n, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g, dtype=dtype) * 1.2 - 0.1  # some outside the cube: clamped
    x[0] = torch.tensor([1.0, 1.0, 1.0], dtype=dtype)  # the far corner vertex
    return x


def test_trilinear_matches_loop_reference(dtype, tol, device):
    table = torch.randn(RES[0] * RES[1] * RES[2], 3, dtype=dtype)
    x = points(30, dtype)
    got = trilinear(table.to(device), RES, x.to(device)).cpu()
    torch.testing.assert_close(got, trilinear_loop(table, RES, x), **tol(dtype))


@pytest.mark.parametrize("channels", [1, 3])
def test_gather_gradients_match_dense_products(device, tol, channels):
    """The gather's backward (per channel on the CPU, one ``index_add_`` elsewhere) against autograd through plain
    indexing, values and gradients."""
    g = torch.Generator().manual_seed(5)
    table = torch.randn(RES[0] * RES[1] * RES[2], channels, generator=g).to(device)
    idx, w = trilinear_corners(points(40, torch.float32).to(device), RES)
    coef = torch.randn(40, channels, generator=g).to(device)
    t1, w1 = table.clone().requires_grad_(), w.clone().requires_grad_()
    (grid_gather(t1, idx, w1) * coef).sum().backward()
    t2, w2 = table.clone().requires_grad_(), w.clone().requires_grad_()
    ((w2[:, :, None] * t2[idx]).sum(1) * coef).sum().backward()
    torch.testing.assert_close(t1.grad, t2.grad, **tol(torch.float32))
    torch.testing.assert_close(w1.grad, w2.grad, **tol(torch.float32))


@pytest.mark.parametrize("channels", [1, 4])
def test_both_weight_gradient_routes_agree(device, tol, channels):
    """The batched product (the CPU's route) and the product-and-sum (CUDA's route) of the gather's backward into
    the weights, on the same device: the route is chosen by device, so each is tested here on both."""
    g = torch.Generator().manual_seed(6)
    rows, v = torch.randn(50, 8, channels, generator=g).to(device), torch.randn(50, channels, generator=g).to(device)
    for batched in (True, False):
        torch.testing.assert_close(row_dot(rows, v, batched), (rows * v[:, None, :]).sum(-1), **tol(torch.float32))


@pytest.mark.parametrize("channels", [1, 4])
def test_both_table_gradient_routes_agree(device, tol, channels):
    """The ``scatter_add_`` per channel (the CPU's route) and ``index_add_`` (elsewhere) of the gather's backward
    into the table, on the same device, with repeated rows and int32 / int64 indices: the same values, bit for bit on
    the CPU (both add in the corners' order; CUDA's atomic adds have no fixed order)."""
    from nerfpipe.functional.gather import table_grad

    g = torch.Generator().manual_seed(8)
    for dtype in (torch.float32, torch.float64):
        table = torch.randn(40, channels, generator=g, dtype=dtype).to(device)
        idx = torch.randint(0, 40, (300, 8), generator=g).to(device)
        idx[:5] = 7  # a row many corners share
        w, grad_out = torch.rand(300, 8, generator=g, dtype=dtype).to(device), torch.randn(300, channels, generator=g, dtype=dtype).to(device)
        ref = torch.zeros_like(table).index_put_((idx.reshape(-1),), (w[:, :, None] * grad_out[:, None, :]).reshape(-1, channels), accumulate=True)
        for index in (idx, idx.int()):
            scattered, added = (table_grad(table, index, w, grad_out, per_channel=c) for c in (True, False))
            assert scattered.dtype == added.dtype == dtype and scattered.shape == table.shape
            if device.type == "cpu":
                assert torch.equal(scattered, added)
            torch.testing.assert_close(scattered, ref, **tol(dtype))
            torch.testing.assert_close(added, ref, **tol(dtype))


@pytest.mark.parametrize("corners", [4, 8])
def test_gather_forward_matches_indexing(device, dtype, tol, corners):
    """The forward (``embedding_bag``'s weighted sum on the CPU, a gather and a contraction elsewhere) against plain
    indexing, with repeated rows, int32 and int64 indices, and no points at all."""
    g = torch.Generator().manual_seed(7)
    table = torch.randn(30, 3, generator=g, dtype=dtype).to(device)
    idx = torch.randint(0, 30, (64, corners), generator=g).to(device)
    idx[0] = 5  # one row taken by every corner
    w = torch.rand(64, corners, generator=g, dtype=dtype).to(device)
    ref = (w[:, :, None] * table[idx]).sum(1)
    for index in (idx, idx.int()):
        torch.testing.assert_close(gather_rows_sum(table, index, w), ref, **tol(dtype))
    wide = torch.cat([table, table], dim=1)[:, 2:5]  # a strided view, as a slice of a larger table is
    torch.testing.assert_close(gather_rows_sum(wide, idx.t().contiguous().t(), w), (w[:, :, None] * wide[idx]).sum(1), **tol(dtype))
    assert gather_rows_sum(table, idx[:0], w[:0]).shape == (0, 3)


def test_trilinear_matches_grid_sample(tol):
    dtype = torch.float64
    table = torch.randn(RES[0] * RES[1] * RES[2], 2, dtype=dtype)
    x = points(50, dtype).clamp(0, 1)
    vol = table.view(*RES, 2).permute(3, 2, 1, 0)[None]  # [1, C, rz, ry, rx]
    ref = F.grid_sample(vol, (x * 2 - 1)[None, None, None], align_corners=True)[0, :, 0, 0].T
    torch.testing.assert_close(trilinear(table, RES, x), ref, **tol(dtype))


def test_gather_gradcheck_float64():
    table = torch.randn(RES[0] * RES[1] * RES[2], 2, dtype=torch.float64, requires_grad=True)
    idx, w = trilinear_corners(points(7, torch.float64), RES)
    w = w.clone().requires_grad_()
    assert torch.autograd.gradcheck(grid_gather, (table, idx, w))


def test_encoding_shapes_and_vertex_values():
    enc = DenseGridEncoding([(3, 3, 3), (5, 5, 5)], channels=2)
    x = torch.rand(10, 3)
    assert enc(x).shape == (10, 4) and enc.summed(x).shape == (10, 2)
    with torch.no_grad():
        enc.tables[1].copy_(torch.arange(125 * 2, dtype=torch.float32).view(125, 2))
    vertex = torch.tensor([[0.25, 0.5, 1.0]])  # vertex (1, 2, 4) of the 5^3 level
    assert enc(vertex)[0, 2:].tolist() == [2.0 * ((1 * 5 + 2) * 5 + 4), 2.0 * ((1 * 5 + 2) * 5 + 4) + 1]


def info(**kw):
    base = dict(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), near=0.5, far=6.0, num_images=10, pixels_per_image=1024)
    return SceneInfo(**{**base, **kw})


TINY = dict(levels=(8, 16), feature_channels=2, hidden=16, occupancy=OccupancyGridConfig(resolution=16, warmup_steps=2, update_every=2))


def test_hashed_corners_match_the_one_vertex_reference():
    res, rows = (40, 33, 50), 256  # 66,000 vertices in 256 rows
    x = points(40, torch.float64)
    idx, w = trilinear_corners(x, res, rows)
    pos = x.clamp(0, 1) * (torch.tensor(res, dtype=x.dtype) - 1)
    lo = torch.minimum(pos.floor(), torch.tensor(res, dtype=x.dtype) - 2).long()
    corners = [(di, dj, dk) for di in (0, 1) for dj in (0, 1) for dk in (0, 1)]
    ref = [[hashed_row_reference(int(i) + di, int(j) + dj, int(k) + dk, rows) for di, dj, dk in corners] for i, j, k in lo.tolist()]
    assert idx.tolist() == ref and int(idx.max()) < rows
    torch.testing.assert_close(w, trilinear_corners(x, res)[1])  # the weights do not depend on the storage
    table = torch.randn(rows, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(grid_gather, (table, idx[:6], w[:6].clone().requires_grad_()))


@pytest.mark.parametrize("rows", [2**4, 2**20, 2**31])
def test_hashed_rows_per_axis_in_32_bits_equal_the_64_bit_broadcast(device, rows):
    """The CPU's route to the hashed rows (per-axis products in wrapping 32-bit integers) gives the 64-bit broadcast's
    rows bit for bit, where the products overflow 32 bits too (coordinates up to 8,191: their products with the
    primes need 45 bits), and the one-vertex reference's on a sample."""
    from nerfpipe.fields.grid import hashed_rows, hashed_rows_per_axis

    g = torch.Generator().manual_seed(0)
    lo = torch.cat([torch.randint(0, 8192, (2, 500, 3), generator=g), torch.tensor([[[0, 0, 0], [8191, 8191, 8191]]] * 2)], 1).to(device)
    fast = hashed_rows_per_axis(lo.float(), rows)
    assert fast.dtype == (torch.int32 if rows <= 1 << 31 else torch.long)
    assert torch.equal(fast.long(), hashed_rows(lo, rows)) and int(fast.max()) < rows
    corners = [(di, dj, dk) for di in (0, 1) for dj in (0, 1) for dk in (0, 1)]
    for (i, j, k), got in zip(lo[1, -20:].tolist(), fast[1, -20:].tolist()):
        assert got == [hashed_row_reference(i + di, j + dj, k + dk, rows) for di, dj, dk in corners]


def test_corners_of_several_levels_at_once_equal_each_levels_own(device):
    """The batched corners (one pass for the dense levels, one for the hashed ones) are each level's
    :func:`trilinear_corners`, bit for bit, and in fewer tensor operations."""
    from nerfpipe.training.opcount import DispatchCounter

    enc = DenseGridEncoding([(4, 5, 6), (8, 8, 9), (16, 12, 16), (33, 20, 31)], channels=2, max_rows=1024).to(device)
    assert enc.hash_rows == [None, None, 1024, 1024]
    x, x_lat = points(50, torch.float32).to(device), points(50, torch.float32).to(device) * 1.1 - 0.05
    got = enc.corners_of(4, x, x_lat)
    want = [enc.corners(lv, x if enc.hash_rows[lv] is None else x_lat) for lv in range(4)]
    for (gi, gw), (wi, ww) in zip(got, want, strict=True):
        assert torch.equal(gi, wi) and torch.equal(gw, ww)
    assert [len(c) for c in enc.corners_of(3, x, x_lat)] == [2, 2, 2]
    enc.corners_of(4, x, x_lat), enc.corners(0, x)  # constants built
    with DispatchCounter() as batched:
        enc.corners_of(4, x, x_lat)
    with DispatchCounter() as each:
        [enc.corners(lv, x) for lv in range(4)]
    assert batched.ops < 0.7 * each.ops, (batched.ops, each.ops)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_direction_encoding_matches_the_written_out_harmonics_values_and_gradients(dtype, device):
    from nerfpipe.fields.fast_field import direction_encoding, direction_encoding_reference

    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=dtype), dim=-1)
    d = torch.cat([d, torch.eye(3, dtype=dtype), -torch.eye(3, dtype=dtype)]).to(device).requires_grad_()  # the poles too
    got, want = direction_encoding(d), direction_encoding_reference(d)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(got, want, rtol=tol, atol=tol)
    up = torch.randn(got.shape, generator=g, dtype=dtype).to(device)
    (ga,), (gb,) = torch.autograd.grad(got, d, up), torch.autograd.grad(want, d, up)
    torch.testing.assert_close(ga, gb, rtol=10 * tol, atol=10 * tol)
    # orthonormal on the sphere: the mean of Y_i Y_j over many directions is delta_ij / (4 pi)
    many = torch.nn.functional.normalize(torch.randn(200_000, 3, generator=g, dtype=torch.float64), dim=-1)
    gram = direction_encoding(many).T @ direction_encoding(many) / len(many) * 4 * torch.pi
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


def test_levels_hash_only_above_the_row_budget():
    enc = DenseGridEncoding([(4, 4, 4), (8, 8, 8), (16, 16, 16)], channels=3, max_rows=512)
    assert enc.hash_rows == [None, None, 512] and [t.shape[0] for t in enc.tables] == [64, 512, 512]
    assert enc(torch.rand(5, 3)).shape == (5, 9)
    with pytest.raises(ValueError, match="power of two"):
        DenseGridEncoding([(4, 4, 4)], channels=1, max_rows=100)


def test_compact_capacity_resolves_a_pixel_and_bounds_memory():
    lego200 = info(num_images=100, pixels_per_image=200 * 200, pixel_footprint=2.0 / 200)
    cap = compact_capacity(lego200)  # box side 2: a pixel is 1/200 of it
    assert cap["levels"][0] == 32 and cap["levels"][-1] == 200 and len(cap["levels"]) <= MAX_LEVELS
    assert list(cap["levels"]) == sorted(cap["levels"]) and cap["log2_hashmap_size"] == 17
    model = FastConfig(preset="compact").setup(lego200)
    rows = sum(t.shape[0] for t in model.field.density_grid.tables)
    assert rows <= 32**3 + 3 * 2**17 and model.stats()["model_mb"] < 9  # dense, it would be 200^3 vertices
    assert model.stats()["finest_voxel"] == pytest.approx(2.0 / 199)
    big = compact_capacity(info(num_images=300, pixels_per_image=800 * 800, pixel_footprint=2.0 / 5000, unbounded=True))
    assert big["levels"] == (32, 64, 128, 256) and big["levels"][-1] == MAX_FINEST and big["log2_hashmap_size"] == 19
    assert "spacing" not in big  # a real capture: the held-out views gain nothing finer
    bounded = compact_capacity(info(num_images=300, pixels_per_image=800 * 800, pixel_footprint=2.0 / 5000))
    assert bounded["levels"] == (32, 64, 128, 256, MAX_FINEST_BOUNDED) and bounded["spacing"] == MAX_FINEST
    assert bounded["log2_hashmap_size"] == 19 and bounded["log2_fine_hashmap_size"] == 20  # pixels / 32 = 2^22.9
    assert big["log2_fine_hashmap_size"] is None  # a real capture's tables stay at 2^19
    fewer = compact_capacity(info(num_images=20, pixels_per_image=800 * 800, pixel_footprint=2.0 / 5000))  # 2^18.6 rows asked
    assert fewer["levels"][-1] == MAX_FINEST_BOUNDED and fewer["log2_fine_hashmap_size"] is None
    assert "spacing" not in compact_capacity(info(num_images=300, pixels_per_image=800 * 800, pixel_footprint=2.0 / 300))
    unknown = compact_capacity(info(num_images=10, pixels_per_image=300 * 300))  # no cameras: the image's side
    assert unknown["levels"][-1] == min(300, MAX_FINEST) and unknown["log2_hashmap_size"] == 17


def test_the_finest_hashed_levels_get_their_own_rows_and_old_runs_keep_theirs():
    """Hashed levels of more than ``fine_min_vertices`` vertices take ``fine_rows`` rows (the 800² stand-in's 256- and
    512-levels, where its occupied cells hold more vertices than 2^19 rows), the others ``max_rows``; a run written
    before the option loads with the rows it trained with."""
    from nerfpipe.models.fast import FINE_HASH_VERTICES, LOG2_FINE_ROWS_BOUNDED

    enc = DenseGridEncoding([(4, 5, 6), (8, 8, 9), (16, 12, 16), (33, 20, 31)], channels=2, max_rows=1024, fine_rows=4096,
                            fine_min_vertices=16 * 12 * 16)
    assert enc.hash_rows == [None, None, 1024, 4096] and [t.shape[0] for t in enc.tables] == [120, 576, 1024, 4096]
    with pytest.raises(ValueError, match="power of two"):
        DenseGridEncoding([(4, 4, 4)], channels=1, max_rows=64, fine_rows=100)
    lego800 = info(num_images=88, pixels_per_image=800 * 800, pixel_footprint=2.0 / 1600)
    model = FastConfig(preset="compact").setup(lego800)
    rows = model.field.density_grid.hash_rows
    big = [math.prod(r) > FINE_HASH_VERTICES for r in model.field.density_grid.resolutions]
    assert rows == [None, None, 2**19, 2**LOG2_FINE_ROWS_BOUNDED, 2**LOG2_FINE_ROWS_BOUNDED] and big == [False, False, False, True, True]
    assert model.field.feature_grid.hash_rows == rows
    off = FastConfig(preset="compact", log2_fine_hashmap_size=0).setup(lego800)  # what an old run's config resolves to
    assert off.capacity["log2_fine_hashmap_size"] is None and off.field.density_grid.hash_rows == [None, None] + [2**19] * 3
    stored = {"preset": "compact"}
    from nerfpipe.training.runs import _options_since

    _options_since(FastConfig, stored)
    assert stored["log2_fine_hashmap_size"] == 0
    assert FastConfig(preset="small").setup(info()).capacity["log2_fine_hashmap_size"] is None


def test_tighten_keeps_hashed_levels_and_checkpoints_round_trip():
    cfg = FastConfig(levels=(8, 40), feature_channels=2, hidden=8, log2_hashmap_size=10, coarse_to_fine_every=0,
                     occupancy=OccupancyGridConfig(resolution=16))
    model = cfg.setup(info())
    assert model.field.density_grid.hash_rows == [None, 1024]
    with torch.no_grad():
        model.field.density_grid.tables[1].normal_()
        model.grid.binary.zero_()
        model.grid.binary.view(16, 16, 16)[4:12, 6:10, 2:14] = True
    probe = torch.rand(100, 3) * 0.5 - 0.25
    before = model.field.density(probe)
    step = model.step_size
    model.grid.update = lambda *a, **k: None
    model.tighten()
    assert (model.field.aabb[1] - model.field.aabb[0] < 2.0).all()
    assert model.field.density_grid.resolutions[1] == (40, 40, 40) and model.step_size == pytest.approx(step)
    torch.testing.assert_close(model.field.density(probe), before, rtol=1e-5, atol=1e-5)  # level 0 is constant
    fresh = cfg.setup(info())
    fresh.load_state_dict(model.state_dict())
    torch.testing.assert_close(fresh.field.density(probe), before, rtol=1e-5, atol=1e-5)


def test_capacity_follows_the_scene():
    assert auto_preset(info(num_images=100, pixels_per_image=200 * 200)) == "small"
    assert auto_preset(info(num_images=100, pixels_per_image=400 * 400)) == "medium"
    assert auto_preset(info(num_images=300, pixels_per_image=800 * 800)) == "compact"  # where large would be
    assert FastConfig().setup(info()).field.density_grid.hash_rows == [None, None, None]  # auto: dense
    model = FastConfig(preset="small", levels=(8, 12)).setup(info())
    assert model.capacity["preset"] == "small" and [r[0] for r in model.field.density_grid.resolutions] == [8, 12]
    with pytest.raises(ValueError, match="unknown preset"):
        FastConfig(preset="huge").setup(info())


def test_adams_second_moment_decay_follows_the_scene():
    """instant-ngp's 0.99 on bounded scenes, torch's 0.999 for real captures, in every parameter group; refused outside [0, 1)."""
    from nerfpipe.models.fast import ADAM_BETA2, ADAM_BETA2_REAL

    bounded = FastConfig(**TINY).setup(info())
    real = FastConfig(**TINY, background_field=False).setup(info(unbounded=True))
    assert (ADAM_BETA2, ADAM_BETA2_REAL) == (0.99, 0.999)
    assert {g["betas"] for g in bounded.param_groups()} == {(0.9, ADAM_BETA2)}
    assert {g["betas"] for g in real.param_groups()} == {(0.9, ADAM_BETA2_REAL)}
    given = FastConfig(**TINY, adam_beta2=0.95).setup(info(unbounded=True))
    assert {g["betas"] for g in given.param_groups(4096)} == {(0.9, 0.95)}
    opt = torch.optim.Adam(bounded.param_groups(4096))  # what the trainer builds: the groups' own betas win
    assert {g["betas"] for g in opt.param_groups} == {(0.9, ADAM_BETA2)}
    with pytest.raises(ValueError, match="adam_beta2"):
        FastConfig(adam_beta2=1.0)


def test_a_presets_spacing_level_sets_the_sample_spacing():
    """``medium``'s hashed finest level (256) keeps the sample spacing of the dense 192 it replaced: with every level on,
    its samples are as far apart as the old preset's (and as ``step_ratio`` says in 192-level voxels); levels of one's
    own count the spacing in their own finest voxel."""
    model = FastConfig(preset="medium").setup(info())
    assert model.capacity["levels"][-1] == 256 and model.capacity["spacing"] == 192
    assert model.field.density_grid.hash_rows[-1] == 2**19 and model.field.density_grid.hash_rows[0] is None
    old = FastConfig(preset="medium", levels=(32, 64, 128, 192), log2_hashmap_size=0).setup(info())  # the former dense medium
    assert old.capacity["spacing"] is None and old.field.density_grid.hash_rows == [None] * 4
    for m in (model, old):
        m.field.active_levels = 4
    assert model.step_size == pytest.approx(old.step_size, rel=1e-6)
    assert model.stats()["model_mb"] < old.stats()["model_mb"] / 3


def test_a_bounded_scenes_finer_level_keeps_the_sample_spacing():
    """A bounded scene whose pixels ask for more than :data:`MAX_FINEST` gets a hashed level of
    :data:`MAX_FINEST_BOUNDED` whose samples, with every level on, lie as far apart as the 256-level's would, and twice
    the model's memory at most; ``spacing`` overrides the level the spacing is counted in."""
    from nerfpipe.models.fast import LOG2_FINE_ROWS_BOUNDED

    scene = info(num_images=300, pixels_per_image=800 * 800, pixel_footprint=2.0 / 800)
    model, plain = FastConfig(preset="compact").setup(scene), FastConfig(preset="compact", levels=(32, 64, 128, 256)).setup(scene)
    assert model.capacity["levels"][-1] == MAX_FINEST_BOUNDED and model.capacity["spacing"] == MAX_FINEST
    assert model.field.density_grid.hash_rows[-2:] == [2**LOG2_FINE_ROWS_BOUNDED] * 2  # its pixels ask for large tables
    model.field.active_levels, plain.field.active_levels = 5, 4
    assert model.step_size == pytest.approx(plain.step_size, rel=1e-6)
    assert model.stats()["finest_voxel"] == pytest.approx(2.0 / (MAX_FINEST_BOUNDED - 1))
    assert model.stats()["model_mb"] < 2 * plain.stats()["model_mb"]
    own = FastConfig(preset="compact", levels=(32, 64, 128, 256), spacing=128).setup(scene)
    own.field.active_levels = 4
    assert own.capacity["spacing"] == 128 and own.step_size == pytest.approx(plain.step_size * 255 / 127, rel=1e-6)


def test_a_checkpoint_of_the_former_dense_medium_still_loads():
    """Runs written before ``medium`` hashed its finest level load with the capacity they were trained with (their
    config.json says only ``auto`` or ``medium``); a checkpoint of today's medium keeps today's."""
    from nerfpipe.models.fast import LEGACY_CAPACITY

    cfg = FastConfig(preset="medium")
    old = replace(cfg, **LEGACY_CAPACITY["medium"]).setup(info())
    with torch.no_grad():
        old.field.density_grid.tables[3].normal_()
    state = old.state_dict()
    fitted = cfg.for_checkpoint(state, info())
    assert fitted.levels == (32, 64, 128, 192) and not fitted.log2_hashmap_size
    model = fitted.setup(info())
    model.load_state_dict(state)
    probe = torch.rand(50, 3) - 0.5
    torch.testing.assert_close(model.field.density(probe), old.field.density(probe))
    assert cfg.for_checkpoint(cfg.setup(info()).state_dict(), info()) is cfg
    with pytest.raises(RuntimeError):  # without it, the former checkpoint does not fit today's medium
        cfg.setup(info()).load_state_dict(state)


def test_tighten_resamples_a_linear_field_exactly():
    model = FastConfig(**TINY).setup(info())
    table = model.field.density_grid.tables[1]
    res = model.field.density_grid.resolutions[1]
    with torch.no_grad():  # a linear function of position: trilinear resampling reproduces it
        ijk = torch.stack(torch.meshgrid(*[torch.arange(r) for r in res], indexing="ij"), -1).reshape(-1, 3).float()
        xyz = -1 + 2 * ijk / (torch.tensor(res) - 1)
        table.copy_((xyz @ torch.tensor([0.3, -0.2, 0.1]))[:, None])
        model.grid.binary.zero_()
        model.grid.binary.view(16, 16, 16)[4:12, 6:10, 2:14] = True
    probe = torch.rand(100, 3) * 0.5 - 0.25
    before = model.field.density(probe)
    model.grid.update = lambda *a, **k: None  # keep the hand-made occupancy
    model.tighten()
    box = model.field.aabb
    assert (box[1] - box[0] < 2.0).all() and (box[0] <= -0.25).all() and (box[1] >= 0.25).all()
    torch.testing.assert_close(model.field.density(probe), before, rtol=1e-4, atol=1e-4)
    # a fresh model accepts the resized checkpoint
    fresh = FastConfig(**TINY).setup(info())
    fresh.load_state_dict(model.state_dict())
    torch.testing.assert_close(fresh.field.density(probe), before, rtol=1e-4, atol=1e-4)


def test_coarse_to_fine_levels_survive_a_checkpoint():
    cfg = FastConfig(levels=(4, 8, 16), feature_channels=2, hidden=8, coarse_to_fine_every=10, tighten_step=0)
    model = cfg.setup(info())
    probe = torch.rand(20, 3) - 0.5
    with torch.no_grad():
        model.field.density_grid.tables[2].normal_()
    coarse = model.field.density(probe)
    model._before_step(25)  # third level switched on
    assert model.field.active_levels == 3
    fine = model.field.density(probe)
    assert not torch.allclose(coarse, fine)
    fresh = cfg.setup(info())
    assert fresh.field.active_levels == 2
    fresh.load_state_dict(model.state_dict())
    assert fresh.field.active_levels == 3
    torch.testing.assert_close(fresh.field.density(probe), fine)


def test_sample_spacing_refines_on_schedule_and_survives_a_checkpoint():
    cfg = FastConfig(levels=(8, 16), feature_channels=2, hidden=8, step_ratio=0.5, early_step_ratio=1.0,
                     fine_steps_from=30, coarse_to_fine_every=0, tighten_step=0)
    model = cfg.setup(info())
    early = model.step_size
    model._before_step(29)
    assert model.step_size == early
    model._before_step(30)
    assert model.step_size == pytest.approx(early / 2)
    fresh = cfg.setup(info())
    assert fresh.step_size == pytest.approx(early)
    fresh.load_state_dict(model.state_dict())
    assert fresh.step_size == pytest.approx(early / 2)
    # a checkpoint written before the step count was saved was trained with the fine spacing
    old = {k: v for k, v in model.state_dict().items() if k != "trained_steps"}
    older = cfg.setup(info())
    older.load_state_dict(old)
    assert older.step_size == pytest.approx(early / 2)


def test_render_outputs_and_stats():
    model = FastConfig(**TINY).setup(info())
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    rays = RayBundle(o, d, torch.zeros(2, dtype=torch.long), torch.ones(2))
    out = model.get_outputs(rays, torch.tensor([[0.2, 0.4, 0.6]]).expand(2, 3))
    assert out.rgb.shape == (2, 3) and out.num_samples > 0
    torch.testing.assert_close(out.rgb[1], torch.tensor([0.2, 0.4, 0.6]))  # misses the box: background
    stats = model.stats()
    for key in ("model_params", "model_mb", "occupied_fraction", "samples_per_ray"):
        assert key in stats


SIZE = 24


@pytest.fixture(scope="module")
def tiny_scene(scene_path, tmp_path_factory):
    src = np.load(scene_path("lego_200x200") / "lego_200x200.npz")
    shrink = lambda im: F.interpolate(torch.from_numpy(im).permute(0, 3, 1, 2).float(), size=(SIZE, SIZE), mode="area").round().byte().permute(0, 2, 3, 1).numpy()  # noqa: E731
    out = tmp_path_factory.mktemp("tiny_fast") / "tiny_lego.npz"
    np.savez(out, images_train=shrink(src["images_train"][::4]), c2ws_train=src["c2ws_train"][::4],
             images_val=shrink(src["images_val"][:2]), c2ws_val=src["c2ws_val"][:2], c2ws_test=src["c2ws_test"][:2],
             focal=np.float64(src["focal"]) * SIZE / 200)
    return load(out)


def test_tiny_training_run_learns(tiny_scene, tmp_path):
    model = FastConfig(levels=(12, 24), feature_channels=2, hidden=16, step_ratio=1.0, tighten_step=20,
                       occupancy=OccupancyGridConfig(resolution=24, warmup_steps=4, update_every=4))
    cfg = TrainerConfig(iters=30, rays_per_step=512, eval_every=30, video_frames=0, checkpoint_every=0, seed=0)
    trainer = Trainer(cfg, tiny_scene, "fast", model, tmp_path)
    metrics = trainer.train()
    val = trainer.history["val"]
    assert val[-1][2] > val[0][2] + 5.0, val  # well above the untrained start
    assert 0 < metrics["occupied_fraction"] < 1
    assert metrics["samples_per_ray"] > 0
    assert trainer.optimizer.param_groups[0]["lr"] < model.grid_lr  # the model's schedule reached the optimiser


def test_resume_keeps_the_learning_rate_schedule(tiny_scene, tmp_path, device):
    """Loading a checkpoint replaces the optimiser's group dicts; the schedule must still reach them. On CUDA the
    model's random stream is a CUDA generator, saved with the checkpoint: the continuation is as exact once CUDA's
    atomic adds are made deterministic (without, two straight H100 runs already differ by ~5e-6)."""
    was = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        _resume_keeps_the_learning_rate_schedule(tiny_scene, tmp_path, device)
    finally:
        torch.use_deterministic_algorithms(was[0], warn_only=was[1])


def _resume_keeps_the_learning_rate_schedule(tiny_scene, tmp_path, device):
    model = FastConfig(levels=(12, 24), feature_channels=2, hidden=16, step_ratio=1.0, tighten_step=6, lr_decay_steps=4,
                       occupancy=OccupancyGridConfig(resolution=24, warmup_steps=2, update_every=2))
    # eager steps: a resumed run warms the CUDA graph up where a straight one replays it, and the two round differently
    # (test_cuda_graph.py resumes a graphed run)
    base = dict(iters=10, rays_per_step=256, eval_every=0, video_frames=0, checkpoint_every=0, seed=0, write_outputs=False, device=str(device),
                cuda_graph=False)
    cfg = lambda **kw: TrainerConfig(**{**base, **kw})  # noqa: E731
    straight = Trainer(cfg(), tiny_scene, "fast", model, tmp_path / "straight")
    straight.train()
    Trainer(cfg(iters=5), tiny_scene, "fast", model, tmp_path / "split").train()
    resumed = Trainer(cfg(resume=True), tiny_scene, "fast", model, tmp_path / "split")
    resumed.train()
    assert resumed.step == 10
    lrs = [g["lr"] for g in resumed.optimizer.param_groups]
    assert lrs == [g["lr"] for g in straight.optimizer.param_groups]
    assert lrs[0] == pytest.approx(model.grid_lr * max(model.lr_min_factor, 0.1 ** (9 / 4)))
    a, b = straight.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)  # bit-identical continuation across the box tightening


def test_briefly_trained_model_renders_the_same_with_early_termination(tiny_scene, tmp_path):
    """The density pass in rounds (early termination) keeps the full pass's samples on a trained field."""
    from nerfpipe.data.rays import camera_rays
    from nerfpipe.outputs.render import render_cameras

    model_cfg = FastConfig(levels=(12, 24), feature_channels=2, hidden=16, step_ratio=1.0, tighten_step=8, min_transmittance=0.3,
                           occupancy=OccupancyGridConfig(resolution=24, warmup_steps=2, update_every=2))  # rays terminate soon
    cfg = TrainerConfig(iters=12, rays_per_step=512, eval_every=0, video_frames=0, checkpoint_every=0, seed=0, write_outputs=False,
                        device="cpu")  # the rays below are built on the host (test_early_termination covers CUDA)
    trainer = Trainer(cfg, tiny_scene, "fast", model_cfg, tmp_path)
    for _ in range(cfg.iters):
        trainer.train_step()
    model, cams = trainer.model.eval(), tiny_scene.cameras[:3]
    evaluated, samples, views = {}, {}, {}
    for early in (True, False):
        model.cfg.early_termination = early
        with torch.no_grad():
            counted = []
            model.field.density = lambda p, f=model.field.density: counted.append(len(p)) or f(p)  # noqa: E731
            samples[early], _ = model._samples(camera_rays(cams, 0).reshape(-1))
            del model.field.density
        evaluated[early] = sum(counted)
        views[early] = render_cameras(model, cams)
    assert len(samples[True]) > 0 and evaluated[True] < evaluated[False]  # some rays did terminate
    for key in ("ray_indices", "t_starts", "t_ends"):
        assert torch.equal(getattr(samples[True], key), getattr(samples[False], key))
    for a, b in zip(views[True], views[False]):
        for key in ("rgb", "depth", "acc"):
            torch.testing.assert_close(getattr(a, key), getattr(b, key), rtol=1e-6, atol=1e-6)


def test_voxel_size_is_read_once_per_box_and_follows_a_new_box():
    """The voxel size is cached per box (a host read on CUDA each time otherwise) and recomputed when the box changes."""
    from nerfpipe.fields.fast_field import FastField
    from nerfpipe.training.opcount import DispatchCounter

    field = FastField(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), [(9, 9, 9), (17, 17, 5)])
    direct = lambda level: float(((field.aabb[1] - field.aabb[0]) / (torch.tensor(field.density_grid.resolutions[level]) - 1.0)).min())  # noqa: E731
    assert field.voxel_size(1) == direct(1) == 0.125
    with DispatchCounter() as c:
        field.voxel_size(1)
    assert c.ops == 0
    field.aabb.copy_(torch.tensor([[-1.0, -1.0, -1.0], [0.0, 1.0, 1.0]]))  # a tightened box
    assert field.voxel_size(1) == direct(1) == 0.0625 and field.voxel_size(0) == direct(0)


def test_both_trilinear_weight_routes_agree_bit_for_bit(device):
    """The per-axis products (the CPU's route) and the broadcast products (other devices') of the trilinear weights:
    chosen by device, so each is tested on every device."""
    from nerfpipe.fields.grid import trilinear_weights

    frac = torch.rand(3, 200, 3, generator=torch.Generator().manual_seed(9)).to(device)
    a, b = trilinear_weights(frac, per_axis=True), trilinear_weights(frac, per_axis=False)
    assert torch.equal(a, b)
    torch.testing.assert_close(a.sum(-1), torch.ones(3, 200, device=device))
    # weights that need gradients (camera refinement): the same values, differentiable (the per-axis route writes into
    # a buffer, which autograd cannot follow)
    x = frac[:, :5].double().requires_grad_()
    assert torch.equal(trilinear_weights(x, per_axis=True), trilinear_weights(x.detach(), per_axis=True))
    assert torch.autograd.gradcheck(lambda t: trilinear_weights(t, per_axis=True), (x,))


def test_learning_rates_fall_tenfold_over_the_steps_the_scene_type_asks_for():
    """Bounded scenes decay over LR_DECAY_STEPS, real captures over LR_DECAY_STEPS_REAL, an explicit value wins; the
    factor is exponential and floored."""
    cfg = FastConfig(preset="small")
    bounded = cfg.setup(info())
    real = cfg.setup(info(unbounded=True))
    assert (bounded.lr_decay_steps, real.lr_decay_steps) == (LR_DECAY_STEPS, LR_DECAY_STEPS_REAL)
    assert LR_DECAY_STEPS > LR_DECAY_STEPS_REAL
    assert bounded.lr_factor(0) == 1.0 and bounded.lr_factor(LR_DECAY_STEPS) == pytest.approx(0.1)
    assert real.lr_factor(LR_DECAY_STEPS_REAL // 2) == pytest.approx(0.1**0.5)
    assert bounded.lr_factor(100 * LR_DECAY_STEPS) == cfg.lr_min_factor
    assert replace(cfg, lr_decay_steps=700).setup(info()).lr_factor(700) == pytest.approx(0.1)
    assert replace(cfg, lr_decay_steps=0).setup(info(unbounded=True)).lr_factor(10**6) == 1.0
