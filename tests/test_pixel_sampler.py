"""The pixel sampler's ray cache (every pixel's ray generated once, kept on the device) against rays generated per batch."""

import pytest
import torch

from nerfpipe.training.pixel_sampler import PixelSampler


def _same_batches(scene, device, **kwargs):
    per_batch = PixelSampler(scene, "train", device=device, cache_rays=False, **kwargs)
    cached = PixelSampler(scene, "train", device=device, cache_rays=True, **kwargs)
    assert per_batch.cached is None and cached.cached is not None
    for seed in range(3):
        a = per_batch.sample(1024, torch.Generator().manual_seed(seed))
        b = cached.sample(1024, torch.Generator().manual_seed(seed))
        assert torch.equal(a.rays.cam_idx, b.rays.cam_idx)
        for x, y in [(a.rays.origins, b.rays.origins), (a.rays.directions, b.rays.directions),
                     (a.rays.z_scale, b.rays.z_scale), (a.rgb, b.rgb), (a.background.expand_as(a.rgb), b.background.expand_as(b.rgb))]:
            assert x.device.type == y.device.type == torch.device(device).type and x.shape == y.shape
            torch.testing.assert_close(x, y, rtol=0, atol=1e-6)
        if a.depth is not None:
            torch.testing.assert_close(a.depth, b.depth, equal_nan=True)
    return per_batch, cached


@pytest.mark.parametrize("background", ["random", "white"])
def test_cached_rays_are_the_rays_generated_per_batch(tiny_lego, device, background):
    """RGBA pixels composited on random or constant backgrounds: the same stream of batches either way."""
    _same_batches(tiny_lego, device, background=background)


def test_cached_rays_of_a_distorted_capture_with_tracks_and_an_error_map(scene_path, device):
    """colmap_mouse: distorted cameras, downscaled photographs, rays through sparse points and error-map draws."""
    pytest.importorskip("pycolmap")  # a device machine's image may lack it (benchmarks/gpu_bundle.sh)
    from nerfpipe.data_adapters import load

    scene = load(scene_path("colmap_mouse"))
    _, cached = _same_batches(scene, device, background="grey", track_rays=128, max_side=240, error_share=0.5, error_tiles=1024)
    table, pixels, offsets = cached.cached
    assert table.shape == (len(cached), 7) and pixels.shape[0] == len(cached) and int(offsets[-1]) == len(cached)
    assert float((table[:, 3:6].norm(dim=-1) - 1).abs().max()) < 1e-5  # unit directions


def test_training_on_cached_rays_trains_as_on_rays_per_batch(tiny_lego, tmp_path, device):
    """Fast-model steps (eager on the CPU; a CUDA graph on CUDA, where the trainer caches by default) see the same losses
    whether the sampler's rays are cached (views into its table) or generated per batch."""
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    losses = {}
    for cache in (False, True):
        cfg = TrainerConfig(iters=10**6, rays_per_step=1024, eval_every=0, checkpoint_every=0, video_frames=0, write_outputs=False,
                            device=str(device))
        fast = FastConfig(preset="small", levels=(16, 32, 48), coarse_to_fine_every=8, tighten_step=24, fine_steps_from=0)
        trainer = Trainer(cfg, tiny_lego, "fast", fast, tmp_path / str(cache))
        assert (trainer.sampler.cached is not None) == (device.type == "cuda")  # the default: cached on CUDA only
        trainer.sampler = PixelSampler(tiny_lego, "train", trainer.train_bg, device, cache_rays=cache)
        trainer.model.train()
        losses[cache] = torch.stack([trainer.train_step() for _ in range(30)]).cpu()
    torch.testing.assert_close(losses[True], losses[False], rtol=1e-3, atol=1e-6)
    assert float(losses[True][-5:].mean()) < float(losses[True][:5].mean())
