"""Supersampled renders: each pixel the mean of k x k rays over its area, against a ray-by-ray reference."""

import math

import numpy as np
import pytest
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import generate_rays
from nerfpipe.models.base import Model, RenderOutputs
from nerfpipe.outputs.render import render_cameras, supersample_factor
from nerfpipe.mesh.views import look_at


class StripesModel(Model):
    """Colour, depth and opacity vary faster than a pixel (stripes over the viewing direction); rays whose opacity is
    below a half do not stop (NaN stop depth)."""

    def get_outputs(self, rays, background):
        d = rays.directions
        s = torch.sin(97.0 * d[:, 0]) * torch.cos(61.0 * d[:, 1])
        acc = 0.5 + 0.5 * s
        rgb = torch.stack([acc, 1.0 - acc, 0.5 + 0.25 * torch.sin(43.0 * d[:, 2])], dim=-1)
        depth = (2.0 + s) * acc
        stop = torch.where(acc > 0.5, 2.0 + s, torch.full_like(s, float("nan")))
        return RenderOutputs(rgb=rgb, depth=depth, acc=acc, stop_depth=stop)


def cameras() -> Cameras:
    mats = [look_at(np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 0.7]), np.zeros(3), np.array([0, 0, 1.0])) for a in (0.3, 2.0)]
    return Cameras.create(np.stack(mats), 40.0, 42.0, 15.5, 11.0, 31, 23)


def reference(model, cams: Cameras, i: int, k: int) -> dict:
    """Ray by ray: for each pixel the rays through the centres of its k x k sub-pixels, then their mean."""
    h, w = int(cams.height[i]), int(cams.width[i])
    sums = {"rgb": torch.zeros(h, w, 3), "depth": torch.zeros(h, w), "acc": torch.zeros(h, w)}
    stops, count = torch.zeros(h, w), torch.zeros(h, w)
    for a in range(k):
        for b in range(k):
            v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
            uv = torch.stack([u + (b + 0.5) / k, v + (a + 0.5) / k], dim=-1)
            rays = generate_rays(cams, torch.full((h, w), i, dtype=torch.long), uv.to(cams.fx.dtype)).reshape(-1)
            out = model.get_outputs(rays, torch.zeros(len(rays), 3))
            for key in sums:
                sums[key] += getattr(out, key).reshape(sums[key].shape) / k**2
            stop = out.stop_depth.reshape(h, w)
            stops += stop.nan_to_num(0.0)
            count += (~torch.isnan(stop)).float()
    sums["stop_depth"] = torch.where(count > 0, stops / count.clamp(min=1), torch.full_like(stops, float("nan")))
    return sums


@pytest.mark.parametrize("k", [1, 2, 3])
def test_supersampled_render_is_the_mean_of_its_sub_pixel_rays(k, device):
    model, cams = StripesModel(), cameras()
    views = render_cameras(model, cams.to(device), chunk=97, supersample=k)
    tol = 1e-5 if torch.device(device).type == "cpu" else 5e-5  # CUDA sums in another order (2.6e-5 seen on an H100)
    for i, view in enumerate(views):
        ref = reference(model, cams, i, k)
        view = type(view)(**{key: getattr(view, key).cpu() for key in ("rgb", "depth", "acc", "stop_depth")})
        assert view.rgb.shape == (23, 31, 3)
        for key in ("rgb", "depth", "acc", "stop_depth"):
            torch.testing.assert_close(getattr(view, key), ref[key].to(getattr(view, key).dtype), rtol=tol, atol=tol, equal_nan=True)
    if k > 1:  # the stripes are finer than a pixel: averaging changes the picture
        assert (views[0].rgb.cpu() - render_cameras(model, cams)[0].rgb).abs().max() > 0.05


def test_supersample_factor_counts_whole_photograph_pixels_per_rendered_pixel():
    assert supersample_factor(400, 1920) == 2 and supersample_factor(400, 1920, limit=8) == 4
    assert supersample_factor(800, 800) == 1 and supersample_factor(801, 1600) == 1 and supersample_factor(10, 5) == 1


def test_render_sequence_supersamples_every_frame_and_records_it():
    from nerfpipe.data.background import background_colors
    from nerfpipe.outputs.novel_views import RenderConfig, path_cameras, render_sequence
    from nerfpipe.outputs.render import resize_cameras
    from tests.test_mesh_command import sphere_scene

    model, scene = StripesModel(), sphere_scene(n=6, size=24)
    cfg = RenderConfig(path="orbit", frames=3, size="20x14", depth=False, supersample=2)
    views, info = render_sequence(model, scene, cfg, background_colors("black", 1)[0], "cpu")
    cams = resize_cameras(path_cameras(scene, cfg, 3), 20, 14)
    assert info["supersample"] == 2 and len(views) == 3
    assert info["along_photographs"] is False  # cameras all round: the orbit (the path it took is recorded)
    for i, view in enumerate(views):
        torch.testing.assert_close(view.rgb, render_cameras(model, cams[i : i + 1], supersample=2)[0].rgb)
        assert not torch.allclose(view.rgb, render_cameras(model, cams[i : i + 1])[0].rgb, atol=0.02)


def test_frame_plans_do_not_shrink_a_views_fixed_cost():
    """A view's appearance fit takes the same time at any size: a plan that shrinks views to fit counts it whole
    (photos_sacre_coeur's final evaluation, its fit scaled down with the view, was estimated at 18.0 s and took 37.2),
    and where fewer views are scored than the plan's least, they are as large as then fits."""
    from nerfpipe.outputs.render import plan_frames
    from nerfpipe.training.evaluation import _fit

    assert plan_frames(2, 2, 10.0, 100.0, fixed_per_frame=20.0).estimated_seconds == pytest.approx(60.0)  # all fit, whole
    plan = plan_frames(2, 2, 10.0, 50.0, fixed_per_frame=20.0)  # 60 s at full size: shrink the render, not the fit
    assert plan.frames == 2 and plan.scale == pytest.approx(0.5**0.5) and plan.estimated_seconds == pytest.approx(50.0)
    assert plan_frames(4, 1, 10.0, 65.0, fixed_per_frame=20.0).frames == 2  # 30 s a view, whole
    assert plan_frames(2, 2, 10.0, 10.0, fixed_per_frame=0.0) == plan_frames(2, 2, 10.0, 10.0)  # no fixed cost: as before
    one = _fit(2, 2, 10.0, 35.0, at_least=1, fixed=30.0)  # two fits do not fit at any size: one view, half its side
    assert (one.frames, one.scale, one.estimated_seconds) == (1, pytest.approx(0.5**0.5), pytest.approx(35.0))
    assert _fit(2, 2, 10.0, 10.0, at_least=1, fixed=30.0).frames == 1  # never fewer than at_least
