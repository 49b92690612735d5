"""Early ray termination (density pass in rounds) against the full density pass it replaces: the same
kept samples on random fields with the hard cases (rays without samples, rays opaque at their first
sample, all-transparent rays, huge densities), fewer densities evaluated, and the fast model's
renders and gradients unchanged."""

import pytest
import torch

from nerfpipe.data.rays import RayBundle
from nerfpipe.estimators.occupancy import OccupancyGridConfig, PackedSamples, Rounds, ray_aabb_intersect
from nerfpipe.functional.packed import prune_mask
from nerfpipe.models.base import SceneInfo
from nerfpipe.models.fast import FastConfig

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RES = 8
STEP = 0.05
MIN_T = 1e-4


def rays(n, seed, device="cpu"):
    """Rays from a sphere of radius 3 towards the box; the last quarter aimed to miss it."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * 3
    target = (torch.rand(n, 3, generator=g) - 0.5) * 2.2
    target[3 * n // 4 :] = origins[3 * n // 4 :] * 2  # pointing away: no samples
    return origins.to(device), torch.nn.functional.normalize(target - origins, dim=-1).to(device)


def scene(seed, device="cpu"):
    """An occupancy grid and a density per cell: transparent (x < -0.5), huge (a few cells), random."""
    g = torch.Generator().manual_seed(seed)
    grid = OccupancyGridConfig(resolution=RES).setup(AABB)
    grid.binary.copy_(torch.rand(RES**3, generator=g) < 0.5)
    table = torch.rand(RES**3, generator=g) ** 3 * 40
    table[torch.rand(RES**3, generator=g) < 0.05] = 1e30
    centers = grid.cell_centers(jitter=False)
    table[centers[:, 0] < -0.5] = 0.0
    grid, table = grid.to(device), table.to(device)

    def density(points):
        idx, _ = grid.cell_index(points)
        return table[idx]

    return grid, density


class Counting:
    """``sigma_fn`` of packed samples from a density of points, counting the samples it sees."""

    def __init__(self, density, origins, directions) -> None:
        self.density, self.o, self.d, self.count = density, origins, directions, 0

    def __call__(self, samples: PackedSamples):
        self.count += len(samples)
        return self.density(samples.points(self.o, self.d))


def reference(grid, o, d, sigma_fn, min_alpha, jitter, seed):
    torch.manual_seed(seed)
    full = grid.march(o, d, 0.0, 10.0, STEP, jitter=jitter)
    sigma = sigma_fn(full)
    keep = prune_mask(sigma, full.t_ends - full.t_starts, full.ray_indices, MIN_T, min_alpha)
    return full, full.select(keep), sigma[keep]


def assert_same_samples(a: PackedSamples, b: PackedSamples) -> None:
    assert a.num_rays == b.num_rays
    assert torch.equal(a.ray_indices, b.ray_indices)
    assert torch.equal(a.t_starts, b.t_starts) and torch.equal(a.t_ends, b.t_ends)


ROUNDS = {
    "default": Rounds(), "small_chunked": Rounds(first=1, most=4, steps_per_sample=2, chunk_samples=64),
    "fixed_shapes": None,  # no rounds: every interval of the longest span at once (the sync-free path)
}


@pytest.mark.parametrize("rounds", ROUNDS.values(), ids=ROUNDS.keys())
@pytest.mark.parametrize("jitter", [False, True])
@pytest.mark.parametrize("min_alpha", [None, 1e-4])
def test_rounds_keep_exactly_the_reference_samples(rounds, jitter, min_alpha, device):
    grid, density = scene(seed=0, device=device)
    o, d = rays(400, seed=1, device=device)
    full, ref, ref_sigma = reference(grid, o, d, Counting(density, o, d), min_alpha, jitter, seed=2)
    torch.manual_seed(2)  # the same jitter
    got, sigma = grid.march_until_opaque(o, d, 0.0, 10.0, STEP, Counting(density, o, d), MIN_T, min_alpha, jitter=jitter, rounds=rounds,
                                         fixed_shapes=rounds is None)
    assert_same_samples(got, ref)
    assert torch.equal(sigma, ref_sigma)
    # the hard cases are present: rays without samples, opaque at their first sample, wholly transparent
    marched = torch.bincount(full.ray_indices, minlength=400)
    kept = torch.bincount(got.ray_indices, minlength=400)
    first = full.ray_indices.new_full((400,), -1).scatter_reduce(0, full.ray_indices, torch.arange(len(full), device=device), "amin", include_self=False)
    first_sigma = torch.where(first >= 0, density(full.points(o, d))[first.clamp(min=0)], 0.0)
    assert (marched == 0).sum() >= 50
    assert ((first_sigma == 1e30) & (kept == 1) & (marched > 1)).any()
    transparent = (marched > 0) & (torch.zeros(400, device=device).index_add_(0, full.ray_indices, density(full.points(o, d))) == 0)
    assert transparent.sum() >= 3
    assert (kept[transparent] == (0 if min_alpha is not None else marched[transparent])).all()


def test_rays_stop_within_one_round_of_termination():
    grid, density = scene(seed=3)
    o, d = rays(300, seed=4)
    full_fn, fast_fn = Counting(density, o, d), Counting(density, o, d)
    full, ref, _ = reference(grid, o, d, full_fn, None, False, seed=0)
    rounds = Rounds(first=2, most=4)
    got, _ = grid.march_until_opaque(o, d, 0.0, 10.0, STEP, fast_fn, MIN_T, None, rounds=rounds)
    assert_same_samples(got, ref)
    # without the alpha test the kept samples are every ray's samples up to its termination
    kept = torch.bincount(ref.ray_indices, minlength=300)
    assert fast_fn.count <= int((kept + rounds.most).clamp(max=torch.bincount(full.ray_indices, minlength=300)).sum())
    assert fast_fn.count < full_fn.count == len(full)


def test_no_rays_and_no_hits():
    grid, density = scene(seed=0)
    o, d = rays(8, seed=1)
    fn = Counting(density, o, d)
    for origins, directions in ((o[:0], d[:0]), (o, o / 3)):  # nothing, and every ray looking away
        t0, t1 = ray_aabb_intersect(origins, directions, AABB)
        assert not (t0.clamp(min=0) < t1).any()
        got, sigma = grid.march_until_opaque(origins, directions, 0.0, 10.0, STEP, fn, MIN_T)
        assert len(got) == 0 and sigma.shape == (0,) and got.num_rays == len(origins)
    assert fn.count == 0


# ---------------------------------------------------------------- the fast model on a trained-like field
INFO = SceneInfo(aabb=AABB, near=0.5, far=6.0, num_images=10, pixels_per_image=1024)


def solid_model(early: bool, seed: int = 0, fixed_shapes: bool = False):
    """A fast model whose density is a sphere of opaque matter with a fuzzy shell, grid refreshed from it."""
    cfg = FastConfig(levels=(8, 16), feature_channels=2, hidden=16, early_termination=early, fixed_shapes=fixed_shapes,
                     occupancy=OccupancyGridConfig(resolution=16, warmup_steps=16))
    torch.manual_seed(seed)
    model = cfg.setup(INFO)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for table, res in zip(model.field.density_grid.tables, model.field.density_grid.resolutions):
            ijk = torch.stack(torch.meshgrid(*[torch.arange(r) for r in res], indexing="ij"), -1).reshape(-1, 3).float()
            radius = (-1 + 2 * ijk / (torch.tensor(res) - 1)).norm(dim=-1)
            table.copy_(((0.7 - radius) * 60 + torch.randn(len(radius), generator=g))[:, None])
    model.grid.update(model.field.density, model.step_size)
    model.march_box.copy_(model.grid.occupied_aabb())
    return model


def camera_rays(n, seed):
    o, d = rays(n, seed)
    return RayBundle(o, d, torch.zeros(n, dtype=torch.long), torch.ones(n))


def test_model_renders_the_same_in_eval():
    fast, slow = solid_model(True), solid_model(False)
    fast.eval(), slow.eval()
    r, bg = camera_rays(256, seed=5), torch.tensor([0.2, 0.4, 0.6]).expand(256, 3)
    with torch.no_grad():
        (a, sa), (b, sb) = fast._samples(r), slow._samples(r)
        assert_same_samples(a, b)
        torch.testing.assert_close(sa, sb)
        oa, ob = fast.get_outputs(r, bg), slow.get_outputs(r, bg)
    for key in ("rgb", "depth", "acc"):
        torch.testing.assert_close(getattr(oa, key), getattr(ob, key), rtol=1e-6, atol=1e-6)
    assert (oa.acc > 0.999).sum() > 20 and (oa.acc == 0).sum() > 20 and ((oa.acc > 0.01) & (oa.acc < 0.99)).any()


@pytest.mark.parametrize("fast", ["rounds", "fixed_shapes"])
@pytest.mark.parametrize("step", [0, 40])  # during warm-up (no alpha test) and after
def test_model_training_outputs_and_gradients_unchanged(step, fast):
    models = [solid_model(True, fixed_shapes=fast == "fixed_shapes"), solid_model(False)]
    r, target = camera_rays(200, seed=6), torch.rand(200, 3, generator=torch.Generator().manual_seed(7))
    outs, grads = [], []
    for model in models:
        model.train()
        model._step = step
        torch.manual_seed(3)  # the same jitter for both
        out = model.get_outputs(r, torch.zeros(200, 3))
        sum(model.get_losses(out, target).values()).backward()
        outs.append(out)
        grads.append({n: p.grad for n, p in model.named_parameters() if p.grad is not None})
    assert outs[0].num_samples == outs[1].num_samples > 0
    for key in ("rgb", "depth", "acc"):
        torch.testing.assert_close(getattr(outs[0], key), getattr(outs[1], key), rtol=1e-6, atol=1e-6)
    assert grads[0].keys() == grads[1].keys() and len(grads[0]) > 0
    for name in grads[0]:
        torch.testing.assert_close(grads[0][name], grads[1][name], rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("step", [0, 40])
def test_sample_slots_render_and_train_as_the_packed_samples(step):
    """Occupied intervals and samples packed into more slots than they need (the padding adds nothing) give the same
    outputs and gradients as the step that reads their number back; into fewer, the counts say how many there were
    and only the last rays lose samples (fewer sample slots) or see intervals as empty (fewer interval slots)."""
    r, target = camera_rays(200, seed=6), torch.rand(200, 3, generator=torch.Generator().manual_seed(7))
    runs = []
    for slots in (None, "more", "fewer samples", "fewer intervals"):
        model = solid_model(True, fixed_shapes=True)
        model.train()
        model._step = step
        if slots is not None:
            n, m = runs[0][2]
            model.sample_capacity = {"more": (n + 777, m + 99), "fewer samples": (n // 2, m + 99), "fewer intervals": (n + 777, m // 2)}[slots]
        torch.manual_seed(3)
        out = model.get_outputs(r, torch.zeros(200, 3))
        sum(model.get_losses(out, target).values()).backward()
        runs.append((out, {n: p.grad for n, p in model.named_parameters() if p.grad is not None}, model.sample_count().tolist()))
    (ref, ref_grads, (n, m)), (more, grads, c_more), (fewer, _, c_fewer), (fewer_i, _, c_fewer_i) = runs
    assert n == ref.num_samples > 50 and m >= n and c_more == c_fewer == [n, m] and c_fewer_i[1] == m
    assert more.num_samples == n + 777 and fewer.num_samples == n // 2
    for key in ("rgb", "depth", "acc"):
        torch.testing.assert_close(getattr(more, key), getattr(ref, key), rtol=1e-6, atol=1e-6)
    for name in ref_grads:
        torch.testing.assert_close(grads[name], ref_grads[name], rtol=1e-5, atol=1e-9)
    for short in (fewer, fewer_i):
        changed = (short.acc != ref.acc).nonzero()[:, 0]
        assert len(changed) > 0 and changed.min() > 0  # the first rays keep theirs
