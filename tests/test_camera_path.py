"""Camera path files (nerfstudio's camera_path.json): round trips, the nerfstudio reading, interpolation, bad files."""

import json
import math

import pytest
import torch

from nerfpipe.data.camera_path import (
    CameraPath, Keyframe, from_json, interpolate_keyframes, matrix_to_wxyz, path_from_keyframes, read_camera_path,
    to_json, write_camera_path, wxyz_to_matrix,
)  # fmt: skip
from nerfpipe.data.cameras import Cameras
from nerfpipe.data.orbit import look_at
from nerfpipe.functional.distortion import Distortion
from nerfpipe.util.errors import NerfpipeError


def _rotations(n: int, seed: int = 0) -> torch.Tensor:
    q = torch.randn(n, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return wxyz_to_matrix(q)


def _cameras(n: int = 5) -> Cameras:
    """Real-camera intrinsics: non-square pixels, off-centre principal points, sizes and distortion differing."""
    m = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    m[:, :3, :3] = _rotations(n)
    m[:, :3, 3] = torch.randn(n, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 3
    ar = torch.arange(n, dtype=torch.float64)
    return Cameras.create(m, 300 + ar, 310 + 2 * ar, 161.5 - ar, 118.25 + ar, 320 + 2 * torch.arange(n), 240 - torch.arange(n),
                          distortion=torch.tensor([int(Distortion.OPENCV)] * (n - 1) + [int(Distortion.NONE)]),
                          dist_params=torch.tensor([0.01, -0.002, 0.0005, 0.0001], dtype=torch.float64), dtype=torch.float64)  # fmt: skip


def test_quaternions_match_scipy():
    from scipy.spatial.transform import Rotation

    rot = _rotations(200, seed=2)
    ours = matrix_to_wxyz(rot)
    ref = torch.as_tensor(Rotation.from_matrix(rot.numpy()).as_quat(scalar_first=True))
    ref = torch.where(ref[:, :1] < 0, -ref, ref)
    torch.testing.assert_close(ours, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(wxyz_to_matrix(ours), rot, atol=1e-12, rtol=0)
    near_pi = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))  # 180 degrees: the trace is -1
    torch.testing.assert_close(wxyz_to_matrix(matrix_to_wxyz(near_pi)), near_pi, atol=1e-12, rtol=0)


def test_round_trip_through_the_file_keeps_poses_and_intrinsics(tmp_path):
    cams = _cameras()
    file = write_camera_path(tmp_path / "camera_path.json", CameraPath(cams, [], fps=30.0))
    back = read_camera_path(file)
    for name in ("world_from_cam", "fx", "fy", "cx", "cy", "dist_params"):
        torch.testing.assert_close(getattr(back.cameras, name), getattr(cams, name), atol=1e-12, rtol=0, msg=name)
    assert back.cameras.width.tolist() == cams.width.tolist() and back.cameras.height.tolist() == cams.height.tolist()
    assert back.cameras.distortion.tolist() == cams.distortion.tolist() and back.fps == 30.0


def test_file_is_nerfstudios_opengl_row_major_with_vertical_fov_degrees():
    """A camera at (1, 2, 3) looking along world +y with image up +z: in nerfstudio's terms its
    camera_to_world has columns right, up, backward (OpenGL) and is written row by row."""
    m = look_at(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), torch.tensor([1.0, 5.0, 3.0], dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    cams = Cameras.create(m[None], 100.0, 100.0, 64.0, 48.0, 128, 96, dtype=torch.float64)
    frame = to_json(CameraPath(cams, []))["camera_path"][0]
    gl = torch.tensor(frame["camera_to_world"], dtype=torch.float64).reshape(4, 4)
    torch.testing.assert_close(gl[:3, 0], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))  # right
    torch.testing.assert_close(gl[:3, 1], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))  # up
    torch.testing.assert_close(gl[:3, 2], torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))  # backward
    torch.testing.assert_close(gl[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    assert frame["fov"] == pytest.approx(math.degrees(2 * math.atan(48 / 100))) and frame["aspect"] == pytest.approx(128 / 96)


def test_a_nerfstudio_file_reads_as_nerfstudio_renders_it():
    """Without our extras: fx = fy = (H/2) / tan(fov/2), principal point at the centre, render size from the file."""
    m = look_at(torch.tensor([0.0, -4.0, 1.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    data = to_json(CameraPath(Cameras.create(m[None], 50.0, 50.0, 10.0, 10.0, 20, 20, dtype=torch.float64), []))
    frame = data["camera_path"][0]
    del frame["nerfpipe"]
    frame["fov"] = 60.0
    data.update(render_width=200, render_height=100)
    cams = from_json(data).cameras
    f = 50 / math.tan(math.radians(30))
    assert (cams.fx.item(), cams.fy.item(), cams.cx.item(), cams.cy.item(), cams.width.item(), cams.height.item()) == pytest.approx((f, f, 100, 50, 200, 100))
    torch.testing.assert_close(cams.world_from_cam[0], m)


def test_keyframes_round_trip_and_the_path_passes_through_them(tmp_path):
    eyes = torch.tensor([[4.0, 0, 1], [0, 4, 2], [-4, 0, 1], [0, -4, 0.5]], dtype=torch.float64)
    m = look_at(eyes, torch.zeros_like(eyes), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    keys = [Keyframe(m[i], 0.6 + 0.1 * i, 1.5) for i in range(4)]
    cams = path_from_keyframes(keys, 96, 64, num_frames=3 * 3 + 1)
    for i, k in enumerate(keys):  # frame 3i is keyframe i
        torch.testing.assert_close(cams.world_from_cam[3 * i], k.world_from_cam, atol=1e-12, rtol=0)
        assert float(2 * torch.atan(32 / cams.fy[3 * i])) == pytest.approx(k.fov)
    rot = cams.world_from_cam[:, :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(rot), atol=1e-12, rtol=0)
    back = read_camera_path(write_camera_path(tmp_path / "p.json", CameraPath(cams, keys, is_cycle=False)))
    for k, b in zip(keys, back.keyframes):
        torch.testing.assert_close(b.world_from_cam, k.world_from_cam, atol=1e-12, rtol=0)
        assert (b.fov, b.aspect) == pytest.approx((k.fov, k.aspect))


def test_a_cycle_comes_back_to_its_start_and_one_keyframe_stands_still():
    eyes = torch.tensor([[4.0, 0, 1], [0, 4, 1], [-4, 0, 1]], dtype=torch.float64)
    m = look_at(eyes, torch.zeros_like(eyes), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    keys = [Keyframe(m[i], 0.7, 1.0) for i in range(3)]
    pose, _ = interpolate_keyframes(keys, 30, is_cycle=True)
    torch.testing.assert_close(pose[0], m[0], atol=1e-12, rtol=0)
    step = (pose[1:, :3, 3] - pose[:-1, :3, 3]).norm(dim=-1)
    closing = (pose[0, :3, 3] - pose[-1, :3, 3]).norm()
    assert 0.2 * float(step.mean()) < float(closing) <= float(step.max())  # the last frame is one step before the first: no jump, no repeat
    still, fov = interpolate_keyframes(keys[:1], 5)
    torch.testing.assert_close(still, m[:1].expand(5, 4, 4), atol=1e-12, rtol=0)
    assert fov.tolist() == pytest.approx([0.7] * 5)


@pytest.mark.parametrize(
    "content, message",
    [
        ("not json", "cannot read the camera path"),
        ("[1, 2]", "not a camera path"),
        ('{"render_width": 10, "render_height": 10, "camera_path": []}', "non-empty list"),
        ('{"render_width": 10, "render_height": 10, "camera_path": [{"camera_to_world": [1, 2], "fov": 50}]}', "16 numbers"),
        ('{"render_width": 10, "render_height": 10, "camera_path": [{"camera_to_world": [2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov": 50}]}', "not a rigid"),
        ('{"render_width": 10, "render_height": 10, "camera_path": [{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov": 190}]}', "below 180"),
        ('{"render_width": -3, "render_height": 10, "camera_path": [{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov": 50}]}', "render_width"),
        ('{"camera_type": "fisheye", "camera_path": [{}]}', "perspective only"),
    ],
)
def test_bad_files_are_one_line_naming_the_file(tmp_path, content, message):
    file = tmp_path / "bad.json"
    file.write_text(content)
    with pytest.raises(NerfpipeError, match=message) as info:
        read_camera_path(file)
    assert str(file) in str(info.value)


def test_the_file_is_plain_json_with_the_world_frame_recorded(tmp_path):
    file = write_camera_path(tmp_path / "p.json", CameraPath(_cameras(2), []), torch.eye(4, dtype=torch.float64) * 2)
    data = json.loads(file.read_text())
    assert data["camera_type"] == "perspective" and len(data["camera_path"]) == 2
    assert data["nerfpipe"]["world_from_input"][0] == 2.0
