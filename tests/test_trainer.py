"""End-to-end training on a tiny scene: learning, determinism, resume, outputs, CLI."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nerfpipe.cli import main
from nerfpipe.data_adapters import load
from nerfpipe.fields.vanilla import VanillaFieldConfig
from nerfpipe.models.vanilla import VanillaConfig
from nerfpipe.training.trainer import Trainer, TrainerConfig
from nerfpipe.util.errors import NerfpipeError

SIZE = 16


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny models are dominated by per-op overhead; a second thread only adds spin-waits (and is
    much slower on a shared, oversubscribed machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _shrink(images: np.ndarray) -> np.ndarray:
    t = torch.from_numpy(images).permute(0, 3, 1, 2).float()
    return F.interpolate(t, size=(SIZE, SIZE), mode="area").round().clamp(0, 255).byte().permute(0, 2, 3, 1).numpy()


@pytest.fixture(scope="module")
def tiny_npz(scene_path, tmp_path_factory):
    """A CS180-layout npz of a few lego views at 16x16 (written to a temp folder, not the repo)."""
    src = np.load(scene_path("lego_200x200") / "lego_200x200.npz")
    out = tmp_path_factory.mktemp("tiny") / "tiny_lego.npz"
    np.savez(
        out,
        images_train=_shrink(src["images_train"][::12]),
        c2ws_train=src["c2ws_train"][::12],
        images_val=_shrink(src["images_val"][:2]),
        c2ws_val=src["c2ws_val"][:2],
        c2ws_test=src["c2ws_test"][::20],
        focal=np.float64(src["focal"]) * SIZE / 200,
    )
    return out


@pytest.fixture(scope="module")
def tiny_scene(tiny_npz):
    return load(tiny_npz)


MODEL = VanillaConfig(num_samples=16, field=VanillaFieldConfig(width=32, depth=3, skip=2, head_width=16, pos_frequencies=6, dir_frequencies=2))


def tcfg(**kw):
    base = dict(iters=8, rays_per_step=128, lr=5e-3, eval_every=4, checkpoint_every=4, video_frames=0, seed=3, write_outputs=False)
    return TrainerConfig(**{**base, **kw})


def params(trainer):
    return {k: v.clone() for k, v in trainer.model.state_dict().items()}


def test_psnr_rises_and_outputs_exist(tiny_scene, tmp_path):
    t = Trainer(tcfg(iters=60, eval_every=20, video_frames=3, write_outputs=True), tiny_scene, "vanilla", MODEL, tmp_path)
    metrics = t.train()
    val = t.history["val"]
    assert val[0][0] == 0 and val[-1][0] == 60
    assert val[-1][2] > val[0][2] + 3.0, val  # well above the untrained start
    for key in ("val_psnr", "val_ssim", "train_seconds", "iterations", "model_params", "samples_per_ray"):
        assert key in metrics
    assert metrics["iterations"] == 60 and metrics["samples_per_ray"] == 16
    assert json.loads((tmp_path / "metrics.json").read_text())["val_psnr"] == pytest.approx(metrics["val_psnr"])
    assert json.loads((tmp_path / "history.json").read_text())["val"][-1]["step"] == 60
    for name in ("config.json", "checkpoint.safetensors", "psnr.png", "progress.png", "cameras.png", "orbit.gif", "orbit.mp4", "depth_orbit.gif"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert "turbo" in metrics["depth_colormap"]


def test_same_seed_same_model(tiny_scene, tmp_path):
    a = Trainer(tcfg(iters=3, eval_every=0), tiny_scene, "vanilla", MODEL, tmp_path / "a")
    b = Trainer(tcfg(iters=3, eval_every=0), tiny_scene, "vanilla", MODEL, tmp_path / "b")
    a.train(), b.train()
    pa, pb = params(a), params(b)
    assert all(torch.equal(pa[k], pb[k]) for k in pa)


def test_resume_continues_from_checkpoint(tiny_scene, tmp_path):
    straight = Trainer(tcfg(), tiny_scene, "vanilla", MODEL, tmp_path / "straight")
    straight.train()
    Trainer(tcfg(iters=4), tiny_scene, "vanilla", MODEL, tmp_path / "split").train()
    resumed = Trainer(tcfg(resume=True), tiny_scene, "vanilla", MODEL, tmp_path / "split")
    resumed.train()
    assert resumed.step == 8
    pa, pb = params(straight), params(resumed)
    assert all(torch.equal(pa[k], pb[k]) for k in pa)  # bit-identical continuation on CPU


def test_time_budget_stops_training(tiny_scene, tmp_path):
    t = Trainer(tcfg(iters=10_000, train_budget=0.0, eval_every=0), tiny_scene, "vanilla", MODEL, tmp_path)
    assert t.train()["iterations"] == 0


def test_spent_time_budget_still_scores_one_view_and_records_the_plan(tiny_scene, tmp_path):
    """A wall-clock budget already spent: no training, one view scored, the video left out, all recorded."""
    t = Trainer(tcfg(iters=10_000, time_budget=0.0, video_frames=30, write_outputs=True), tiny_scene, "vanilla", MODEL, tmp_path)
    metrics = t.train()
    plan = json.loads((tmp_path / "metrics.json").read_text())["budget_plan"]
    assert metrics["iterations"] == 0 and metrics["val_views"] == 1 == plan["final_eval"]["views"]
    assert plan["final_eval"]["of"] == 2 and plan["video"]["skipped"] and not (tmp_path / "orbit.gif").exists()
    assert t.history["val"] == [[0, 0.0, metrics["val_psnr"], metrics["val_ssim"], 1]]  # no step-0 validation under a budget


def test_ample_time_budget_keeps_the_full_protocol(tiny_scene, tmp_path):
    t = Trainer(tcfg(iters=4, time_budget=3600.0, video_frames=3, write_outputs=True), tiny_scene, "vanilla", MODEL, tmp_path)
    metrics = t.train()
    plan = metrics["budget_plan"]
    assert metrics["iterations"] == 4 and metrics["val_views"] == 2 and plan["final_eval"]["scale"] == 1.0
    assert plan["video"]["frames"] == 3 and metrics["video"]["size"] == [SIZE, SIZE]


def test_training_leaves_what_the_final_evaluation_needs_within_bounds(tiny_scene, tmp_path):
    """The training window leaves FINAL_SHARE of the budget, more where the validations' time per ray says the
    final evaluation of every view needs it where that is at most FINAL_MAX_SHARE."""
    from nerfpipe.training.evaluation import FINAL_MAX_SHARE, FINAL_SHARE, final_eval_need

    t = Trainer(tcfg(time_budget=100.0, eval_max_size=SIZE // 2), tiny_scene, "vanilla", MODEL, tmp_path)
    assert t.training_window() == pytest.approx((1 - FINAL_SHARE) * 100.0) and final_eval_need(t) is None  # no validation yet
    t.seconds_per_pixel = 1.0
    per_ray = final_eval_need(t)  # 2 views of 8x8 pixels, one ray each, over the final share, with the margin
    assert per_ray == pytest.approx(1.3 * 2 * 64 / 0.8) and final_eval_need(t, supersample=True) == pytest.approx(4 * per_ray)
    t.seconds_per_pixel = 30.0 / per_ray
    assert t.training_window() == pytest.approx(70.0)
    t.seconds_per_pixel = 40.0 / per_ray
    assert t.training_window() == pytest.approx((1 - FINAL_MAX_SHARE) * 100.0)
    t.seconds_per_pixel = 41.0 / per_ray  # no share up to FINAL_MAX_SHARE would score every view: the usual share
    assert t.training_window() == pytest.approx((1 - FINAL_SHARE) * 100.0)
    t.seconds_per_pixel = 1e-9
    assert t.training_window() == pytest.approx((1 - FINAL_SHARE) * 100.0)


def test_training_leaves_the_supersampled_final_evaluation_its_time_past_supersample_from(tiny_scene, tmp_path):
    """From ``supersample_from`` on, the window leaves what the final evaluation needs with its rays per pixel
    (2 x 2 here: 8-pixel renders of 16-pixel views), beyond FINAL_MAX_SHARE too; before it, and at 0, one ray's."""
    from nerfpipe.training.evaluation import FINAL_SHARE, final_eval_need

    t = Trainer(tcfg(time_budget=100.0, eval_max_size=SIZE // 2, supersample_from=10), tiny_scene, "vanilla", MODEL, tmp_path)
    t.seconds_per_pixel = 1.0
    t.seconds_per_pixel = 15.0 / final_eval_need(t)  # one ray per pixel: 15 s, under the usual share; 2 x 2: 60 s
    assert t.training_window() == pytest.approx((1 - FINAL_SHARE) * 100.0)
    t.step = 10
    assert t.training_window() == pytest.approx(40.0)
    t.supersample_from = 0
    assert t.training_window() == pytest.approx((1 - FINAL_SHARE) * 100.0)


@pytest.mark.parametrize("elapsed, plan, window", [(10.0, "generous", 48.0), (50.0, "now", 50.0), (65.0, "now", 65.0), (70.0, "none", 75.0)])
def test_past_the_plateau_training_stops_for_the_supersampled_evaluation_only_where_it_is_affordable(tiny_scene, tmp_path, monkeypatch,
                                                                                                    elapsed, plan, window):
    """Decided once, at the first window past ``supersample_from``: the generous reserve where the time left affords it,
    a stop at once where only the evaluation's own cost fits (no margin: 65 s + 40 / 1.3 s fits in 100, 50 s + 1.3 x 40 s does not), else the window
    of one ray per pixel (no stop for a supersampled evaluation that could not run then: 70 s + 30.8 s does not)."""
    from nerfpipe.training.evaluation import AVERAGED_RENDER_FACTOR, FINAL_MARGIN, FINAL_SHARE, final_eval_need

    t = Trainer(tcfg(time_budget=100.0, eval_max_size=SIZE // 2, supersample_from=10, average=True), tiny_scene, "vanilla", MODEL, tmp_path)
    t.seconds_per_pixel = 1.0
    t.seconds_per_pixel = 10.0 / final_eval_need(t)  # one ray per pixel 10 s; 2 x 2 rays 40 s at the validations' cost
    assert final_eval_need(t, supersample=True) == pytest.approx(AVERAGED_RENDER_FACTOR * 40.0) and AVERAGED_RENDER_FACTOR == 1.3
    assert final_eval_need(t, supersample=True, averaged_factor=1.0, margin=1.0) == pytest.approx(40.0 / FINAL_MARGIN) and FINAL_MARGIN == 1.3
    assert (1 - FINAL_SHARE) * 100.0 == pytest.approx(75.0)  # the window of one ray per pixel
    clock = {"now": elapsed}
    monkeypatch.setattr(t, "wall_elapsed", lambda: clock["now"])
    assert t.training_window() == pytest.approx(75.0) and t.supersample_plan is None  # before the plateau
    t.step = 10
    assert t.training_window() == pytest.approx(window) and t.supersample_plan == (plan, elapsed)
    clock["now"] = elapsed + 5.0  # decided once: the window does not move with the clock
    assert t.training_window() == pytest.approx(window) and t.supersample_plan == (plan, elapsed)


def test_the_supersampled_final_evaluation_of_averaged_parameters_is_reserved_more(tiny_scene, tmp_path):
    """The final evaluation renders the averaged parameters (the occupancy grid refreshed in full), slower per ray than
    the validations during training: the window reserves AVERAGED_RENDER_FACTOR times more for its 2 x 2 rays."""
    from nerfpipe.training.evaluation import AVERAGED_RENDER_FACTOR, final_eval_need

    plain = Trainer(tcfg(time_budget=100.0, eval_max_size=SIZE // 2, average=False), tiny_scene, "vanilla", MODEL, tmp_path / "a")
    averaged = Trainer(tcfg(time_budget=100.0, eval_max_size=SIZE // 2, average=True), tiny_scene, "vanilla", MODEL, tmp_path / "b")
    plain.seconds_per_pixel = averaged.seconds_per_pixel = 1.0
    assert final_eval_need(averaged) == pytest.approx(final_eval_need(plain))  # one ray per pixel: as measured
    assert final_eval_need(averaged, supersample=True) == pytest.approx(AVERAGED_RENDER_FACTOR * final_eval_need(plain, supersample=True))
    assert AVERAGED_RENDER_FACTOR > 1


def test_supersample_from_defaults_to_the_plateau_where_parameters_are_averaged(tiny_scene, tmp_path):
    """The plateau is a real capture's (held-out views that stop improving); a synthetic scene's average does not stop
    training early."""
    from colmap_synth import make_scene

    from nerfpipe.data_adapters import load
    from nerfpipe.training.trainer import PLATEAU_STEPS

    real = load(make_scene(tmp_path / "colmap"))
    assert Trainer(tcfg(average=True), real, "vanilla", MODEL, tmp_path / "a").supersample_from == PLATEAU_STEPS
    assert Trainer(tcfg(average=True), tiny_scene, "vanilla", MODEL, tmp_path / "d").supersample_from == 0
    assert Trainer(tcfg(average=False), tiny_scene, "vanilla", MODEL, tmp_path / "b").supersample_from == 0
    assert Trainer(tcfg(average=False, supersample_from=5), tiny_scene, "vanilla", MODEL, tmp_path / "c").supersample_from == 5


@pytest.mark.parametrize("budget, supersample", [(3600.0, 2), (0.0, 1)])
def test_final_evaluation_supersamples_small_views_when_every_view_fits(tiny_scene, tmp_path, budget, supersample):
    t = Trainer(tcfg(iters=2, time_budget=budget, eval_max_size=SIZE // 2), tiny_scene, "vanilla", MODEL, tmp_path)
    plan = t.train()["budget_plan"]["final_eval"]
    assert plan["supersample"] == supersample and plan["size"] == [SIZE // 2, SIZE // 2]


def test_the_final_evaluations_probe_renders_the_planned_rays_per_pixel_after_a_warm_up(tiny_scene, tmp_path, monkeypatch):
    """Under a budget the final evaluation times its probe (half the side) with the rays per pixel it plans, as many as a
    view's at one ray per pixel, after an untimed warm-up render: a probe at one ray per pixel, timed cold, overestimated
    colmap_mouse's final 2 x 2 rays 1.45x."""
    from nerfpipe.training import evaluation

    calls = []
    real = evaluation.render_cameras

    def recording(model, cameras, chunk=None, background=None, supersample=1):
        calls.append((int(cameras.width[0]), int(cameras.height[0]), supersample))
        return real(model, cameras, chunk, background, supersample)

    monkeypatch.setattr(evaluation, "render_cameras", recording)
    t = Trainer(tcfg(iters=2, time_budget=3600.0, eval_max_size=SIZE // 2), tiny_scene, "vanilla", MODEL, tmp_path)
    plan = t.train()["budget_plan"]["final_eval"]
    assert plan["supersample"] == 2  # 8-pixel renders of 16-pixel views
    warm, probe = calls[0], calls[1]
    assert warm == (evaluation.PROBE_WARMUP, evaluation.PROBE_WARMUP, 1)
    assert probe == (SIZE // 2 // evaluation.PROBE, SIZE // 2 // evaluation.PROBE, 2)


def test_the_appearance_fit_is_planned_from_two_short_fits():
    """The final evaluation plans for the appearance fit of each view (NeRF-W's protocol) from two short fits timed:
    a fit of ``s`` steps that costs ``a + b s`` is estimated at the full count."""
    from contextlib import contextmanager

    from nerfpipe.training.evaluation import FIT_PROBE_STEPS, FIT_WARMUP_STEPS, appearance_fit_seconds

    clock = [0.0]

    class Fits:
        appearance_fit_steps = 1024

        @contextmanager
        def fitted_appearance(self, rays, rgb, background, steps=None):
            clock[0] += 2.0 + 0.01 * (self.appearance_fit_steps if steps is None else steps)  # a fit of 2 s + 10 ms a step
            yield True

    model = Fits()
    assert appearance_fit_seconds(model, None, None, None, clock=lambda: clock[0]) == pytest.approx(2.0 + 0.01 * 1024)
    assert clock[0] == pytest.approx(3 * 2.0 + 0.01 * (sum(FIT_PROBE_STEPS) + FIT_WARMUP_STEPS))  # only the short fits ran (and an untimed warm-up)
    model.appearance_fit_steps = 0  # nothing to fit: nothing timed
    assert appearance_fit_seconds(model, None, None, None, clock=lambda: clock[0]) == 0.0


def test_training_leaves_each_view_its_appearance_fit(tiny_scene, tmp_path):
    """Photo collections: the final evaluation fits each held-out view's appearance (a fixed cost per view) and renders
    it whole with it; the window leaves that too, or it scores fewer views than the protocol's (Sacre Coeur: 1 of 2)."""
    from nerfpipe.training.evaluation import FINAL_MARGIN, final_eval_need

    t = Trainer(tcfg(time_budget=100.0, eval_max_size=SIZE // 2), tiny_scene, "vanilla", MODEL, tmp_path)
    t.seconds_per_pixel = 1.0 / 128  # 2 views of 8 x 8 pixels: 1 s at one ray per pixel
    plain = final_eval_need(t)
    t.appearance_fit_seconds = 3.0
    assert final_eval_need(t) == pytest.approx(plain + FINAL_MARGIN * (2 * 3.0 + 1.0) / 0.8)  # 2 fits, 2 pictures
    assert final_eval_need(t, margin=1.0) == pytest.approx((1.0 + 2 * 3.0 + 1.0) / 0.8)


def test_a_budgeted_validation_times_the_appearance_fit_once(tiny_scene, tmp_path, monkeypatch):
    """The first validation under a budget times one view's appearance fit (0 without per-image appearance), as
    validation time; later ones do not again; without a budget nothing is timed."""
    from nerfpipe.training import evaluation

    calls = []
    monkeypatch.setattr(evaluation, "appearance_fit_seconds", lambda model, rays, rgb, bg: calls.append(rays.shape) or 4.0)
    t = Trainer(tcfg(time_budget=3600.0, eval_max_size=SIZE // 2), tiny_scene, "vanilla", MODEL, tmp_path / "a")
    evaluation.validate(t, 1)
    assert t.appearance_fit_seconds == 0.0 and calls == []  # the classic MLP fits no appearance
    monkeypatch.setattr(type(t.model), "appearance_fit_steps", 1024, raising=False)
    t.appearance_fit_seconds, before = None, t.validation_seconds
    evaluation.validate(t, 1)
    assert t.appearance_fit_seconds == 4.0 and calls == [((SIZE // 2) * (SIZE // 4),)]  # the left half of the first view
    assert t.validation_seconds > before
    evaluation.validate(t, 1)
    assert len(calls) == 1
    u = Trainer(tcfg(eval_max_size=SIZE // 2), tiny_scene, "vanilla", MODEL, tmp_path / "b")
    evaluation.validate(u, 1)
    assert u.appearance_fit_seconds is None


def test_progress_eta_under_a_time_budget_is_the_time_to_the_end_of_the_run():
    from nerfpipe.util.progress import TrainProgress

    bar = TrainProgress(tcfg(iters=100_000, time_budget=100.0), 0, 0.0, window=75.0)
    assert bar.eta(1, 1.0, wall=10.0) == pytest.approx(90.0)  # first update: to the end of the budget
    assert bar.eta(11, 5.0, wall=20.0) == pytest.approx(55.0 + 25.0)  # the window binds, then the final phase
    bar = TrainProgress(tcfg(iters=21, time_budget=100.0), 0, 0.0, window=75.0)
    bar.eta(1, 1.0, wall=10.0)
    assert bar.eta(11, 5.0, wall=20.0) == pytest.approx(10 * 1.0 + 25.0)  # the iterations end first (1 s each)
    assert bar.completed(11, 5.0, 20.0) == (20.0, "20/75 s, step 11")


def test_eval_command_scores_every_view_at_full_size(tiny_npz, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(tiny_npz), "--model", "vanilla", "--out", str(run), "--iters", "2", "--rays-per-step", "32",
                 "--model.num-samples", "8", "--video-frames", "0", "--eval-every", "0"]) == 0
    capsys.readouterr()
    assert main(["eval", str(run), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    metrics = json.loads((run / "metrics.json").read_text())
    assert result["views"] == 2 and result["sizes"] == [f"{SIZE}x{SIZE}"] and result == json.loads((run / "eval.json").read_text())
    assert result["psnr"] == pytest.approx(metrics["val_psnr"], abs=1e-5)  # the trainer's protocol without a budget: the same scores
    import imageio.v3 as iio

    from nerfpipe.training.evaluation import ground_truth

    held_out = iio.imread(run / "held_out.png")  # the final evaluation's views, one per row: photograph | render | error
    assert held_out.shape == (result["views"] * SIZE, 3 * SIZE, 3)
    scene = load(tiny_npz)

    def check_strip(strip, view):
        gt = ground_truth(scene, view["view"], torch.zeros(3), (SIZE, SIZE))  # the tiny scene's evaluation background: black
        assert np.abs(strip[:, :SIZE].astype(int) - np.round(gt.numpy() * 255).astype(int)).max() <= 1
        mse = np.mean((strip[:, SIZE : 2 * SIZE] / 255.0 - gt.numpy()) ** 2)  # the middle third is the render that was scored
        assert -10 * np.log10(mse) == pytest.approx(view["psnr"], abs=0.05)

    for row, view in enumerate(result["per_view"]):
        check_strip(held_out[row * SIZE : (row + 1) * SIZE], view)
    assert result["lpips"] is None or 0 <= result["lpips"] <= 1

    pipeline_layout = tmp_path / "piperun"  # nerfpipe run's layout: the trained model in train/
    pipeline_layout.mkdir()
    run.rename(pipeline_layout / "train")
    assert main(["eval", str(pipeline_layout), "--views", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["per_view"][0] == result["per_view"][0]
    assert (pipeline_layout / "train" / "eval.json").is_file()

    half = SIZE // 2  # below the photographs' size: 2x2 rays per pixel by default, one with --supersample 1
    scores = {}
    for k in (1, 2):
        assert main(["eval", str(pipeline_layout), "--max-size", str(half), "--supersample", str(k), "--json"]) == 0
        scores[k] = json.loads(capsys.readouterr().out)
        assert scores[k]["supersample"] == k and scores[k]["sizes"] == [f"{half}x{half}"]
    assert scores[1]["psnr"] != scores[2]["psnr"]
    assert main(["eval", str(pipeline_layout), "--supersample", "0"]) == 2  # one line naming the parameter
    assert "supersample" in capsys.readouterr().err

    assert main(["eval", str(pipeline_layout), "--pictures", "--json"]) == 0  # photograph | render | error, each view
    pictures = json.loads(capsys.readouterr().out)["pictures"]
    assert pictures["files"] == [f"view_{v['view']:04d}.png" for v in result["per_view"]]
    for view, name in zip(result["per_view"], pictures["files"]):
        strip = iio.imread(pipeline_layout / "train" / "eval" / name)
        assert strip.shape == (SIZE, 3 * SIZE, 3)
        check_strip(strip, view)


def test_held_out_picture_keeps_a_few_views_at_a_bounded_width(tiny_npz, tmp_path, monkeypatch):
    import imageio.v3 as iio

    from nerfpipe.training import evaluation

    monkeypatch.setattr(evaluation, "HELD_OUT_ROWS", 1)
    monkeypatch.setattr(evaluation, "HELD_OUT_WIDTH", 3 * SIZE // 2)  # rows twice too wide: 2x2 means
    run = tmp_path / "run"
    assert main(["train", str(tiny_npz), "--model", "vanilla", "--out", str(run), "--iters", "2", "--rays-per-step", "32",
                 "--model.num-samples", "8", "--video-frames", "0", "--eval-every", "0"]) == 0
    held_out = iio.imread(run / "held_out.png")
    assert held_out.shape == (SIZE // 2, 3 * SIZE // 2, 3)  # one view of two
    view = json.loads((run / "history.json").read_text())["val"][-1]
    assert view["views"] == 2
    scene = load(tiny_npz)
    gt = evaluation.ground_truth(scene, evaluation.eval_views(scene)[0], torch.zeros(3), (SIZE, SIZE))
    means = F.avg_pool2d(gt.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0).numpy()
    assert np.abs(held_out[:, : SIZE // 2].astype(int) - np.round(means * 255).astype(int)).max() <= 1


def test_pictures_show_the_render_the_appearance_fitted_figure_scores(tiny_npz, tmp_path, monkeypatch, capsys):
    """For a model that fits each held-out view's appearance (photo collections), ``eval --pictures`` and
    ``held_out.png`` show the render in that appearance, whose right half the appearance-fitted figure scores."""
    import imageio.v3 as iio

    from nerfpipe.training import evaluation

    run = tmp_path / "run"
    assert main(["train", str(tiny_npz), "--model", "vanilla", "--out", str(run), "--iters", "2", "--rays-per-step", "32",
                 "--model.num-samples", "8", "--video-frames", "0", "--eval-every", "0"]) == 0
    capsys.readouterr()
    shade = torch.tensor([0.25, 0.5, 0.75])  # a stand-in for the fitted render: one colour, easy to find

    def fitted(model, rays, gt, background, chunk, whole=True):
        return 17.0, shade.expand(*rays.shape, 3).clone()

    monkeypatch.setattr(evaluation, "appearance_fitted_view", fitted)
    assert main(["eval", str(run), "--pictures", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["psnr_appearance_fitted"] == 17.0 and result["pictures"]["render"].startswith("appearance fitted")
    strip = iio.imread(run / "eval" / result["pictures"]["files"][0])
    middle = strip[:, SIZE : 2 * SIZE].reshape(-1, 3).astype(int)
    assert np.abs(middle - np.round(shade.numpy() * 255).astype(int)).max() <= 1
    assert result["psnr"] < 40.0  # the mean render is scored as before, not the stand-in


def test_error_strip_maps_the_pixel_error_on_one_fixed_scale():
    from matplotlib import colormaps

    from nerfpipe.outputs.colormap import ERROR_MAX, error_strip, pixel_error

    gt = torch.rand(6, 5, 3, generator=torch.Generator().manual_seed(0))
    pred = gt.clone()
    pred[:2] = (gt[:2] + ERROR_MAX).clamp(max=1.0)  # rows 0-1 off (by up to ERROR_MAX per channel), the rest exact
    err = pixel_error(pred, gt)
    assert float((err**2).mean()) == pytest.approx(float(((pred - gt) ** 2).mean()))  # its squared mean is the MSE
    strip = error_strip(pred, gt)
    assert strip.shape == (6, 15, 3) and strip.dtype == np.uint8
    turbo = colormaps["turbo"]
    zero = np.round(np.asarray(turbo(0.0)[:3]) * 255).astype(int)
    assert (strip[2:, 10:].reshape(-1, 3) == zero).all()  # exact pixels: the scale's 0
    expected = np.round(np.asarray(turbo(min(float(err[1, 3]) / ERROR_MAX, 1.0))[:3]) * 255).astype(int)
    assert np.abs(strip[1, 13].astype(int) - expected).max() <= 1
    assert not (strip[:2, 10:].reshape(-1, 3) == zero).all(axis=1).any()  # every wrong pixel off the 0 colour


def test_cli_train_then_render(tiny_npz, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", str(tiny_npz), "--model", "vanilla", "--out", str(run), "--iters", "2", "--rays-per-step", "32", "--model.num-samples", "8", "--video-frames", "0", "--eval-every", "0"]
    assert main(args) == 0
    assert main(["render", str(run), "--path", "orbit", "--depth", "--size", "12x10", "--frames", "2", "--background", "white"]) == 0
    import imageio.v3 as iio

    frames = iio.imread(run / "render" / "orbit.gif")
    assert frames.shape[:3] == (2, 10, 12)
    assert (run / "render" / "depth_orbit.gif").is_file() and (run / "render" / "orbit.mp4").is_file()
    assert main(["render", str(run), "--size", "12"]) == 2  # bad size: one-line user error
    assert "--size must be WxH" in capsys.readouterr().err


def test_rgba_targets_use_the_batch_background():
    from nerfpipe.data.background import background_colors, composite_pixels, backgrounds

    px = torch.tensor([[255, 0, 0, 255], [0, 255, 0, 0], [0, 0, 255, 128]], dtype=torch.uint8)
    bg = background_colors("random", 3, torch.Generator().manual_seed(0))
    out = composite_pixels(px, bg)
    torch.testing.assert_close(out[0], torch.tensor([1.0, 0.0, 0.0]))  # opaque: its own colour
    torch.testing.assert_close(out[1], bg[1])  # transparent: the background
    a = 128 / 255
    torch.testing.assert_close(out[2], torch.tensor([0.0, 0.0, a]) + (1 - a) * bg[2])
    assert not torch.equal(bg[0], bg[1])  # random per ray
    assert backgrounds("auto", True) == ("random", "white") and backgrounds("auto", False) == ("black", "black")
    assert backgrounds("auto", False, surroundings=True) == ("grey", "grey")  # a real capture: photographs of more than the box
    assert backgrounds("auto", True, surroundings=True) == ("random", "white")  # alpha decides first
    assert backgrounds("black", False, surroundings=True) == ("black", "black")  # a chosen colour stays
    assert background_colors("white", 2).tolist() == [[1.0, 1.0, 1.0]] * 2
    assert background_colors("grey", 2).tolist() == [[0.5, 0.5, 0.5]] * 2


def test_stale_optimizer_state_of_resized_parameters_is_dropped():
    from nerfpipe.training.trainer import drop_stale_optimizer_state

    keep, resized = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(4))
    opt = torch.optim.Adam([keep, resized], lr=0.1)
    (keep.sum() + resized.sum()).backward()
    opt.step()
    resized.data = torch.ones(6)  # a model resampled this grid
    resized.grad = torch.ones(6)
    drop_stale_optimizer_state(opt)
    assert opt.state[resized] == {} and opt.state[keep]["exp_avg"].shape == (3,)
    opt.step()  # would raise on the shape mismatch without the drop
    assert opt.state[resized]["exp_avg"].shape == (6,)


def test_cpu_clock_budget_counts_process_seconds(tiny_scene, tmp_path, monkeypatch):
    import time as time_module

    cpu = iter(range(0, 10_000, 3))  # every reading of the CPU clock advances it by 3 s
    monkeypatch.setattr(time_module, "process_time", lambda: float(next(cpu)))
    t = Trainer(tcfg(iters=100, train_budget=10.0, clock="cpu", eval_every=0), tiny_scene, "vanilla", MODEL, tmp_path)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    t.train()
    assert t.step == 4 and t.train_seconds == 12.0  # 3 CPU seconds per step, stopped once 10 were spent
    with pytest.raises(NerfpipeError, match="--clock must be wall or cpu"):
        tcfg(clock="sundial")


def test_a_budget_not_an_iteration_count_ends_a_budgeted_run(tiny_scene, tmp_path):
    """Without ``iters``: 1,000 iterations without a budget, no cap under one (an H100 ended a 150 s budget on lego_200
    after 70 s at the old cap); a set ``iters`` caps either."""
    from nerfpipe.training.trainer import DEFAULT_ITERS

    assert TrainerConfig().max_iters == DEFAULT_ITERS == 1000
    assert TrainerConfig(iters=5, time_budget=60.0).max_iters == 5
    for budget in (dict(time_budget=3600.0), dict(train_budget=3600.0)):
        assert TrainerConfig(**budget).max_iters > 10**12
    free = Trainer(tcfg(iters=None), tiny_scene, "vanilla", MODEL, tmp_path / "free")
    budgeted = Trainer(tcfg(iters=None, time_budget=3600.0), tiny_scene, "vanilla", MODEL, tmp_path / "budgeted")
    for t in (free, budgeted):
        t.step = DEFAULT_ITERS
    assert free.done() and not budgeted.done()


def test_held_out_fall_reads_the_intermediate_validations_of_the_same_views():
    """A held-out view whose PSNR falls while training (folded poses) is measured from its best to the last; the
    final evaluation's row (more views) and a rise do not count (``held_out_fall``)."""
    from nerfpipe.training.evaluation import HELD_OUT_FALL_DB, held_out_fall

    fold = [[100, 6.0, 20.84, 0.8, 1], [500, 30.0, 17.63, 0.7, 1], [800, 50.0, 16.54, 0.7, 1], [890, 55.0, 20.41, 0.8, 3]]
    assert held_out_fall(fold) == pytest.approx(20.84 - 16.54) and held_out_fall(fold) >= HELD_OUT_FALL_DB
    right = [[100, 11.0, 22.54, 0.87, 1], [600, 73.0, 26.02, 0.93, 1], [915, 129.0, 24.74, 0.93, 7]]
    assert held_out_fall(right) == 0.0
    assert held_out_fall(right[:1]) == 0.0 and held_out_fall([]) == 0.0


def test_the_trainer_hands_its_batch_to_the_learning_rates(tiny_scene, tmp_path):
    """The fast model's rates follow the trainer's rays per step (``FastConfig.lr_reference_rays``): 128 rays at a
    reference of 32 take twice each rate, as the schedule's ``initial_lr`` too."""
    from nerfpipe.models.fast import FastConfig

    cfg = FastConfig(preset="small", lr_reference_rays=32)
    t = Trainer(tcfg(rays_per_step=128), tiny_scene, "fast", cfg, tmp_path)
    given = [g["lr"] for g in t.model.param_groups()]
    assert [g["initial_lr"] for g in t.optimizer.param_groups] == pytest.approx([2 * lr for lr in given])
    assert given[0] == cfg.grid_lr and t.model.stats()["lr_batch_scale"] == 2.0
