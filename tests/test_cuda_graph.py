"""The training step as a replayed CUDA graph (:mod:`nerfpipe.training.cuda_graph`) against the eager step: the same
gradients for the same batch and random stream, and the same training (CUDA only); and its state machine (when it warms
up, captures, replays, grows and shrinks the slots, gives up) on the CPU with stand-ins for its CUDA calls. The pieces
it rests on (the slots, a step that reads nothing back) are tested in ``test_packed``, ``test_early_termination`` and
``test_unbounded``."""

import contextlib
import math

import pytest
import torch

from nerfpipe.training.cuda_graph import HEADROOM, QUANTUM, GraphedStep, capacity_for

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


@CUDA
def test_a_graphed_run_checkpoints_and_resumes(tiny_lego, tmp_path):
    """The model's generator, registered with the graphs, is saved in checkpoints and restored on resume; the resumed
    run captures anew and ends where a straight run does (to rounding: it warms up where the straight run replays)."""
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    model = FastConfig(preset="small", levels=(16, 32, 48), coarse_to_fine_every=8, tighten_step=24, fine_steps_from=0)
    base = dict(iters=80, rays_per_step=1024, eval_every=0, video_frames=0, checkpoint_every=20, seed=0, write_outputs=False, device="cuda")
    straight = Trainer(TrainerConfig(**base), tiny_lego, "fast", model, tmp_path / "straight")
    a = straight.train()
    Trainer(TrainerConfig(**{**base, "iters": 50}), tiny_lego, "fast", model, tmp_path / "split").train()
    resumed = Trainer(TrainerConfig(**{**base, "resume": True}), tiny_lego, "fast", model, tmp_path / "split")
    b = resumed.train()
    assert resumed.step == 80 and resumed.graph.failed is None and resumed.graph.replays > 20, resumed.graph.stats()
    assert a["cuda_graph"]["failed"] is None and a["cuda_graph"]["graph_replays"] > 60, a["cuda_graph"]
    assert abs(a["val_psnr"] - b["val_psnr"]) < 0.3, (a["val_psnr"], b["val_psnr"])


# ---------------------------------------------------------------- the state machine on the CPU
class _Landed:
    """An event that has always landed."""

    def query(self) -> bool:
        return True

    def synchronize(self) -> None:
        pass


class _Replay:
    """A stand-in for a captured graph: a replay runs the body again on the static inputs, its gradients zeroed first
    and its output written into the captured one (as a graph writes the same memory)."""

    def __init__(self, step, body, out) -> None:
        self.step, self.body, self.out = step, body, out

    def replay(self) -> None:
        for _, grad in self.step.grads:
            grad.zero_()
        self.out.copy_(self.body())


class EmulatedGraphs(GraphedStep):
    """:class:`GraphedStep` with its CUDA calls replaced (streams, pinned memory, events, capture): the rest, when to warm
    up, capture, replay, grow and shrink the slots, runs as on a GPU."""

    def _new_stream(self):
        return None

    def _host_buffer(self, n: int):
        return torch.zeros(n, dtype=torch.long)

    def _record_event(self):
        return _Landed()

    @contextlib.contextmanager
    def _side_stream(self):
        yield

    def _record(self, body):
        out = body()  # a capture runs nothing; here the first replay's work is done twice
        return _Replay(self, body, out), out


def _cpu_trainer(tiny_lego, out, rays: int = 256, **model):
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    cfg = TrainerConfig(iters=10**6, rays_per_step=rays, eval_every=0, checkpoint_every=0, video_frames=0, write_outputs=False, device="cpu")
    fast = FastConfig(preset="small", levels=(16, 32, 48), coarse_to_fine_every=8, tighten_step=24, fine_steps_from=0, fixed_shapes=True, **model)
    trainer = Trainer(cfg, tiny_lego, "fast", fast, out)
    trainer.model.train()
    assert trainer.graph is None  # never on the CPU by itself
    return trainer


def test_the_graph_state_machine_captures_where_the_step_changes_and_trains_as_eager_steps(tiny_lego, tmp_path):
    torch.set_num_threads(1)
    psnr = {}
    for emulated in (False, True):
        trainer = _cpu_trainer(tiny_lego, tmp_path / str(emulated))
        if emulated:
            trainer.graph = EmulatedGraphs(trainer.model, trainer.optimizer, trainer.forward_backward)
        losses = [trainer.train_step() for _ in range(60)]
        psnr[emulated] = -10 * math.log10(float(torch.stack(losses[-20:]).mean()))
    g = trainer.graph
    # a capture after each warm-up: levels switched on (8, 16), the warm-up over, the box tightened (24), ...
    assert g.failed is None and g.overflows == 0 and 3 <= g.captures <= g.eager_steps <= g.captures + 1, g.stats()
    assert g.replays == 60 - g.eager_steps
    assert all(c >= n for c, n in zip(g.capacity, trainer.model.sample_count().tolist())), (g.capacity, trainer.model.sample_count())
    assert abs(psnr[True] - psnr[False]) < 0.5, psnr


def test_too_few_slots_are_seen_and_captured_anew_and_too_many_shrink(tiny_lego, tmp_path, monkeypatch):
    import nerfpipe.training.cuda_graph as cg

    torch.set_num_threads(1)
    trainer = _cpu_trainer(tiny_lego, tmp_path, rays=256)
    trainer.graph = g = EmulatedGraphs(trainer.model, trainer.optimizer, trainer.forward_backward)
    while trainer.step < 30:  # past the changes of the step's code
        trainer.train_step()
    monkeypatch.setattr(cg, "HEADROOM", 0.5)  # slots for half of what a step needs, from the next window's check on
    for _ in range(cg.WINDOW + 4):
        trainer.train_step()
    assert g.overflows >= 2, g.stats()  # seen at the next read back, and captured anew (with too few again)
    monkeypatch.setattr(cg, "HEADROOM", 4.0)
    for _ in range(4):  # the overflows' captures: four times what a step needed of what overflowed (intervals dropped as
        trainer.train_step()  # empty left fewer samples kept, so the samples' slots may come from a smaller count)
    big, overflows, captures = g.capacity, g.overflows, g.captures
    assert any(c >= 3 * n for c, n in zip(big, trainer.model.sample_count().tolist())), (big, trainer.model.sample_count())
    monkeypatch.setattr(cg, "HEADROOM", 1.15)
    for _ in range(cg.WINDOW + 1):
        trainer.train_step()
    assert g.overflows == overflows and g.captures == captures + 1, g.stats()  # one shrink, at the window's end
    assert all(a < b for a, b in zip(g.capacity, big)), (big, g.stats())


def test_a_failed_capture_leaves_the_run_stepping_eagerly(tiny_lego, tmp_path):
    class Failing(EmulatedGraphs):
        def _record(self, body):
            raise RuntimeError("operation not permitted when stream is capturing")

    trainer = _cpu_trainer(tiny_lego, tmp_path)
    trainer.graph = g = Failing(trainer.model, trainer.optimizer, trainer.forward_backward)
    for _ in range(6):
        assert torch.isfinite(trainer.train_step())
    assert "not permitted" in g.failed and g.captures == 0 and g.replays == 0 and trainer.step == 6
