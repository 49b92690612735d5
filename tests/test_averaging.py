"""The average of the parameters over the late steps (:mod:`nerfpipe.training.averaging`): its arithmetic against a
written-out reference (a fixed decay and the power-function weights), a restart where a parameter changes shape,
checkpoints that resume it exactly, a run that ends with it, and the default (real captures, and the models that ask for it)."""

import pytest
import torch
from torch import nn

from nerfpipe.training.averaging import ParameterAverage


def reference(values: "list[torch.Tensor]", decay: float) -> torch.Tensor:
    """The average written out: uniform while ``1 / n >= 1 - decay``, then exponential."""
    avg = values[0].clone()
    for n, v in enumerate(values[1:], start=2):
        w = max(1.0 - decay, 1.0 / n)
        avg = (1 - w) * avg + w * v
    return avg


def test_warm_start_is_the_mean_then_exponential_and_a_new_shape_restarts():
    lin = nn.Linear(3, 2)
    avg = ParameterAverage(lin, start=3, decay=0.75)  # uniform over 4 steps, then 1/4 for the newest
    seen = []
    g = torch.Generator().manual_seed(0)
    for step in range(1, 11):
        with torch.no_grad():
            lin.weight.copy_(torch.randn(2, 3, generator=g))
        avg.update(step)
        if step >= 3:
            seen.append(lin.weight.detach().clone())
        if step == 6:  # four steps in: the plain mean
            torch.testing.assert_close(avg.values["weight"], torch.stack(seen).mean(0))
    torch.testing.assert_close(avg.values["weight"], reference(seen, 0.75))
    assert avg.count == 8
    lin.weight.data = torch.zeros(4, 3)  # resampled to another shape: the average starts again from it
    avg.update(11)
    assert avg.count == 1 and torch.equal(avg.values["weight"], lin.weight)
    before = lin.bias.detach().clone()
    assert avg.apply() and torch.equal(lin.bias, avg.values["bias"]) and torch.equal(before, lin.bias)


def test_power_weights_follow_the_step_count():
    """``power``: the newest step weighs ``(power + 1) / step``, never less than the plain mean's ``1 / count`` nor more
    than 1."""
    lin = nn.Linear(3, 2)
    avg = ParameterAverage(lin, start=2, decay=0.5, power=3.0)  # decay ignored
    g = torch.Generator().manual_seed(0)
    want = None
    for step in range(1, 41):
        with torch.no_grad():
            lin.weight.copy_(torch.randn(2, 3, generator=g))
        avg.update(step)
        if step >= 2:
            count = step - 1
            w = min(1.0, max(4.0 / step, 1.0 / count))  # at most the newest step alone (step 3: 4/3)
            want = lin.weight.detach().clone() if want is None else (1 - w) * want + w * lin.weight.detach()
    torch.testing.assert_close(avg.values["weight"], want)
    fixed = ParameterAverage(lin, start=2, decay=0.5)  # what 1 - decay would have made of the same steps
    g = torch.Generator().manual_seed(0)
    for step in range(1, 41):
        with torch.no_grad():
            lin.weight.copy_(torch.randn(2, 3, generator=g))
        fixed.update(step)
    assert not torch.allclose(fixed.values["weight"], want)  # past the warm start the power weight made the last steps
    assert avg.count == 39


def test_nothing_before_the_start_and_state_round_trip():
    lin = nn.Linear(2, 2)
    avg = ParameterAverage(lin, start=5, decay=0.9)
    avg.update(4)
    assert avg.values is None and not avg.apply()
    for step in (5, 6, 7):
        with torch.no_grad():
            lin.weight.add_(1.0)
        avg.update(step)
    other = ParameterAverage(lin, start=5, decay=0.9)
    other.load_state(avg.state())
    assert other.count == 3 and all(torch.equal(other.values[k], avg.values[k]) for k in avg.values)
    empty = ParameterAverage(lin, start=5, decay=0.9)
    empty.load_state(ParameterAverage(lin, start=5, decay=0.9).state())
    assert empty.values is None
    with pytest.raises(KeyError):
        ParameterAverage(nn.Linear(2, 3, bias=False), start=5, decay=0.9).load_state(avg.state())


@pytest.fixture(scope="module")
def tiny_scene(scene_path, tmp_path_factory):
    import numpy as np
    import torch.nn.functional as F

    from nerfpipe.data_adapters import load

    src = np.load(scene_path("lego_200x200") / "lego_200x200.npz")

    def shrink(images):
        t = torch.from_numpy(images[..., :3]).permute(0, 3, 1, 2).float()
        return F.interpolate(t, size=(24, 24), mode="area").round().byte().permute(0, 2, 3, 1).numpy()

    path = tmp_path_factory.mktemp("avg") / "tiny.npz"
    np.savez(path, images_train=shrink(src["images_train"][:8]), c2ws_train=src["c2ws_train"][:8], images_val=shrink(src["images_val"][:1]),
             c2ws_val=src["c2ws_val"][:1], c2ws_test=src["c2ws_test"][:2], focal=np.float64(src["focal"]) * 24 / 200)
    return load(path)


def _trainer(scene, out, **kw):
    from nerfpipe.models.vanilla import VanillaConfig, VanillaFieldConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    model = VanillaConfig(num_samples=8, field=VanillaFieldConfig(width=16, depth=2, skip=1, head_width=8, pos_frequencies=4, dir_frequencies=2))
    base = dict(iters=8, rays_per_step=64, lr=5e-3, eval_every=0, checkpoint_every=4, video_frames=0, seed=1, write_outputs=False,
                num_threads=1, device="cpu", final_eval_views=1)
    return Trainer(TrainerConfig(**{**base, **kw}), scene, "vanilla", model, out)


def test_a_run_ends_with_the_average_and_resumes_it_exactly(tiny_scene, tmp_path):
    from nerfpipe.models.base import Callback
    from nerfpipe.training.checkpoint import CHECKPOINT, load_checkpoint

    straight = _trainer(tiny_scene, tmp_path / "straight", average=True, average_from=3, average_decay=0.6, average_power=0.0)
    steps = []
    straight.hooks.setdefault(Callback.AFTER_TRAIN_ITERATION, []).append(
        lambda step: steps.append({k: v.detach().clone() for k, v in straight.model.named_parameters()}))
    straight.train()
    assert len(steps) == 8
    name = next(iter(steps[0]))
    want = reference([s[name] for s in steps[2:]], 0.6)  # steps 3..8
    got = dict(straight.model.named_parameters())[name]
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-7)
    assert not torch.allclose(got, steps[-1][name])  # not the last step's
    saved = load_checkpoint(tmp_path / "straight" / CHECKPOINT)
    assert torch.equal(saved["model"][name], got) and saved["average"]["count"] == 6
    # killed after 4 steps and resumed: the same average and model, bit for bit
    _trainer(tiny_scene, tmp_path / "split", iters=4, average=True, average_from=3, average_decay=0.6, average_power=0.0).train()
    resumed = _trainer(tiny_scene, tmp_path / "split", average=True, average_from=3, average_decay=0.6, average_power=0.0, resume=True)
    resumed.train()
    a, b = straight.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_on_by_default_for_real_captures_and_the_fast_model(tiny_scene, tmp_path):
    from colmap_synth import make_scene

    from nerfpipe.data_adapters import load
    from nerfpipe.training.trainer import scene_info

    real = load(make_scene(tmp_path / "colmap"))
    assert scene_info(real).unbounded and not scene_info(tiny_scene).unbounded
    average = _trainer(real, tmp_path / "a").average
    assert (average.power, average.start) == (3.0, 256)  # a power-function average over about the last quarter there
    assert _trainer(tiny_scene, tmp_path / "b").average is None
    assert _trainer(real, tmp_path / "c", average=False).average is None
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    fast = Trainer(TrainerConfig(iters=1, rays_per_step=64, eval_every=0, video_frames=0, write_outputs=False, device="cpu"),
                   tiny_scene, "fast", FastConfig(preset="small"), tmp_path / "d")
    assert fast.average is not None and fast.supersample_from == 0  # the fast model averages everywhere; no plateau stop there
    assert (fast.average.power, fast.average.start) == (7.0, 128)  # a power-function average on bounded scenes
