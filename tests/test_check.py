"""``nerfpipe check``: kornia agreement, round trip, COLMAP reprojection, and that it can fail."""

import json

import numpy as np
import pytest
import torch

pytest.importorskip("kornia")
pycolmap = pytest.importorskip("pycolmap")

from nerfpipe import data_adapters  # noqa: E402
from colmap_synth import make_scene  # noqa: E402
from nerfpipe.cli import main  # noqa: E402
from nerfpipe.data import consistency  # noqa: E402
from nerfpipe.data.cameras import opengl_to_opencv  # noqa: E402
from nerfpipe.data.consistency import MAX_PX, REPROJ_AGREE_PX, check_scene  # noqa: E402
from nerfpipe.data.rays import generate_rays  # noqa: E402


def _pycolmap_reprojection(rec) -> np.ndarray:
    """Per-observation reprojection errors computed by pycolmap alone (the reference)."""
    errs = []
    for i in rec.reg_image_ids():
        im = rec.image(i)
        obs = im.get_observation_points2D()
        xyz = np.array([rec.points3D[p.point3D_id].xyz for p in obs])
        m = im.cam_from_world().matrix()
        uv = rec.camera(im.camera_id).img_from_cam(xyz @ m[:, :3].T + m[:, 3], check_cheirality=False)
        errs.append(np.linalg.norm(uv - np.array([p.xy for p in obs]), axis=-1))
    return np.concatenate(errs)


def _assert_passes(report):
    assert report.failures == []
    assert report.kornia_max_px <= MAX_PX and report.kornia_unproject_max_px <= MAX_PX
    assert report.roundtrip_max_px <= MAX_PX
    assert report.facing_fraction == 1.0 and report.points_in_front_fraction == 1.0


@pytest.fixture(scope="module")
def mouse(scene_path):
    return data_adapters.load(scene_path("colmap_mouse"))


def test_colmap_mouse(mouse, scene_path):
    report = check_scene(mouse, samples=8)
    _assert_passes(report)
    rec = pycolmap.Reconstruction(str(scene_path("colmap_mouse") / "sparse" / "0"))
    ref = _pycolmap_reprojection(rec)
    assert report.reproj_mean_px == pytest.approx(ref.mean(), abs=REPROJ_AGREE_PX)
    assert report.reproj_median_px == pytest.approx(np.median(ref), abs=REPROJ_AGREE_PX)
    assert report.reproj_point_mean_px == pytest.approx(rec.compute_mean_reprojection_error(), abs=REPROJ_AGREE_PX)


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE", "SIMPLE_RADIAL"])
def test_synthetic_distorted(tmp_path, model):
    scene = data_adapters.load(make_scene(tmp_path, model, frames=8, points=100))
    report = check_scene(scene, samples=8)
    _assert_passes(report)
    assert report.reproj_mean_px < 1e-3  # synthetic observations are exact projections
    assert report.fisheye_checked_by_kornia == (True if model == "OPENCV_FISHEYE" else None)


def test_kornia_agrees_with_nerfpipe_distortion(tmp_path):
    """Independent of the probes: kornia's projection of random points equals Cameras.project."""
    scene = data_adapters.load(make_scene(tmp_path, "OPENCV", frames=4, points=10))
    cams, _ = consistency.orthonormalized(scene.cameras)
    idx = torch.arange(4).repeat_interleave(50)
    per = cams[idx]
    noise = torch.randn(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    pts = per.centers + 3.0 * per.forward + noise
    uv_n, z = per.project(pts)
    keep = z > 0.5
    torch.testing.assert_close(consistency.kornia_project(per[keep], pts[keep]), uv_n[keep], atol=1e-7, rtol=0)


def test_detects_opengl_axes(mouse):
    """Cameras left in OpenGL axes look away from the scene and see points behind them."""
    broken = data_adapters.load(mouse.source)
    broken.cameras.world_from_cam = opengl_to_opencv(broken.cameras.world_from_cam)
    report = check_scene(broken, samples=2)
    assert report.facing_fraction < 0.5 and report.points_in_front_fraction < 0.5
    assert len(report.failures) >= 2


def test_detects_half_pixel_slip(mouse, monkeypatch):
    """A ray generator that forgets the (0.5, 0.5) pixel centre fails kornia and the round trip;
    a principal point moved by half a pixel fails the COLMAP reprojection."""
    monkeypatch.setattr(consistency, "generate_rays", lambda cams, idx, uv: generate_rays(cams, idx, uv - 0.5))
    report = check_scene(mouse, samples=2)
    assert report.kornia_max_px > 0.4 and report.roundtrip_max_px > 0.4 and len(report.failures) >= 2
    monkeypatch.undo()
    shifted = data_adapters.load(mouse.source)
    shifted.cameras.cx += 0.5
    shifted.cameras.cy += 0.5
    report = check_scene(shifted, samples=2)
    assert abs(report.reproj_point_mean_px - report.colmap_reported_mean_px) > REPROJ_AGREE_PX
    assert any("differs from COLMAP" in f for f in report.failures)


def test_cli_json_and_exit_codes(tmp_path, capsys, monkeypatch):
    root = make_scene(tmp_path, "OPENCV", frames=8, points=50)
    assert main(["check", "--json", "--samples", "4", str(root)]) == 0
    figures = json.loads(capsys.readouterr().out)
    for key in ("kornia_max_px", "roundtrip_max_px", "reproj_mean_px", "reproj_median_px"):
        assert figures[key] <= MAX_PX
    assert main(["info", "--json", str(root)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "colmap" and info["splits"] == {"train": 7, "val": 1, "test": 0}
    assert info["camera_models"] == {"OPENCV": 8} and info["image_sizes"] == {"64x48": 8}
    assert info["num_sparse_points"] == 50
    real_load = data_adapters.load

    def load_flipped(path):
        scene = real_load(path)
        scene.cameras.world_from_cam = opengl_to_opencv(scene.cameras.world_from_cam)
        return scene

    monkeypatch.setattr(data_adapters, "load", load_flipped)
    assert main(["check", "--samples", "2", str(root)]) == 1
    assert "FAILED" in capsys.readouterr().out


def test_the_command_hands_the_thread_count_back(tmp_path, capsys):
    """Called from another pipeline's Python, ``check`` (which runs on at most 2 threads) leaves the
    caller's thread count as it found it."""
    import torch

    from nerfpipe.commands.check import check

    root = make_scene(tmp_path, "OPENCV", frames=4, points=20)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        assert check(str(root), json=True, samples=2) == 0
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)
    capsys.readouterr()
