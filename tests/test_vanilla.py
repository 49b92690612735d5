"""The classic NeRF field and model, the model registry, orbit cameras and the shared renderer."""

import math

import pytest
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.orbit import AROUND_ARC, PHOTO_PATH_SPREAD, distance_spread, look_at, orbit_azimuths, orbit_cameras, photo_path_cameras
from nerfpipe.data.rays import RayBundle
from nerfpipe.fields.vanilla import VanillaField, VanillaFieldConfig
from nerfpipe.models.base import Model, ModelSpec, SceneInfo
from nerfpipe.models.registry import models
from nerfpipe.models.vanilla import VanillaConfig
from nerfpipe.outputs.render import render_cameras

TINY = VanillaFieldConfig(width=16, depth=3, skip=2, head_width=8, pos_frequencies=4, dir_frequencies=2)
INFO = SceneInfo(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=2.0, far=6.0, num_images=1, pixels_per_image=4)


def classic_param_count(w=256, pos=63, dirs=27, head=128):
    trunk = (pos * w + w) + 3 * (w * w + w) + ((w + pos) * w + w) + 3 * (w * w + w)
    return trunk + (w + 1) + (w * w + w) + ((w + dirs) * head + head) + (head * 3 + 3)


def test_field_architecture_is_the_classic_one():
    f = VanillaField()
    assert sum(p.numel() for p in f.parameters()) == classic_param_count()
    assert [l.in_features for l in f.trunk] == [63, 256, 256, 256, 256 + 63, 256, 256, 256]
    assert f.color_hidden.in_features == 256 + 27 and f.color_hidden.out_features == 128


@pytest.mark.parametrize("shape", [(), (1,), (2, 3)])
def test_field_shapes_and_ranges(shape):
    torch.manual_seed(0)
    f = VanillaField(TINY)
    with torch.no_grad():
        f.density_head.bias.fill_(-0.5)  # push pre-activations negative: ReLU must still give >= 0
    pos = torch.randn(*shape, 3)
    dirs = torch.nn.functional.normalize(torch.randn(*shape, 3), dim=-1)
    sigma, rgb = f(pos, dirs)
    assert sigma.shape == shape and rgb.shape == (*shape, 3)
    assert torch.all(sigma >= 0) and torch.all((rgb > 0) & (rgb < 1))
    torch.testing.assert_close(f.density(pos), sigma)


def rays(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    return RayBundle(origins=torch.tensor([0.0, 0.0, -4.0]).expand(n, 3).clone(), directions=d, cam_idx=torch.zeros(n, dtype=torch.long), z_scale=torch.ones(n))


@pytest.mark.parametrize("num_importance", [0, 8])
def test_model_outputs_and_losses(num_importance):
    torch.manual_seed(0)
    model = VanillaConfig(num_samples=8, num_importance=num_importance, field=TINY).setup(INFO)
    assert isinstance(model, Model)
    out = model.get_outputs(rays(), torch.ones(6, 3))
    assert out.rgb.shape == (6, 3) and out.depth.shape == (6,) and out.acc.shape == (6,)
    assert out.num_samples == 6 * (8 + (num_importance and 8 + num_importance))
    losses = model.get_losses(out, torch.zeros(6, 3))
    assert set(losses) == ({"rgb"} | ({"rgb_coarse"} if num_importance else set()))
    sum(losses.values()).backward()
    assert all(p.grad is not None for p in model.parameters())
    model.eval()
    a, b = model.get_outputs(rays(), torch.ones(6, 3)), model.get_outputs(rays(), torch.ones(6, 3))
    assert torch.equal(a.rgb, b.rgb)  # no jitter at evaluation
    assert model.stats()["samples_per_ray"] == 8 + num_importance


def test_registry_has_vanilla():
    found = models()
    assert isinstance(found["vanilla"], ModelSpec)
    assert found["vanilla"].config is VanillaConfig


def test_look_at_and_orbit_are_upright_and_centred():
    ref = Cameras.create(look_at(torch.tensor([4.0, 0.0, 2.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))[None], 50.0, 50.0, 32.0, 24.0, 64, 48)
    center = torch.tensor([0.1, -0.2, 0.3])
    cams = orbit_cameras(ref, center, 12)
    assert cams.shape == (12,)
    rot = cams.world_from_cam[:, :3, :3]
    torch.testing.assert_close(rot.transpose(1, 2) @ rot, torch.eye(3).expand(12, 3, 3), atol=1e-5, rtol=0)
    assert torch.all(torch.det(rot) > 0)
    uv, z = cams.project(center.expand(12, 3))  # the centre lands on the principal point
    torch.testing.assert_close(uv, torch.tensor([32.0, 24.0]).expand(12, 2), atol=1e-3, rtol=0)
    assert torch.all(z > 0)
    assert torch.all(-rot[:, 2, 1] > 0)  # image up (-y) points to world +z
    assert torch.all(rot[:, 2, 0].abs() < 1e-6)  # no roll: image x stays horizontal
    dist = (cams.centers - center).norm(dim=-1)
    expected = float((ref.centers[0] - center).norm())  # same distance and elevation as the reference
    torch.testing.assert_close(dist, torch.full((12,), expected), atol=1e-3, rtol=0)
    torch.testing.assert_close(cams.centers[:, 2], torch.full((12,), 2.0), atol=1e-3, rtol=0)


def test_the_orbit_sweeps_only_the_arc_the_cameras_cover():
    full = torch.linspace(0, 2 * math.pi, 13)[:-1]  # all round: a full circle from the first camera on
    torch.testing.assert_close(orbit_azimuths(full, 24), torch.arange(24, dtype=torch.float64) * (2 * math.pi / 24))
    half = torch.linspace(-0.5, 2.0, 9)  # a 143-degree arc (a forward-facing capture): there and back within it
    path = orbit_azimuths(half, 30)
    span = torch.remainder(path - (2 * math.pi - 0.5), 2 * math.pi)
    assert float(span.max()) == pytest.approx(2.5, abs=1e-9) and float(span.min()) == pytest.approx(0.0, abs=1e-12)
    assert float(span[15]) == pytest.approx(2.5) and float(span[1]) == pytest.approx(float(span[-1]))  # turns at the far end, loops smoothly
    ref = Cameras.create(look_at(torch.stack([4 * torch.cos(half), 4 * torch.sin(half), torch.ones(9)], -1), torch.zeros(9, 3), torch.tensor([0.0, 0.0, 1.0])),
                         50.0, 50.0, 32.0, 24.0, 64, 48)  # fmt: skip
    cams = orbit_cameras(ref, torch.zeros(3), 30)
    az = torch.atan2(cams.centers[:, 1], cams.centers[:, 0])
    assert float(az.min()) >= -0.5 - 1e-4 and float(az.max()) <= 2.0 + 1e-4  # never behind, where no photograph looked


def test_the_orbit_is_framed_as_the_typical_photograph_not_the_first():
    """The path's intrinsics are those of the reference camera of the median field of view, whichever comes first."""
    eyes = torch.tensor([[4.0, 0.0, 2.0], [0.0, 4.0, 2.0], [-4.0, 0.0, 2.0], [0.0, -4.0, 2.0], [3.0, 3.0, 2.0]])
    focal = torch.tensor([20.0, 55.0, 50.0, 60.0, 45.0])  # the first the widest, as colmap_mouse's
    size = torch.tensor([64, 64, 48, 64, 64]), torch.tensor([48, 48, 64, 48, 48])
    ref = Cameras.create(look_at(eyes, torch.zeros(5, 3), torch.tensor([0.0, 0.0, 1.0])), focal, focal, size[0] / 2, size[1] / 2, *size)
    cams = orbit_cameras(ref, torch.zeros(3), 6)
    assert cams.fx.reshape(-1).tolist() == [50.0] * 6  # fov 100/80 = 1.25: the median of 0.5, 1.375, 1.25, 1.5, 1.125
    assert (int(cams.width.reshape(-1)[0]), int(cams.height.reshape(-1)[0])) == (48, 64)  # its size and principal point
    torch.testing.assert_close(cams.cx.reshape(-1), torch.full((6,), 24.0), check_dtype=False)


def test_a_collection_from_near_and_far_gets_a_path_along_its_photographs():
    """Photographs that do not surround their object (arc under AROUND_ARC) taken from near and far (distances spread
    over PHOTO_PATH_SPREAD): frames pass the photographs' own viewpoints, in azimuth order there and back, upright, each
    looking where the photographs near it look, at their field of view. At one distance (a facade, an object on a wall)
    the orbit stays."""
    az = torch.tensor([0.9, 0.1, 0.5, 0.3, 0.7])  # a 46-degree arc, out of order
    dist = torch.tensor([6.0, 3.0, 3.5, 5.0, 3.0])  # near and far photographs, as a collection's
    eyes = torch.stack([dist * torch.cos(az), dist * torch.sin(az), 0.2 * dist], -1)
    targets = torch.tensor([[0.0, 0.0, 0.5]]) + 0.3 * torch.randn(5, 3, generator=torch.Generator().manual_seed(0))
    focal = 10.0 * dist  # the far ones zoomed in
    ref = Cameras.create(look_at(eyes, targets, torch.tensor([0.0, 0.0, 1.0])), focal, focal, 32.0, 24.0, 64, 48)
    center = torch.zeros(3)
    assert torch.equal(orbit_cameras(ref, center, 20).world_from_cam, photo_path_cameras(ref, center, 20).world_from_cam)
    sharp = photo_path_cameras(ref, center, 20, smoothing=1e-3)  # no smoothing: frame 0 and 10 are the end photographs
    order = torch.argsort(az)
    for frame, cam in ((0, int(order[0])), (10, int(order[-1]))):
        torch.testing.assert_close(sharp.centers[frame], eyes[cam], atol=1e-4, rtol=0)
        torch.testing.assert_close(sharp.forward[frame], ref.forward[cam], atol=1e-4, rtol=0)
        torch.testing.assert_close(sharp.fx[frame], focal[cam], atol=1e-3, rtol=0, check_dtype=False)
    cams = photo_path_cameras(ref, center, 40)
    rot = cams.world_from_cam[:, :3, :3]
    torch.testing.assert_close(rot.transpose(1, 2) @ rot, torch.eye(3).expand(40, 3, 3), atol=1e-5, rtol=0)
    assert torch.all(rot[:, 2, 0].abs() < 1e-6) and torch.all(-rot[:, 2, 1] > 0)  # upright, no roll
    path_az = torch.atan2(cams.centers[:, 1], cams.centers[:, 0])
    assert float(path_az.min()) >= 0.1 - 1e-4 and float(path_az.max()) <= 0.9 + 1e-4  # where the photographs stood
    d = (cams.centers - center).norm(dim=-1)
    assert 3.0 * 1.02 - 1e-3 <= float(d.min()) and float(d.max()) <= 6.0 * 1.02 + 1e-3  # between the nearest and the farthest
    assert torch.all((cams.centers[1:] - cams.centers[:-1]).norm(dim=-1) < 1.0)  # smooth: no jumps between frames
    _, z = cams.project(torch.tensor([0.0, 0.0, 0.5]).expand(40, 3))
    assert torch.all(z > 0)  # the scene in front of every frame
    ring = torch.linspace(0, 2 * math.pi, 9)[:-1]  # all round: the orbit, not the photographs' path
    around = Cameras.create(look_at(torch.stack([4 * torch.cos(ring), 4 * torch.sin(ring), torch.ones(8)], -1), torch.zeros(8, 3),
                                    torch.tensor([0.0, 0.0, 1.0])), 50.0, 50.0, 32.0, 24.0, 64, 48)  # fmt: skip
    torch.testing.assert_close((orbit_cameras(around, center, 12).centers - center).norm(dim=-1), torch.full((12,), math.sqrt(17.0)), atol=1e-4, rtol=0)
    assert AROUND_ARC > math.radians(46) and distance_spread(ref, center) > PHOTO_PATH_SPREAD
    steady = Cameras.create(look_at(eyes / dist[:, None] * 4.0, targets, torch.tensor([0.0, 0.0, 1.0])), 40.0, 40.0, 32.0, 24.0, 64, 48)
    torch.testing.assert_close((orbit_cameras(steady, center, 12).centers - center).norm(dim=-1), torch.full((12,), 4.0 * math.sqrt(1.04)),
                               atol=1e-4, rtol=0)  # fmt: skip


def test_render_cameras_is_chunk_invariant():
    torch.manual_seed(0)
    model = VanillaConfig(num_samples=8, field=TINY).setup(INFO)
    ref = Cameras.create(look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))[None], 8.0, 8.0, 4.0, 3.0, 8, 6)
    a = render_cameras(model, ref, chunk=5)[0]
    b = render_cameras(model, ref, chunk=1000)[0]
    assert a.rgb.shape == (6, 8, 3) and a.depth.shape == (6, 8)
    torch.testing.assert_close(a.rgb, b.rgb)
    torch.testing.assert_close(a.depth, b.depth)
    assert model.training  # restored after rendering


def test_depth_colormap_is_monotone_and_marks_background():
    from nerfpipe.outputs.colormap import colorize_depth

    depth = torch.linspace(2.0, 6.0, 5)[None].expand(2, 5).clone()
    acc = torch.ones(2, 5)
    acc[1, 0] = 0.1
    img = colorize_depth(depth, acc, 2.0, 6.0)
    assert img.shape == (2, 5, 3) and img.dtype.name == "uint8"
    assert img[0, 0, 2] > img[0, 0, 0] and img[0, -1, 0] > img[0, -1, 2]  # near blue, far red
    assert img[1, 0].tolist() == [0, 0, 0]
