"""The error map: training rays drawn where the field is still wrong (tiles, capped weights, state, resume)."""

import pytest
import torch

from nerfpipe.training.pixel_sampler import ErrorMap, PixelSampler

# Two images whose sizes are not multiples of the tile (their last tiles are cut), flat pixels one after the other.
WIDTHS, HEIGHTS = torch.tensor([40, 33]), torch.tensor([20, 17])
OFFSETS = torch.tensor([0, 800, 800 + 33 * 17])


def small_map() -> ErrorMap:
    return ErrorMap(WIDTHS, HEIGHTS, OFFSETS, tiles=8)


def test_drawn_pixels_lie_in_their_tiles_and_cover_the_cut_tiles():
    m = small_map()
    assert m.tile == 13 and len(m.error) == 4 * 2 + 3 * 2  # ceil(40/13) x ceil(20/13), ceil(33/13) x ceil(17/13)
    idx, tiles = m.draw(60_000, torch.Generator().manual_seed(0))
    assert int(idx.min()) >= 0 and int(idx.max()) < int(OFFSETS[-1])
    cam = torch.searchsorted(OFFSETS, idx, right=True) - 1
    local = idx - OFFSETS[cam]
    assert torch.equal(m.tiles_of(cam, local % WIDTHS[cam], local // WIDTHS[cam]), tiles)
    assert torch.equal(torch.unique(idx), torch.arange(int(OFFSETS[-1])))  # every pixel, the cut tiles' too
    counts = torch.bincount(tiles, minlength=len(m.error)).float()
    assert float(counts.std() / counts.mean()) < 0.1  # an untouched map draws every tile alike


def test_weights_leave_what_is_learnt_and_are_even_over_the_rest():
    """Solved tiles are drawn in proportion to their error; tiles above the mean error no more than the mean
    (drawn in proportion to the error itself, rays crowd where the field cannot explain the photographs)."""
    m = small_map()
    n = len(m.error)
    errors = torch.full((n,), 0.01)
    errors[0], errors[1] = 0.0, 10.0  # tile 0 learnt, tile 1 unexplainable
    m.update(torch.arange(n), errors)
    assert float(m.mean) == pytest.approx(0.5 + 0.5 * float(errors.mean()))  # a running mean from 1
    m.update(torch.arange(n), errors)
    counts = torch.bincount(m.draw(200_000, torch.Generator().manual_seed(1))[1], minlength=n).float()
    rest = counts[2:]
    assert float(counts[0]) < 0.01 * float(rest.mean())  # the learnt tile is left (its error is clamped at 1e-6)
    assert float(counts[1]) < 1.1 * float(rest.max()) * float(m.mean) / 0.01  # capped at the mean error ...
    assert float(counts[1]) > 5 * float(rest.mean())  # ... which is still above the others'
    assert float(rest.std() / rest.mean()) < 0.1


def test_unvisited_tiles_count_the_mean_error_and_a_first_visit_sets_the_tile():
    m = small_map()
    m.update(torch.tensor([2, 2, 3]), torch.tensor([0.2, 0.4, 0.0]))
    assert float(m.error[2]) == pytest.approx(0.3) and float(m.error[3]) == pytest.approx(1e-6)
    assert m.visited.tolist() == [i in (2, 3) for i in range(len(m.error))]
    m.update(torch.tensor([2]), torch.tensor([0.1]))
    assert float(m.error[2]) == pytest.approx(0.3 + 0.5 * (0.1 - 0.3))  # later visits: a running mean
    counts = torch.bincount(m.draw(100_000, torch.Generator().manual_seed(2))[1], minlength=len(m.error)).float()
    unvisited = counts[[i for i in range(len(m.error)) if i not in (2, 3)]]
    assert float(unvisited.std() / unvisited.mean()) < 0.1 and float(counts[3]) == 0


def test_state_round_trip_and_a_map_of_other_images_is_refused():
    m = small_map()
    m.update(torch.tensor([1, 5]), torch.tensor([0.3, 0.05]))
    other = small_map()
    other.load_state(m.state())
    assert torch.equal(other.error, m.error) and torch.equal(other.visited, m.visited) and float(other.mean) == float(m.mean)
    g1, g2 = torch.Generator().manual_seed(4), torch.Generator().manual_seed(4)
    assert torch.equal(other.draw(100, g1)[0], m.draw(100, g2)[0])
    with pytest.raises(ValueError, match="tiles"):
        ErrorMap(WIDTHS, HEIGHTS, OFFSETS, tiles=40).load_state(m.state())


def test_sampler_draws_its_share_from_the_map_and_folds_the_errors_back(scene_path):
    from nerfpipe.data_adapters import load

    scene = load(scene_path("lego_200x200") / "lego_200x200.npz")
    sampler = PixelSampler(scene, "train", "black", error_share=0.75, error_tiles=4096)
    m = sampler.errors
    assert m is not None and m.tile == 31  # sqrt(100 images x 200 x 200 / 4096)
    first = torch.arange(int(m.tile_offsets[1]))  # the first image's tiles
    m.update(torch.arange(len(m.error)), torch.where(torch.isin(torch.arange(len(m.error)), first), 0.5, 0.0))
    batch = sampler.sample(4000, torch.Generator().manual_seed(0))
    tiles = sampler.last_tiles
    assert len(tiles) == len(batch.rgb) == 4000
    assert float((tiles[:3000] < len(first)).float().mean()) > 0.99  # the map's share: where the error is
    assert float((tiles[3000:] < len(first)).float().mean()) < 0.05  # the uniform rest: everywhere
    before = m.error[tiles[:3000]].clone()
    sampler.update_errors(torch.zeros(4000))
    after, floor = m.error[tiles[:3000]], before <= 1e-6  # a learnt tile is drawn now and then: it stays at the floor
    assert bool((after[~floor] < before[~floor]).all()) and bool((after[floor] == before[floor]).all())


def test_a_resumed_run_goes_on_with_its_error_map(scene_path, tmp_path):
    """The map is part of the checkpoint: a run resumed half way ends with the same map and model as one that was not."""
    from nerfpipe.data_adapters import load
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    scene = load(scene_path("lego_200x200") / "lego_200x200.npz")
    model = FastConfig(levels=(16, 32), tighten_step=0)
    cfg = dict(iters=6, rays_per_step=256, eval_every=0, checkpoint_every=3, video_frames=0, final_eval_views=1,
               write_outputs=False, num_threads=1, error_sampling=0.8, error_tiles=1024, device="cpu")  # bit-exact: the CPU
    straight = Trainer(TrainerConfig(**cfg), scene, "fast", model, tmp_path / "straight")
    straight.train()
    Trainer(TrainerConfig(**{**cfg, "iters": 3}), scene, "fast", model, tmp_path / "split").train()
    resumed = Trainer(TrainerConfig(**cfg, resume=True), scene, "fast", model, tmp_path / "split")
    resumed.train()
    m, r = straight.sampler.errors, resumed.sampler.errors
    assert m is not None and bool(m.visited.any()) and float(m.error[m.visited].max()) < 1.0
    assert torch.equal(m.error, r.error) and torch.equal(m.visited, r.visited)
    a, b = straight.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_on_by_default_for_the_fast_model_on_bounded_scenes_only(tiny_lego, tmp_path):
    """``error_sampling`` None: the device's :data:`~nerfpipe.training.trainer.DEVICE_ERROR_SAMPLING` for the fast model on a bounded scene,
    recorded in the run's config as the share used; none on a real capture, none for the classic NeRF MLP."""
    from dataclasses import replace

    from colmap_synth import make_scene

    from nerfpipe.data_adapters import load
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.models.vanilla import VanillaConfig
    from nerfpipe.training.trainer import DEVICE_ERROR_SAMPLING, Trainer, TrainerConfig

    cfg = TrainerConfig(iters=1, rays_per_step=64, eval_every=0, video_frames=0, write_outputs=False, device="cpu")
    fast = Trainer(cfg, tiny_lego, "fast", FastConfig(preset="small"), tmp_path / "fast")
    assert fast.cfg.error_sampling == DEVICE_ERROR_SAMPLING["cpu"] > 0 and fast.sampler.errors is not None
    assert fast.sampler.error_share == DEVICE_ERROR_SAMPLING["cpu"]
    real = Trainer(cfg, load(make_scene(tmp_path / "colmap")), "fast", FastConfig(preset="small"), tmp_path / "real")
    assert real.cfg.error_sampling == 0 and real.sampler.errors is None
    assert Trainer(cfg, tiny_lego, "vanilla", VanillaConfig(), tmp_path / "vanilla").sampler.errors is None
    chosen = Trainer(replace(cfg, error_sampling=0.0), tiny_lego, "fast", FastConfig(preset="small"), tmp_path / "off")
    assert chosen.sampler.errors is None


def test_a_stage_with_the_defaults_resumes_the_run_that_recorded_them_resolved(tiny_lego, tmp_path):
    """The trainer records the share (and the rays per step) it resolved from None; the train stage given None again
    continues that run instead of starting over, and one given another share does not."""
    from dataclasses import replace

    from nerfpipe.models.fast import FastConfig
    from nerfpipe.plugins.train import _resumable
    from nerfpipe.training import checkpoint
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    cfg = TrainerConfig(iters=2, rays_per_step=None, eval_every=0, video_frames=0, final_eval_views=1, device="cpu")
    model = FastConfig(preset="small", levels=(16, 32), tighten_step=0)
    Trainer(cfg, tiny_lego, "fast", model, tmp_path).train()
    assert (tmp_path / checkpoint.CHECKPOINT).is_file()
    assert _resumable(tmp_path, "fast", model, replace(cfg, iters=4))
    assert not _resumable(tmp_path, "fast", model, replace(cfg, iters=4, error_sampling=0.5))


def test_the_uniform_share_is_uniform_over_pixels_the_cut_tiles_included():
    """The uniform rays come through the same tiles, drawn by their pixel counts: every pixel alike, where the error
    draws (an untouched map: every tile alike) give the pixels of an image's cut last tiles more rays each."""
    m = small_map()
    total = int(OFFSETS[-1])
    uniform = torch.bincount(m.draw(400_000, torch.Generator().manual_seed(5), uniform=400_000)[0], minlength=total).float()
    assert float(uniform.std() / uniform.mean()) < 0.1
    by_error = torch.bincount(m.draw(400_000, torch.Generator().manual_seed(5))[0], minlength=total).float()
    assert float(by_error.std() / by_error.mean()) > 0.3
