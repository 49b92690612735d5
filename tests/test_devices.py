"""``--device auto``: one resolver (:func:`nerfpipe.util.devices.check_device`) for every command, config and stage."""

import dataclasses

import pytest
import torch

from nerfpipe.training.bench import BenchConfig
from nerfpipe.training.trainer import TrainerConfig
from nerfpipe.util import devices
from nerfpipe.util.errors import NerfpipeError


def test_auto_is_the_cpu_on_a_machine_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert devices.check_device("auto") == "cpu"
    assert devices.describe("cpu").startswith("device: cpu (")


def test_the_cpu_line_says_how_openmp_waits_where_the_program_chose_it(monkeypatch):
    """The step's time differs 1.8x between spinning and sleeping waits: a run's log says which it got."""
    from nerfpipe.util import runtime

    monkeypatch.setattr(runtime, "OMP_WAIT", "passive")
    assert devices.describe("cpu").endswith("threads, OpenMP waits: passive)")
    monkeypatch.setattr(runtime, "OMP_WAIT", "unset")  # a library import: nothing chosen, nothing said
    assert "OpenMP" not in devices.describe("cpu")


def test_auto_is_cuda_when_torch_sees_a_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert devices.check_device("auto") == "cuda"
    assert devices.check_device("cuda:1") == "cuda:1"
    with pytest.raises(NerfpipeError, match="--device 'cuda:2': this machine has 2 CUDA"):
        devices.check_device("cuda:2")


def test_auto_never_picks_mps(monkeypatch):
    """The packed renderer sums in float64, which MPS lacks: auto stays on the CPU there."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    assert devices.check_device("auto") == "cpu"


def test_a_missing_gpu_names_the_flag_and_the_way_out(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(NerfpipeError, match=r"--device 'cuda': no CUDA device .*\(use auto or cpu\)"):
        devices.check_device("cuda")


@pytest.mark.parametrize("config", [TrainerConfig, BenchConfig])
def test_configs_default_to_auto(config):
    assert {f.name: f.default for f in dataclasses.fields(config)}["device"] == devices.AUTO


def test_every_command_defaults_to_auto():
    import inspect

    from nerfpipe.commands import bench, demo, eval, mesh, render, run, view

    commands = ((bench, "bench"), (demo, "demo"), (eval, "eval_run"), (mesh, "MeshCommand"), (render, "RenderCommand"), (run, "run"), (view, "view"))
    for module, name in commands:  # functions, or the dataclass a generated command parses into
        assert inspect.signature(getattr(module, name)).parameters["device"].default == devices.AUTO, name


def test_the_python_api_defaults_to_auto(tmp_path, monkeypatch):
    """What other pipelines call (``Pipeline.run``, ``load_run``, a ``StageContext`` they build) picks the
    best device as the commands do, not the CPU."""
    import inspect

    from nerfpipe.pipeline.stages import Pipeline, StageContext
    from nerfpipe.training.runs import load_run

    assert inspect.signature(Pipeline.run).parameters["device"].default == devices.AUTO
    assert inspect.signature(load_run).parameters["device"].default == devices.AUTO
    assert StageContext(run_dir=tmp_path).device == devices.auto_device()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # as on a GPU machine
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert StageContext(run_dir=tmp_path).device == "cuda"


def test_the_trainer_records_the_resolved_device(tiny_lego, tmp_path, monkeypatch):
    """``auto`` is resolved once, so config.json and the run's generators name the device the run used."""
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    trainer = Trainer(TrainerConfig(iters=1, video_frames=0, write_outputs=False), tiny_lego, "fast", FastConfig(levels=(8, 16)), tmp_path)
    assert trainer.cfg.device == "cpu" and trainer.model.generator.device.type == "cpu"
    trainer.write_config()
    assert '"device": "cpu"' in (tmp_path / "config.json").read_text()


def test_train_prints_the_resolved_device_first(tiny_lego_npz, tmp_path, monkeypatch, capsys):
    """``nerfpipe train`` without ``--device`` runs on auto's pick and says which before anything else."""
    from nerfpipe.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    npz = tiny_lego_npz
    assert main(["train", str(npz), "--out", str(tmp_path / "run"), "--iters", "1", "--rays-per-step", "16", "--video-frames", "0",
                 "--eval-every", "0", "--no-write-outputs", "--model.levels", "4", "8"]) == 0
    assert capsys.readouterr().out.lstrip().startswith("device: cpu (")  # stdout: stderr is for the one line of an error


def test_the_fast_models_batch_follows_the_device_and_is_recorded(tiny_lego, tmp_path, device):
    """The fast model's default rays per step (None) are chosen by the device the run resolved to, and the number
    used is what config.json records (a resumed run reads it back); an explicit number is kept on any device."""
    import json

    from nerfpipe.models.fast import FastConfig
    from nerfpipe.models.registry import get_preset
    from nerfpipe.training.trainer import DEVICE_RAYS_PER_STEP, Trainer

    assert get_preset("fast").trainer["rays_per_step"] is None
    small = FastConfig(levels=(8, 16))
    for asked, expected in ((None, DEVICE_RAYS_PER_STEP[torch.device(device).type]), (300, 300)):
        cfg = TrainerConfig(iters=1, video_frames=0, write_outputs=False, rays_per_step=asked, device=str(device))
        trainer = Trainer(cfg, tiny_lego, "fast", small, tmp_path / str(asked))
        assert trainer.cfg.rays_per_step == trainer.rays == expected
        trainer.write_config()
        assert json.loads((tmp_path / str(asked) / "config.json").read_text())["trainer"]["rays_per_step"] == expected


def test_the_cpu_batch_follows_the_pixels_of_an_object_on_a_transparent_background(tiny_lego, tmp_path, monkeypatch):
    """On the CPU the fast model's default batch grows with the training images of an object on a transparent background
    (``default_rays_per_step``), up to its cap; the learning rates follow the batch chosen; a scene without alpha, a real
    capture and the vanilla model keep the device's."""
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.models.vanilla import VanillaConfig
    from nerfpipe.training import trainer as trainer_module
    from nerfpipe.training.trainer import CPU_MAX_RAYS_PER_STEP, DEVICE_RAYS_PER_STEP, Trainer, scene_info

    rgba = dataclasses.replace(tiny_lego, has_alpha=True)  # what the trainer reads of it here: the flag
    pixels = scene_info(rgba).pixels_per_image
    cfg = TrainerConfig(iters=1, video_frames=0, write_outputs=False, rays_per_step=None, device="cpu")
    small = FastConfig(levels=(8, 16))
    assert Trainer(cfg, rgba, "fast", small, tmp_path / "a").rays == DEVICE_RAYS_PER_STEP["cpu"]  # tiny images
    monkeypatch.setattr(trainer_module, "CPU_PIXELS_PER_RAY", pixels / (2 * DEVICE_RAYS_PER_STEP["cpu"]))
    doubled = Trainer(cfg, rgba, "fast", small, tmp_path / "b")
    assert doubled.cfg.rays_per_step == doubled.rays == 2 * DEVICE_RAYS_PER_STEP["cpu"]
    assert doubled.model.lr_batch_scale == pytest.approx(2**0.5)  # the rates follow the batch chosen
    assert Trainer(cfg, tiny_lego, "fast", small, tmp_path / "c").rays == DEVICE_RAYS_PER_STEP["cpu"]  # no alpha
    monkeypatch.setattr(trainer_module, "CPU_PIXELS_PER_RAY", pixels / 10**7)
    capped = Trainer(cfg, rgba, "fast", small, tmp_path / "d")
    assert capped.rays == CPU_MAX_RAYS_PER_STEP
    real = dataclasses.replace(scene_info(rgba), unbounded=True)
    assert trainer_module.default_rays_per_step("cpu", real, capped.model) == DEVICE_RAYS_PER_STEP["cpu"]
    assert Trainer(cfg, rgba, "vanilla", VanillaConfig(), tmp_path / "e").rays == DEVICE_RAYS_PER_STEP["cpu"]


@pytest.mark.requires_cuda
def test_the_default_chain_runs_on_cuda_with_device_auto(tmp_path):
    """The CUDA smoke run: the synthetic scene through the default chain (shrunk as test_demo shrinks it) on auto's
    pick, which is CUDA on a machine with a GPU. The synthetic scene is ray cast by Open3D (the ``mesh`` extra)."""
    import json

    pytest.importorskip("open3d")

    from nerfpipe.data.synthetic import SynthConfig, generate
    from nerfpipe.pipeline.stages import DEFAULT_CHAIN, Pipeline
    from nerfpipe.plugins.train import TRAIN_DIR
    from test_demo import _tiny_configs

    scene = generate(tmp_path / "scene", SynthConfig(views=16, width=48, height=48, num_points=800))
    Pipeline(list(DEFAULT_CHAIN), _tiny_configs()).run(scene.path, tmp_path / "run", resume=False, device=devices.AUTO)
    assert json.loads((tmp_path / "run" / TRAIN_DIR / "config.json").read_text())["trainer"]["device"] == "cuda"


def test_a_trained_fast_model_renders_the_same_on_every_device(tiny_lego, tmp_path, device):
    """Field, occupancy marching, early termination and packed rendering on the device against the CPU: a model
    trained on the CPU, copied to the device, renders the same colours (no jitter at evaluation)."""
    import copy

    from nerfpipe.data.rays import camera_rays
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.trainer import Trainer

    cfg = TrainerConfig(iters=40, rays_per_step=256, eval_every=0, checkpoint_every=0, video_frames=0, write_outputs=False, device="cpu")
    trainer = Trainer(cfg, tiny_lego, "fast", FastConfig(levels=(16, 32), coarse_to_fine_every=8, tighten_step=24), tmp_path)
    for _ in range(cfg.iters):
        trainer.train_step()
    rays = camera_rays(tiny_lego.cameras[:2], 0).reshape(-1)
    bg = torch.zeros(3)
    ref_model, model = trainer.model.eval(), copy.deepcopy(trainer.model).to(device).eval()
    with torch.no_grad():
        ref = ref_model.get_outputs(rays, bg)
        got = model.get_outputs(rays.to(device), bg.to(device))
    assert abs(got.num_samples - ref.num_samples) <= 1e-3 * ref.num_samples  # rounding may move a sample across a cut
    torch.testing.assert_close(got.rgb.cpu(), ref.rgb, rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(got.depth.cpu(), ref.depth, rtol=1e-3, atol=1e-3)
