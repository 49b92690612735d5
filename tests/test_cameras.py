"""The camera model and rays: conventions, golden values, and a slow per-pixel reference."""

import math

import numpy as np
import pytest
import torch
from scipy.optimize import fsolve

import nerfpipe
from nerfpipe import Cameras, Distortion, Similarity, camera_rays, generate_rays, invert_rigid, opengl_to_opencv, pixel_centers
from nerfpipe.data.normalize import TARGET_CAMERA_DISTANCE, auto_normalization, bounds_from_cameras, focus_point, rotation_to_z, upright_direction
from nerfpipe.functional.distortion import distort_opencv


def random_rotation(gen, dtype=torch.float64):
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=dtype))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def random_pose(gen, dtype=torch.float64):
    m = torch.eye(4, dtype=dtype)
    m[:3, :3] = random_rotation(gen, dtype)
    m[:3, 3] = torch.randn(3, generator=gen, dtype=dtype)
    return m


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """OpenCV world_from_cam looking from eye at target, with world up mapped to image up (-y)."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    z = torch.nn.functional.normalize(target - eye, dim=0)
    x = torch.nn.functional.normalize(torch.linalg.cross(z, up), dim=0)
    y = torch.linalg.cross(z, x)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def test_public_api_resolves():
    for name in nerfpipe.__all__:
        assert getattr(nerfpipe, name) is not None, name


def test_opengl_to_opencv_golden():
    gl = torch.eye(4)
    gl[:3, 3] = torch.tensor([0.0, 0.0, 4.0])  # Blender camera at +z looking down -z at the origin
    cv = opengl_to_opencv(gl)
    assert cv[:3, 2].tolist() == [0.0, 0.0, -1.0]  # OpenCV forward (+z) now points at the origin
    assert cv[:3, 1].tolist() == [0.0, -1.0, 0.0]  # image down is world -y (world +y is up in the picture)
    assert cv[:3, 3].tolist() == [0.0, 0.0, 4.0]


def test_invert_rigid_matches_inverse():
    gen = torch.Generator().manual_seed(0)
    m = torch.stack([random_pose(gen) for _ in range(5)])
    torch.testing.assert_close(invert_rigid(m), torch.linalg.inv(m))


def test_principal_point_ray_is_optical_axis():
    pose = look_at((3.0, -2.0, 1.0))
    cams = Cameras.create(pose[None], 300.0, 310.0, 64.0, 48.0, 128, 96, dtype=torch.float64)
    rays = generate_rays(cams, torch.tensor([0]), torch.tensor([[64.0, 48.0]], dtype=torch.float64))
    torch.testing.assert_close(rays.directions[0], pose[:3, 2])
    torch.testing.assert_close(rays.origins[0], pose[:3, 3])


def test_pixel_centre_convention_golden():
    """Top-left pixel (0, 0) has its centre at (0.5, 0.5); its ray direction in camera axes is known."""
    cams = Cameras.create(torch.eye(4, dtype=torch.float64)[None], 100.0, 200.0, 2.0, 1.0, 4, 2, dtype=torch.float64)
    rays = camera_rays(cams, 0)
    assert rays.shape == (2, 4)
    expected = torch.tensor([(0.5 - 2.0) / 100.0, (0.5 - 1.0) / 200.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(rays.directions[0, 0], expected / expected.norm())
    # +x right, +y down: the bottom-right pixel's ray points right and down.
    assert rays.directions[1, 3, 0] > 0 and rays.directions[1, 3, 1] > 0
    assert pixel_centers(2, 4)[1, 3].tolist() == [3.5, 1.5]


def _slow_ray(pose, fx, fy, cx, cy, params, u, v):
    """Per-pixel reference: solve distort(x) = normalised pixel with a root finder, rotate by hand."""
    target = np.array([(u - cx) / fx, (v - cy) / fy])
    f = lambda q: distort_opencv(torch.tensor(q)[None], torch.tensor(params)[None])[0].numpy() - target  # noqa: E731
    x, y = fsolve(f, target, xtol=1e-13)
    d = np.array([x, y, 1.0])
    d = d / np.linalg.norm(d)
    p = pose.numpy()
    return p[:3, 3], p[:3, :3] @ d


def test_rays_match_slow_reference_with_distortion_and_mixed_sizes():
    gen = torch.Generator().manual_seed(1)
    poses = torch.stack([random_pose(gen) for _ in range(2)])
    params = torch.tensor([[0.0578421, -0.0805099, -0.000980296, 0.00015575], [-0.2, 0.05, 0.001, 0.002]], dtype=torch.float64)
    cams = Cameras.create(
        poses, [1375.5, 700.0], [1374.5, 705.0], [554.6, 320.0], [965.3, 240.0], [1080, 640], [1920, 480],
        distortion=torch.tensor([1, 1]), dist_params=params, dtype=torch.float64,
    )
    cam_idx = torch.tensor([0, 0, 0, 1, 1, 1])
    uv = torch.tensor([[0.5, 0.5], [1079.5, 1919.5], [540.0, 960.0], [0.5, 479.5], [639.5, 0.5], [100.25, 200.75]], dtype=torch.float64)
    rays = generate_rays(cams, cam_idx, uv)
    for i in range(len(uv)):
        c = int(cam_idx[i])
        o, d = _slow_ray(poses[c], float(cams.fx[c]), float(cams.fy[c]), float(cams.cx[c]), float(cams.cy[c]), params[c].tolist(), *uv[i].tolist())
        np.testing.assert_allclose(rays.origins[i].numpy(), o, atol=1e-12)
        np.testing.assert_allclose(rays.directions[i].numpy(), d, atol=1e-10)


@pytest.mark.parametrize("kind", [Distortion.NONE, Distortion.OPENCV, Distortion.FISHEYE])
def test_pixel_ray_point_pixel_round_trip(kind, dtype):
    gen = torch.Generator().manual_seed(2)
    params = {Distortion.NONE: [0, 0, 0, 0], Distortion.OPENCV: [-0.056, 0.205, 0.00084, -2.2e-5], Distortion.FISHEYE: [0.05, -0.01, 0.002, -0.0005]}[kind]
    cams = Cameras.create(torch.stack([random_pose(gen), random_pose(gen)]), 500.0, 510.0, 320.0, 240.0, 640, 480,
                          distortion=int(kind), dist_params=params, dtype=dtype)
    n = 200
    cam_idx = torch.randint(0, 2, (n,), generator=gen)
    uv = torch.rand(n, 2, generator=gen, dtype=dtype) * torch.tensor([640.0, 480.0], dtype=dtype)
    rays = generate_rays(cams, cam_idx, uv)
    t = 0.5 + 10 * torch.rand(n, generator=gen, dtype=dtype)
    pix, z = cams[cam_idx].project(rays.points_at(t))
    atol = 1e-3 if dtype == torch.float32 else 1e-8
    torch.testing.assert_close(pix, uv, rtol=0, atol=atol)
    torch.testing.assert_close(z, t * rays.z_scale, rtol=1e-5 if dtype == torch.float32 else 1e-10, atol=0)
    assert rays.shape == (n,)


@pytest.mark.parametrize("shape", [(), (1,), (2, 3)])
def test_cameras_batch_shapes(shape):
    m = torch.eye(4).expand(*shape, 4, 4)
    cams = Cameras.create(m, 100.0, 100.0, 50.0, 50.0, 100, 80)
    assert cams.shape == shape
    assert cams.K.shape == (*shape, 3, 3)
    assert cams.centers.shape == (*shape, 3)
    if shape == (2, 3):
        assert cams[1].shape == (3,)
        assert cams.reshape(6).shape == (6,)
        assert cams.to(dtype=torch.float64).fx.dtype == torch.float64
        assert cams.to(dtype=torch.float64).width.dtype == torch.long


def test_similarity_inverse_compose_and_poses():
    gen = torch.Generator().manual_seed(3)
    s = Similarity(random_rotation(gen), torch.randn(3, generator=gen, dtype=torch.float64), 2.5)
    x = torch.randn(10, 3, dtype=torch.float64, generator=gen)
    torch.testing.assert_close(s.inverse().apply_points(s.apply_points(x)), x)
    torch.testing.assert_close(s.compose(s.inverse()).matrix(), torch.eye(4, dtype=torch.float64))
    pose = random_pose(gen)
    moved = s.apply_world_from_cam(pose)
    torch.testing.assert_close(moved[:3, :3] @ moved[:3, :3].T, torch.eye(3, dtype=torch.float64))
    # A point seen by the camera keeps its camera coordinates up to the scale.
    p_cam = torch.tensor([0.1, -0.2, 3.0], dtype=torch.float64)
    p_world = pose[:3, :3] @ p_cam + pose[:3, 3]
    p_cam_new = invert_rigid(moved)[:3, :3] @ s.apply_points(p_world) + invert_rigid(moved)[:3, 3]
    torch.testing.assert_close(p_cam_new, 2.5 * p_cam)


def test_auto_normalization_centres_scales_and_uprights():
    ring = [look_at((5 * math.cos(a) + 1, 5 * math.sin(a) - 2, 7.0), target=(1.0, -2.0, 4.0), up=(0.0, 0.0, 1.0)) for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)]
    tilt = Similarity(rotation_to_z(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)).T, torch.zeros(3, dtype=torch.float64), 0.37)
    poses = tilt.apply_world_from_cam(torch.stack(ring))
    cams = Cameras.create(poses, 100.0, 100.0, 50.0, 50.0, 100, 100, dtype=torch.float64)
    norm = auto_normalization(cams)
    new = Cameras.create(norm.apply_world_from_cam(poses), 100.0, 100.0, 50.0, 50.0, 100, 100, dtype=torch.float64)
    torch.testing.assert_close(focus_point(new), torch.zeros(3, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(new.centers.norm(dim=-1).mean(), torch.tensor(TARGET_CAMERA_DISTANCE, dtype=torch.float64))
    up = -new.world_from_cam[:, :3, 1].mean(0)
    assert float(up[2] / up.norm()) > 0.999  # mean camera up is +z
    near, far, aabb = bounds_from_cameras(new)
    assert 0 < near < TARGET_CAMERA_DISTANCE < far
    assert torch.all(aabb[0] < 0) and torch.all(aabb[1] > 0)


def _angle(a, b) -> float:
    return math.degrees(math.acos(min(1.0, float(a @ b) / float(a.norm() * b.norm()))))


def test_upright_direction_is_the_normal_of_the_right_axes_not_the_mean_image_up():
    """Half a ring of upright cameras looking down at a table (50-70 degrees up) in a tilted world: their
    image-ups lean over the table, their right axes stay horizontal."""
    true_up = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    tilt = Similarity(rotation_to_z(true_up).T, torch.zeros(3, dtype=torch.float64), 1.0)
    ring = [look_at((3 * math.cos(e) * math.cos(a), 3 * math.cos(e) * math.sin(a), 3 * math.sin(e)))
            for a, e in zip(np.linspace(0, math.pi, 9), np.radians(np.linspace(50, 70, 9)))]
    cams = Cameras.create(tilt.apply_world_from_cam(torch.stack(ring)), 100.0, 100.0, 50.0, 50.0, 100, 100, dtype=torch.float64)
    assert _angle(cams.up.mean(0), true_up) > 15  # what the mean image-up gives
    assert _angle(upright_direction(cams), true_up) < 1e-6

    # a third of them portrait photos stored sideways (turned a quarter either way about their optical axis)
    quarter = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    turned = torch.stack(ring).clone()
    for i, turn in ((1, quarter), (4, quarter.T), (7, quarter)):
        turned[i, :3, :3] = turned[i, :3, :3] @ turn
    cams = Cameras.create(tilt.apply_world_from_cam(turned), 100.0, 100.0, 50.0, 50.0, 100, 100, dtype=torch.float64)
    assert _angle(cams.up.mean(0), true_up) > 15
    assert _angle(upright_direction(cams), true_up) < 1e-6

    # half of them, and then all, portrait photos stored sideways (a phone held upright stores its sensor's rows):
    # neither every right axis nor the mean image-up is a start the per-camera choice recovers from
    for sideways in (range(0, 9, 2), range(9)):
        turned = torch.stack(ring).clone()
        for i in sideways:
            turned[i, :3, :3] = turned[i, :3, :3] @ (quarter if i % 4 else quarter.T)
        cams = Cameras.create(tilt.apply_world_from_cam(turned), 100.0, 100.0, 50.0, 50.0, 100, 100, dtype=torch.float64)
        assert _angle(upright_direction(cams), true_up) < 1e-6, list(sideways)  # the sign too: they look down at the table

    # cameras all facing one way (a facade): the right axes decide nothing along the views; the mean image-up stays
    facade = [look_at((x, -5.0, 1.0), target=(x, 0.0, 1.5)) for x in np.linspace(-2, 2, 5)]
    cams = Cameras.create(torch.stack(facade), 100.0, 100.0, 50.0, 50.0, 100, 100, dtype=torch.float64)
    torch.testing.assert_close(upright_direction(cams), torch.nn.functional.normalize(cams.up.mean(0), dim=0))


def test_camera_rays_equals_generate_rays():
    gen = torch.Generator().manual_seed(4)
    cams = Cameras.create(torch.stack([random_pose(gen), random_pose(gen)]), 90.0, 95.0, 30.0, 20.0, [64, 40], [48, 30],
                          distortion=torch.tensor([1, 2]), dist_params=torch.tensor([[-0.1, 0.02, 0.001, 0.0], [0.05, -0.01, 0.0, 0.0]]),
                          dtype=torch.float64)
    for i in range(2):
        fast = camera_rays(cams, i)
        h, w = int(cams.height[i]), int(cams.width[i])
        slow = generate_rays(cams, torch.full((h * w,), i), pixel_centers(h, w, dtype=torch.float64).reshape(-1, 2))
        torch.testing.assert_close(fast.directions.reshape(-1, 3), slow.directions)
        torch.testing.assert_close(fast.origins.reshape(-1, 3), slow.origins)
        torch.testing.assert_close(fast.z_scale.reshape(-1), slow.z_scale)


@pytest.mark.parametrize("distortion", [Distortion.NONE, Distortion.OPENCV])
def test_capped_cameras_see_the_same_rays_through_the_same_image_points(distortion):
    """A camera capped to half its size: the ray through half-size position (u, v) is the full-size camera's ray
    through (2u, 2v) (the same point of the image); cameras already small enough are unchanged."""
    params = [0.1, -0.02, 0.001, 0.002] if distortion == Distortion.OPENCV else None
    cams = Cameras.create(torch.eye(4).expand(2, 4, 4), [800.0, 300.0], [790.0, 300.0], [400.0, 160.0], [300.0, 120.0],
                          [800, 320], [600, 240], distortion, params, dtype=torch.float64)
    half = cams.capped(400)
    assert half.width.tolist() == [400, 320] and half.height.tolist() == [300, 240]  # the second is small enough
    assert torch.equal(half.fx[1], cams.fx[1]) and torch.equal(half.dist_params, cams.dist_params)
    uv = torch.tensor([[10.5, 20.5], [399.5, 0.5], [200.0, 150.0]], dtype=torch.float64)
    idx = torch.zeros(3, dtype=torch.long)
    small, full = generate_rays(half, idx, uv), generate_rays(cams, idx, 2 * uv)
    torch.testing.assert_close(small.directions, full.directions, rtol=0, atol=1e-12)
    assert cams.capped(None) is cams
