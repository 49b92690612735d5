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
