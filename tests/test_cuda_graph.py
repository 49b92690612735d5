"""The training step as a replayed CUDA graph (:mod:`nerfpipe.training.cuda_graph`) against the eager step: the same
gradients for the same batch and random stream, and the same training. CUDA only (skipped elsewhere); the CPU-side
pieces it rests on (the sample slots, a step that reads nothing back) are tested in ``test_packed``,
``test_early_termination`` and ``test_unbounded``."""

import math

import pytest
import torch

from nerfpipe.training.cuda_graph import HEADROOM, QUANTUM, capacity_for

def test_capacity_has_headroom_in_whole_quanta():
    for n in (0, 1, QUANTUM, 10**6):
        c = capacity_for(n)
        assert c % QUANTUM == 0 and c >= max(QUANTUM, HEADROOM * n) and c < HEADROOM * n + QUANTUM + 1


CUDA = pytest.mark.requires_cuda


def _trainer(tiny_lego, out, graph: bool, **model):
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    cfg = TrainerConfig(iters=10**6, rays_per_step=1024, eval_every=0, checkpoint_every=0, video_frames=0, write_outputs=False,
                        device="cuda", cuda_graph=graph)
    fast = FastConfig(preset="small", levels=(16, 32, 48), coarse_to_fine_every=8, tighten_step=24, fine_steps_from=0, **model)
    trainer = Trainer(cfg, tiny_lego, "fast", fast, out)
    trainer.model.train()
    return trainer


@CUDA
def test_a_replayed_step_gives_the_eager_steps_gradients(tiny_lego, tmp_path):
    trainer = _trainer(tiny_lego, tmp_path, graph=True)
    while trainer.step < 40:
        trainer.train_step()
    assert trainer.graph.failed is None and trainer.graph.replays > 0, trainer.graph.stats()
    batch = trainer.sampler.sample(trainer.rays, trainer.generator)
    state = trainer.model.generator.get_state()
    trainer.optimizer.zero_grad(set_to_none=True)
    sq_eager = trainer.forward_backward(batch).clone()
    eager = {n: p.grad.clone() for n, p in trainer.model.named_parameters() if p.grad is not None}
    trainer.model.generator.set_state(state)
    replays = trainer.graph.replays
    sq_graph = trainer.graph(batch)
    assert trainer.graph.replays == replays + 1  # replayed, not captured anew
    torch.testing.assert_close(sq_graph, sq_eager, rtol=1e-4, atol=1e-6)
    graphed = {n: p.grad for n, p in trainer.model.named_parameters() if p.grad is not None}
    assert graphed.keys() == eager.keys() and eager
    for name in eager:
        torch.testing.assert_close(graphed[name], eager[name], rtol=1e-3, atol=1e-6)


@CUDA
def test_graphed_training_trains_as_eager_training(tiny_lego, tmp_path):
    psnr = {}
    for graph in (False, True):
        trainer = _trainer(tiny_lego, tmp_path / str(graph), graph=graph)
        losses = [trainer.train_step() for _ in range(120)]
        psnr[graph] = -10 * math.log10(float(torch.stack(losses[-20:]).mean()))
        if graph:
            g = trainer.graph
            # captured anew where the step's code changes (levels switched on, warm-up over, the box tightened)
            assert g.failed is None and g.captures >= 3 and g.replays >= 100 - 2 * g.captures, g.stats()
    assert abs(psnr[True] - psnr[False]) < 0.5, psnr


@CUDA
def test_a_step_that_cannot_be_captured_runs_eagerly(tiny_lego, tmp_path):
    """Rounds of early termination read counts back: no graph, the eager step, nothing lost."""
    trainer = _trainer(tiny_lego, tmp_path, graph=True, fixed_shapes=False)
    for _ in range(5):
        trainer.train_step()
    assert trainer.graph.captures == 0 and trainer.graph.replays == 0 and trainer.step == 5


@CUDA
def test_a_real_capture_step_replays_with_the_eager_gradients():
    """The field behind the box, the depth loss of track rays, colour corrections and image codes in one captured
    step: replayed, the same squared errors and gradients as the eager step with the same random stream."""
    from nerfpipe.data.rays import RayBundle
    from nerfpipe.models.base import SceneInfo
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.cuda_graph import GraphedStep
    from nerfpipe.training.pixel_sampler import PixelBatch

    info = SceneInfo(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=4, pixels_per_image=100,
                     unbounded=True, focal_spread=1.0)
    model = FastConfig(preset="small").setup(info).cuda()
    assert model.behind is not None and model.appearance is not None
    model.train()
    model._step = model.cfg.behind_from
    model.generator = torch.Generator("cuda").manual_seed(0)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(3)
    n = 256
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    rays = RayBundle(torch.tensor([0.0, 0.0, 4.0]).expand(n, 3).clone(), d, torch.randint(0, 4, (n,), generator=g), torch.ones(n)).to("cuda")
    batch = PixelBatch(rays, torch.rand(n, 3, generator=g).cuda(), torch.zeros(n, 3, device="cuda"),
                       torch.where(torch.arange(n) % 2 == 0, 3.5, float("nan")).cuda())

    def forward_backward(b):
        out = model.get_outputs(b.rays, b.background)
        sum(model.get_losses(out, b.rgb, b.depth).values()).backward()
        return ((out.rgb.detach() - b.rgb) ** 2).mean(-1)

    step = GraphedStep(model, opt, forward_backward)
    step(batch)  # the eager warm-up
    state = model.generator.get_state()
    opt.zero_grad(set_to_none=True)
    sq_eager = forward_backward(batch).clone()
    eager = {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}
    model.generator.set_state(state)
    sq_graph = step(batch)  # captured and replayed
    assert step.failed is None and step.captures == 1 and step.replays == 1, step.stats()
    torch.testing.assert_close(sq_graph, sq_eager, rtol=1e-4, atol=1e-6)
    graphed = {k: p.grad for k, p in model.named_parameters() if p.grad is not None}
    assert graphed.keys() == eager.keys() and any(k.startswith("behind.") for k in eager)
    for k in eager:
        torch.testing.assert_close(graphed[k], eager[k], rtol=1e-3, atol=1e-6)
