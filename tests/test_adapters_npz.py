"""The npz adapter on the real CS180 lego file, a tiny-NeRF npz made from it, and broken files."""

import math

import numpy as np
import pytest
import torch

from nerfpipe import data_adapters
from nerfpipe.data.cameras import opengl_to_opencv
from nerfpipe.util.errors import NerfpipeError

LEGO_CAMERA_ANGLE_X = 0.6911112070083618  # nerf_synthetic lego, see blender_lego/PROVENANCE.md


@pytest.fixture(scope="module")
def lego_file(scene_path):
    return scene_path("lego_200x200") / "lego_200x200.npz"


@pytest.fixture(scope="module")
def raw(lego_file):
    with np.load(lego_file, allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


@pytest.fixture(scope="module")
def scene(lego_file):
    return data_adapters.load(lego_file)


def _looks_at_origin(cameras) -> float:
    """Mean cosine between each camera's +z axis and the direction to the world origin."""
    to_origin = torch.nn.functional.normalize(-cameras.centers.double(), dim=-1)
    return float((cameras.forward.double() * to_origin).sum(-1).mean())


def test_detects_file_and_folder(lego_file):
    assert data_adapters.detect(lego_file).name == "npz"
    assert data_adapters.detect(lego_file.parent).name == "npz"
    assert data_adapters.load(lego_file.parent).source == lego_file


def test_cs180_splits_and_intrinsics(scene):
    assert {k: len(v) for k, v in scene.splits.items()} == {"train": 100, "val": 10, "test": 60}
    assert len(scene.cameras) == len(scene.images) == 170
    focal = 0.5 * 200 / math.tan(0.5 * LEGO_CAMERA_ANGLE_X)
    assert focal == pytest.approx(277.78, abs=0.01)
    for name, value in [("fx", focal), ("fy", focal), ("cx", 100.0), ("cy", 100.0), ("width", 200), ("height", 200)]:
        assert torch.allclose(getattr(scene.cameras, name).double(), torch.tensor(value, dtype=torch.float64)), name
    assert (scene.near, scene.far) == (2.0, 6.0)
    assert scene.format == "cs180-npz" and not scene.has_alpha
    assert torch.equal(scene.world_from_input.matrix(), torch.eye(4, dtype=torch.float64))


def test_cs180_poses_are_converted_opengl(scene, raw):
    gl = np.concatenate([raw["c2ws_train"], raw["c2ws_val"], raw["c2ws_test"]])
    expected = gl @ np.diag([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_allclose(scene.cameras.world_from_cam.numpy(), expected, atol=1e-6)
    assert _looks_at_origin(scene.cameras) > 0.98


def test_cs180_origin_projects_to_image_centre(scene):
    """Cameras look at the origin, so it must land on the principal point in every view (OpenCV axes, intrinsics)."""
    cams = scene.cameras
    uv, depth = cams.project(torch.zeros(len(cams), 3))
    assert (depth > 0).all()
    centre = torch.stack([cams.cx, cams.cy], dim=-1)
    assert float((uv - centre).norm(dim=-1).max()) < 1.0


def test_cs180_box_holds_origin_not_cameras(scene):
    lo, hi = scene.aabb
    assert (lo < 0).all() and (hi > 0).all()
    inside = ((scene.cameras.centers >= lo) & (scene.cameras.centers <= hi)).all(-1)
    assert not inside.any()


def test_cs180_images_load_in_camera_order(scene, raw):
    np.testing.assert_array_equal(scene.images.load(0), raw["images_train"][0])
    val = scene.splits["val"][3]
    img = scene.images.load(int(val))
    assert img.dtype == np.uint8 and img.shape == (200, 200, 3)
    np.testing.assert_array_equal(img, raw["images_val"][3])
    test = int(scene.splits["test"][0])
    assert scene.images.has(int(val)) and not scene.images.has(test)
    with pytest.raises(NerfpipeError, match="no image"):
        scene.images.load(test)


@pytest.mark.parametrize("pose_rows", [4, 3])
def test_tiny_nerf_layout(tmp_path, raw, scene, pose_rows):
    """The original authors' layout: float images in [0, 1], poses [N,4,4] or [N,3,4]; first 100 train."""
    images = np.concatenate([raw["images_train"], raw["images_val"]]).astype(np.float32) / 255.0
    poses = np.concatenate([raw["c2ws_train"], raw["c2ws_val"]])[:, :pose_rows]
    file = tmp_path / "tiny_nerf_data.npz"
    np.savez(file, images=images, poses=poses, focal=np.float64(raw["focal"]))
    tiny = data_adapters.load(file)
    assert tiny.format == "tiny-nerf-npz"
    assert {k: len(v) for k, v in tiny.splits.items()} == {"train": 100, "val": 10, "test": 0}
    np.testing.assert_allclose(tiny.cameras.world_from_cam.numpy(), scene.cameras.world_from_cam[:110].numpy(), atol=1e-6)
    img = tiny.images.load(105)
    assert img.dtype == np.uint8
    np.testing.assert_array_equal(img, raw["images_val"][5])
    assert (tiny.near, tiny.far) == (2.0, 6.0)


# ---------------------------------------------------------------- broken files


def _cs180(raw, **changes):
    arrays = {k: v for k, v in raw.items() if changes.get(k, 0) is not None}
    arrays.update({k: v for k, v in changes.items() if v is not None})
    return arrays


def _bad_rotation(raw, kind):
    m = raw["c2ws_train"].copy()
    if kind == "scaled":
        m[4, :3, :3] *= 1.1
    elif kind == "reflection":
        m[4, :3, 0] *= -1
    elif kind == "shear":
        m[4, :3, 1] += 0.05 * m[4, :3, 0]
    return m


def _with(raw, key, index, value):
    m = raw[key].copy()
    m[index] = value
    return m


BAD_CASES = {
    "missing c2ws_test": (lambda r: _cs180(r, c2ws_test=None), "c2ws_test"),
    "missing focal": (lambda r: _cs180(r, focal=None), "focal"),
    "poses wrong shape": (lambda r: _cs180(r, c2ws_train=r["c2ws_train"][:, :, :3]), "c2ws_train must have shape"),
    "images wrong shape": (lambda r: _cs180(r, images_train=r["images_train"][..., 0]), r"images_train must have shape"),
    "pose count": (lambda r: _cs180(r, c2ws_val=r["c2ws_val"][:5]), "c2ws_val has 5 poses but there are 10 images"),
    "val size": (lambda r: _cs180(r, images_val=r["images_val"][:, :100]), "differ in size"),
    "nan pose": (lambda r: _cs180(r, c2ws_train=_with(r, "c2ws_train", (7, 0, 3), np.nan)), r"c2ws_train\[7\] contains NaN"),
    "inf pose": (lambda r: _cs180(r, c2ws_test=_with(r, "c2ws_test", (2, 1, 1), np.inf)), r"c2ws_test\[2\] contains NaN or Inf"),
    "scaled rotation": (lambda r: _cs180(r, c2ws_train=_bad_rotation(r, "scaled")), r"c2ws_train\[4\] is not a rotation"),
    "reflection": (lambda r: _cs180(r, c2ws_train=_bad_rotation(r, "reflection")), r"c2ws_train\[4\] is not a rotation plus translation \(det -1,"),
    "shear": (lambda r: _cs180(r, c2ws_train=_bad_rotation(r, "shear")), r"c2ws_train\[4\] is not a rotation"),
    "projective last row": (lambda r: _cs180(r, c2ws_val=_with(r, "c2ws_val", (1, 3, 0), 0.5)), r"c2ws_val\[1\] has last row"),
    "zero focal": (lambda r: _cs180(r, focal=np.float64(0.0)), "focal must be a positive"),
    "nan focal": (lambda r: _cs180(r, focal=np.float64(np.nan)), "focal must be a positive"),
    "two focals": (lambda r: _cs180(r, focal=np.array([1.0, 2.0])), "focal must be one number"),
    "float images out of range": (lambda r: _cs180(r, images_val=r["images_val"].astype(np.float32)), r"outside \[0, 1\]"),
    "tiny missing poses": (lambda r: {"images": r["images_val"], "focal": r["focal"]}, "tiny-NeRF npz is missing key.* poses"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_npz_is_a_user_error_naming_the_file(tmp_path, raw, case):
    make, message = BAD_CASES[case]
    file = tmp_path / "scene.npz"
    np.savez(file, **make(raw))
    with pytest.raises(NerfpipeError, match=message) as err:
        data_adapters.load(file)
    assert err.value.path == file


def test_unreadable_npz_files(tmp_path, raw):
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not a zip archive" * 10)
    good = tmp_path / "good.npz"
    np.savez_compressed(good, **raw)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, **_cs180(raw, focal=np.array([{"f": 1.0}], dtype=object)))
    for file in (garbage, truncated, pickled):
        with pytest.raises(NerfpipeError, match="cannot read npz") as err:
            data_adapters.load(file)
        assert err.value.path == file
