"""The render stage's budget plan: frames first, then resolution, never past the share of the time left."""

import pytest

from nerfpipe.plugins.render import RenderConfig, frame_size, plan_frames


def test_no_budget_or_enough_time_keeps_the_configured_frames():
    cfg = RenderConfig(frames=60)
    assert plan_frames(cfg, 2.0, None).frames == 60
    plan = plan_frames(cfg, 1.0, 1000.0)  # 60 s needed, 400 s allowed
    assert (plan.frames, plan.scale) == (60, 1.0)


def test_tight_budget_drops_frames_then_resolution():
    cfg = RenderConfig(frames=60, min_frames=12, budget_share=0.5)
    plan = plan_frames(cfg, 1.0, 60.0)  # 30 s allowed: 30 frames at full size
    assert (plan.frames, plan.scale) == (30, 1.0)
    plan = plan_frames(cfg, 1.0, 12.0)  # 6 s allowed: 12 frames need a quarter of the pixels
    assert plan.frames == 12 and plan.scale == pytest.approx(0.5 ** 0.5)
    assert plan.estimated_seconds == pytest.approx(6.0)
    assert plan_frames(cfg, 100.0, 1.0).scale == 0.25  # never below a quarter of the side


@pytest.mark.parametrize("budget", [0.5, 3.0, 50.0, 400.0])
def test_plan_never_exceeds_the_allowed_time_unless_at_the_floor(budget):
    cfg = RenderConfig(frames=60, min_frames=12, budget_share=0.4)
    plan = plan_frames(cfg, 0.7, budget)
    assert 12 <= plan.frames <= 60
    assert plan.estimated_seconds <= 0.4 * budget + 1e-9 or plan.scale == 0.25


def test_frame_size_caps_the_longer_side():
    class Cams:  # only width/height are read
        width, height = [1920], [1440]

    assert frame_size(Cams, RenderConfig(max_size=400), 1.0) == (400, 300)
    assert frame_size(Cams, RenderConfig(max_size=4000, scale=0.5), 0.5) == (480, 360)


def test_the_command_and_the_stage_render_the_same_files(scene_path, tmp_path, capsys):
    """One renderer: ``nerfpipe render RUN`` on a pipeline run gives the stage's frames for the same path
    and options, in the same layout (``render/``), next to what is already there."""
    import json
    import shutil

    import imageio.v3 as iio
    import numpy as np

    from nerfpipe.cli import main
    from nerfpipe.pipeline.stages import Pipeline

    tiny = {"train": {"model": "vanilla", "model_options": {"num_samples": 8, "field": {"width": 16, "depth": 2, "skip": 1,
            "head_width": 16, "pos_frequencies": 2, "dir_frequencies": 1}}, "trainer": {"iters": 2, "rays_per_step": 32,
            "eval_every": 0, "final_eval_views": 1, "eval_scale": 0.1, "write_outputs": False}},
            "render": {"path": "test", "frames": 3, "scale": 0.1, "pngs": True, "background": "white"}}  # fmt: skip
    npz = scene_path("lego_200x200") / "lego_200x200.npz"
    Pipeline(["load", "train", "render"], tiny).run(npz, tmp_path)
    staged = tmp_path / "staged"
    shutil.copytree(tmp_path / "render", staged)
    (tmp_path / "render" / "orbit.gif").write_text("another path's render")  # must stay
    capsys.readouterr()  # what the pipeline logged: stdout is the command's JSON from here
    assert main(["render", str(tmp_path), "--path", "test", "--frames", "3", "--scale", "0.1", "--pngs", "--background", "white", "--device", "cpu"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in (tmp_path / "render").iterdir()) == sorted(["orbit.gif", *(p.name for p in staged.iterdir())])
    assert (tmp_path / "render" / "orbit.gif").read_text() == "another path's render"
    pngs = sorted((staged / "test_frames").iterdir())
    assert len(pngs) == 3 and iio.imread(pngs[0]).shape == (20, 20, 3)
    for png in pngs:
        assert np.array_equal(iio.imread(png), iio.imread(tmp_path / "render" / "test_frames" / png.name))
    ours, theirs = json.loads((tmp_path / "render" / "test.json").read_text()), json.loads((staged / "test.json").read_text())
    assert printed == ours and ours.pop("device") == "cpu" and ours.pop("budget_plan")["frames"] == theirs.pop("budget_plan")["frames"]
    assert ours == {k: v for k, v in theirs.items()} and ours["depth_gif"] == str(tmp_path / "render" / "depth_test.gif")
