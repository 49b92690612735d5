"""The transforms.json adapter: Blender, instant-ngp and nerfstudio flavours on real data, tiny
synthetic datasets for the rules, broken inputs, and a cross-check of the nerfstudio (COLMAP) poses
of the lego training images against the Blender ground truth."""

import json
import math
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfpipe import data_adapters
from nerfpipe.data.normalize import TARGET_CAMERA_DISTANCE
from nerfpipe.functional.distortion import Distortion
from nerfpipe.util.errors import NerfpipeError

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


# ---------------------------------------------------------------- real data, loaded once


@pytest.fixture(scope="module")
def blender(scene_path):
    return data_adapters.load(scene_path("blender_lego"))


@pytest.fixture(scope="module")
def ngp(scene_path):
    return data_adapters.load(scene_path("ngp_fox"))


@pytest.fixture(scope="module")
def nerfstudio(scene_path):
    return data_adapters.load(scene_path("nerfstudio_lego"))


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def _looks_at_origin(cameras) -> float:
    """Mean cosine between each camera's +z axis and the direction to the world origin."""
    to_origin = torch.nn.functional.normalize(-cameras.centers.double(), dim=-1)
    return float((cameras.forward.double() * to_origin).sum(-1).mean())


def _mean_up_z(cameras) -> float:
    """z component of the mean camera up vector (-y in OpenCV axes)."""
    return float(-cameras.world_from_cam[:, :3, 1].double().mean(0)[2])


def _input_world_from_cam(scene) -> np.ndarray:
    """Cameras mapped back to the file's own frame."""
    return scene.world_from_input.inverse().apply_world_from_cam(scene.cameras.world_from_cam.double()).numpy()


@pytest.mark.parametrize(
    "rel",
    ["blender_lego", "blender_lego/transforms_train.json", "blender_lego/transforms_val.json", "ngp_fox",
     "ngp_fox/transforms.json", "nerfstudio_lego", "nerfstudio_lego/transforms.json"],
)  # fmt: skip
def test_detects_files_and_folders(shared_data, rel):
    assert data_adapters.detect(shared_data / rel).name == "transforms"


def test_split_file_stands_for_the_whole_blender_set(scene_path):
    scene = data_adapters.load(scene_path("blender_lego") / "transforms_val.json")
    assert {k: len(v) for k, v in scene.splits.items()} == {"train": 100, "val": 100, "test": 200}


# ---------------------------------------------------------------- Blender


def test_blender_splits_intrinsics_and_bounds(blender, scene_path):
    assert blender.format == "blender"
    assert {k: len(v) for k, v in blender.splits.items()} == {"train": 100, "val": 100, "test": 200}
    angle = _json(scene_path("blender_lego") / "transforms_train.json")["camera_angle_x"]
    focal = 0.5 * 400 / math.tan(0.5 * angle)
    assert focal == pytest.approx(555.56, abs=0.01)
    cams = blender.cameras
    for name, value in [("fx", focal), ("fy", focal), ("cx", 200.0), ("cy", 200.0), ("width", 400), ("height", 400)]:
        assert torch.allclose(getattr(cams, name).double(), torch.tensor(value, dtype=torch.float64)), name
    assert not cams.has_distortion() and set(blender.camera_models) == {"PINHOLE"}
    assert (blender.near, blender.far) == (2.0, 6.0)
    assert torch.equal(blender.world_from_input.matrix(), torch.eye(4, dtype=torch.float64))


def test_blender_poses_are_converted_opengl(blender, scene_path):
    for split in ("train", "val", "test"):
        frames = _json(scene_path("blender_lego") / f"transforms_{split}.json")["frames"]
        idx = blender.splits[split]
        gl = np.array([f["transform_matrix"] for f in frames])
        np.testing.assert_allclose(blender.cameras.world_from_cam[idx].numpy(), gl @ GL_TO_CV, atol=1e-6)
        assert Path(blender.images.name(int(idx[7]))).relative_to(scene_path("blender_lego")) == Path(f"{split}/r_7.png")
    assert _looks_at_origin(blender.cameras) > 0.98
    assert _mean_up_z(blender.cameras) > 0.5


def test_blender_origin_projects_to_image_centre(blender):
    cams = blender.cameras
    uv, depth = cams.project(torch.zeros(len(cams), 3))
    assert (depth > 0).all()
    assert float((uv - torch.stack([cams.cx, cams.cy], -1)).norm(dim=-1).max()) < 1.0


def test_blender_images_are_rgba_uint8(blender):
    assert blender.has_alpha
    img = blender.images.load(int(blender.splits["test"][3]))
    assert img.dtype == np.uint8 and img.shape == (400, 400, 4)
    alpha = img[..., 3]
    assert alpha.min() == 0 and alpha.max() == 255  # transparent background, opaque object


# ---------------------------------------------------------------- instant-ngp


def test_ngp_fox(ngp, scene_path):
    doc = _json(scene_path("ngp_fox") / "transforms.json")
    assert ngp.format == "instant-ngp" and len(ngp.cameras) == 67
    assert {k: len(v) for k, v in ngp.splits.items()} == {"train": 58, "val": 9, "test": 0}
    np.testing.assert_array_equal(ngp.splits["val"], np.arange(0, 67, 8))
    cams = ngp.cameras
    for name, key in [("fx", "fl_x"), ("fy", "fl_y"), ("cx", "cx"), ("cy", "cy"), ("width", "w"), ("height", "h")]:
        assert torch.allclose(getattr(cams, name).double(), torch.tensor(float(doc[key]), dtype=torch.float64)), name
    assert (cams.distortion == Distortion.OPENCV).all()
    expected = torch.tensor([doc["k1"], doc["k2"], doc["p1"], doc["p2"]], dtype=torch.float32)
    assert torch.allclose(cams.dist_params, expected.expand(67, 4))
    assert ngp.meta["aabb_scale"] == 4 and set(ngp.camera_models) == {"OPENCV"}
    assert not ngp.has_alpha
    img = ngp.images.load(5)
    assert img.dtype == np.uint8 and img.shape == (1920, 1080, 3)


def test_ngp_normalisation_is_recorded(ngp, scene_path):
    """Sorted by file name; the inverse of world_from_input gives back the file's poses."""
    frames = sorted(_json(scene_path("ngp_fox") / "transforms.json")["frames"], key=lambda f: f["file_path"])
    assert [Path(ngp.images.name(i)).name for i in range(3)] == [Path(f["file_path"]).name for f in frames[:3]]
    gl = np.array([f["transform_matrix"] for f in frames])
    np.testing.assert_allclose(_input_world_from_cam(ngp), gl @ GL_TO_CV, atol=1e-4)
    assert float(ngp.cameras.centers.double().norm(dim=-1).mean()) == pytest.approx(TARGET_CAMERA_DISTANCE, rel=1e-4)
    assert _looks_at_origin(ngp.cameras) > 0.98
    assert _mean_up_z(ngp.cameras) > 0.5
    assert 0 < ngp.near < ngp.far


# PROVENANCE.md of ngp_fox: upstream deleted these 17 images but kept their frames in transforms.json.
NGP_DELETED = "0005 0016 0017 0024 0032 0051 0068 0071 0075 0083 0087 0088 0093 0099 0104 0106 0113".split()


def test_ngp_frames_without_image_are_skipped(tmp_path, scene_path):
    src = scene_path("ngp_fox")
    (tmp_path / "transforms.json").write_text((src / "transforms.json").read_text())
    (tmp_path / "images").mkdir()
    for image in sorted((src / "images").glob("*.jpg")):
        if image.stem not in NGP_DELETED:
            shutil.copyfile(image, tmp_path / "images" / image.name)  # a symlink out of the dataset is refused
    with pytest.warns(UserWarning, match="17 of 67 frames have no image file"):
        scene = data_adapters.load(tmp_path)
    assert len(scene.cameras) == 50
    assert not any(Path(scene.images.name(i)).stem in NGP_DELETED for i in range(50))
    for image in (tmp_path / "images").iterdir():
        image.unlink()
    with pytest.raises(NerfpipeError, match="none of the 67 frames"):
        data_adapters.load(tmp_path)


# ---------------------------------------------------------------- nerfstudio


def test_nerfstudio_lego(nerfstudio, scene_path):
    doc = _json(scene_path("nerfstudio_lego") / "transforms.json")
    assert nerfstudio.format == "nerfstudio" and len(nerfstudio.cameras) == 100
    assert {k: len(v) for k, v in nerfstudio.splits.items()} == {"train": 87, "val": 13, "test": 0}
    assert [Path(nerfstudio.images.name(i)).name for i in (0, 1, 99)] == ["frame_00001.png", "frame_00002.png", "frame_00100.png"]
    cams = nerfstudio.cameras
    for name, key in [("fx", "fl_x"), ("fy", "fl_y"), ("cx", "cx"), ("cy", "cy"), ("width", "w"), ("height", "h")]:
        assert torch.allclose(getattr(cams, name).double(), torch.tensor(float(doc[key]), dtype=torch.float64)), name
    assert (cams.distortion == Distortion.OPENCV).all() and set(nerfstudio.camera_models) == {"OPENCV"}
    assert nerfstudio.meta["applied_transform"] == doc["applied_transform"]
    assert nerfstudio.has_alpha
    img = nerfstudio.images.load(0)
    assert img.dtype == np.uint8 and img.shape == (800, 800, 4)
    assert _looks_at_origin(cams) > 0.98 and _mean_up_z(cams) > 0.5


def test_nerfstudio_poses_map_back_to_the_file(nerfstudio, scene_path):
    frames = sorted(_json(scene_path("nerfstudio_lego") / "transforms.json")["frames"], key=lambda f: f["file_path"])
    gl = np.array([f["transform_matrix"] for f in frames])
    np.testing.assert_allclose(_input_world_from_cam(nerfstudio), gl @ GL_TO_CV, atol=1e-4)


def _read_ascii_ply(path: Path) -> "tuple[np.ndarray, np.ndarray]":
    """Reference reader for the x y z red green blue ASCII PLY of the fixture."""
    lines = path.read_text().splitlines()
    end = lines.index("end_header")
    count = int(next(line.split()[-1] for line in lines[:end] if line.startswith("element vertex")))
    table = np.loadtxt(lines[end + 1 : end + 1 + count])
    return table[:, :3], table[:, 3:6].astype(np.uint8)


def test_nerfstudio_points_follow_the_normalisation(nerfstudio, scene_path):
    xyz, rgb = _read_ascii_ply(scene_path("nerfstudio_lego") / "sparse_pc.ply")
    pts = nerfstudio.points
    assert pts is not None and len(pts.xyz) == len(xyz) == 13112
    np.testing.assert_array_equal(pts.rgb.numpy(), rgb)
    back = nerfstudio.world_from_input.inverse().apply_points(pts.xyz.double()).numpy()
    np.testing.assert_allclose(back, xyz, atol=1e-4)
    lo, hi = nerfstudio.aabb
    inside = ((pts.xyz >= lo) & (pts.xyz <= hi)).all(-1).double().mean()
    assert inside > 0.9
    assert float(pts.xyz.double().median(0).values.norm()) < 0.5  # the object is at the centre


# ---------------------------------------------------------------- cross-check: nerfstudio vs Blender


def umeyama(src: np.ndarray, dst: np.ndarray) -> "tuple[float, np.ndarray, np.ndarray]":
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(xd.T @ xs / len(src))
    e = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    rot = u @ e @ vt
    scale = float(np.trace(np.diag(sig) @ e) / xs.var(0).sum())
    return scale, rot, mu_d - scale * rot @ mu_s


def test_umeyama_recovers_a_known_similarity():
    gen = np.random.default_rng(0)
    src = gen.normal(size=(20, 3))
    q, _ = np.linalg.qr(gen.normal(size=(3, 3)))
    rot = q * np.sign(np.linalg.det(q))
    dst = 0.7 * src @ rot.T + [1.0, -2.0, 3.0]
    s, r, t = umeyama(src, dst)
    assert s == pytest.approx(0.7) and np.allclose(r, rot) and np.allclose(t, [1.0, -2.0, 3.0])


def _robust_sim3(src, dst, rounds: int = 4):
    """Umeyama refitted on the cameras within 5x the median residual (COLMAP misplaces a few)."""
    keep = np.ones(len(src), bool)
    for _ in range(rounds):
        s, rot, t = umeyama(src[keep], dst[keep])
        residual = np.linalg.norm(s * src @ rot.T + t - dst, axis=1)
        keep = residual < 5 * np.median(residual)
    return rot, residual, keep


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def test_nerfstudio_and_blender_agree_on_the_lego_training_cameras(nerfstudio, blender):
    """Same 100 images, independent poses: after a Sim(3) fit in the INPUT frames, camera centres and
    orientations (all three axes) must agree for the well-registered cameras (PROVENANCE mapping)."""
    lexicographic = sorted([f"r_{i}" for i in range(100)], key=str)
    blender_index = {Path(blender.images.name(int(i))).stem: int(i) for i in blender.splits["train"]}
    ns_frame = [int(Path(nerfstudio.images.name(i)).stem.split("_")[1]) for i in range(100)]
    match = np.array([blender_index[lexicographic[k - 1]] for k in ns_frame])
    ns = _input_world_from_cam(nerfstudio)
    gt = _input_world_from_cam(blender)[match]
    rot, residual, keep = _robust_sim3(ns[:, :3, 3], gt[:, :3, 3])
    distance = float(np.linalg.norm(gt[:, :3, 3], axis=1).mean())
    rms = float(np.sqrt((residual[keep] ** 2).mean()))
    aligned = np.einsum("ij,njk->nik", rot, ns[:, :3, :3])
    axes = [_angles_deg(aligned[keep, :, a], gt[keep, :3, a]) for a in range(3)]
    assert keep.sum() >= 90
    assert rms < 0.01 * distance and residual[keep].max() < 0.02 * distance
    assert max(ang.max() for ang in axes) < 2.0 and axes[2].mean() < 1.0


# ---------------------------------------------------------------- tiny synthetic datasets


def _gl_look_at_origin(n: int, radius: float = 4.0) -> np.ndarray:
    """OpenGL camera-to-world matrices on a ring, each looking at the origin (z up)."""
    out = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        centre = radius * np.array([np.cos(a), np.sin(a), 0.5])
        back = centre / np.linalg.norm(centre)  # OpenGL camera +z points away from the target
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        m[:3, 3] = centre
        out.append(m)
    return np.array(out)


def _write_image(path: Path, h: int = 12, w: int = 16, c: int = 3) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.full((h, w, c), 200, np.uint8))


def _blender_set(root: Path, mutate=None) -> Path:
    """train (3 frames) and val (2 frames) of 16x12 RGBA images; ``mutate(train_doc)`` edits the train JSON."""
    for split, n in (("train", 3), ("val", 2)):
        frames = [{"file_path": f"./{split}/r_{i}", "transform_matrix": m.tolist()} for i, m in enumerate(_gl_look_at_origin(n))]
        for i in range(n):
            _write_image(root / split / f"r_{i}.png", c=4)
        doc = {"camera_angle_x": 0.69, "frames": frames}
        if split == "train" and mutate is not None:
            mutate(doc)
        (root / f"transforms_{split}.json").write_text(json.dumps(doc))
    return root


def _capture(root: Path, mutate=None, n: int = 9) -> Path:
    """A nerfstudio-style capture of ``n`` 16x12 RGB images, JSON frames in reverse name order."""
    frames = [{"file_path": f"images/frame_{i:05d}.png", "transform_matrix": m.tolist()} for i, m in enumerate(_gl_look_at_origin(n))]
    for f in frames:
        _write_image(root / f["file_path"])
    doc = {"w": 16, "h": 12, "fl_x": 20.0, "fl_y": 21.0, "cx": 8.5, "cy": 6.5, "k1": 0.01, "k2": 0.0, "p1": 0.0, "p2": 0.0,
           "camera_model": "OPENCV", "frames": frames[::-1]}  # fmt: skip
    if mutate is not None:
        mutate(doc)
    (root / "transforms.json").write_text(json.dumps(doc))
    return root


def test_synthetic_blender_set(tmp_path):
    scene = data_adapters.load(_blender_set(tmp_path))
    assert {k: len(v) for k, v in scene.splits.items()} == {"train": 3, "val": 2, "test": 0}
    assert torch.allclose(scene.cameras.fx, torch.tensor(0.5 * 16 / math.tan(0.5 * 0.69)))
    assert scene.has_alpha and scene.images.load(4).shape == (12, 16, 4)
    assert (scene.near, scene.far) == (2.0, 6.0)  # every camera at distance 4 * sqrt(1.25) ~ 4.5 from the origin


def test_synthetic_capture_split_rule_and_order(tmp_path):
    scene = data_adapters.load(_capture(tmp_path))
    assert [Path(scene.images.name(i)).name for i in range(9)] == [f"frame_{i:05d}.png" for i in range(9)]
    np.testing.assert_array_equal(scene.splits["val"], [0, 8])
    np.testing.assert_array_equal(scene.splits["train"], np.arange(1, 8))
    assert (scene.cameras.distortion == Distortion.OPENCV).all()
    assert torch.allclose(scene.cameras.fy, torch.tensor(21.0))


def test_per_frame_intrinsics_override_global(tmp_path):
    def mutate(doc):
        doc["frames"][0].update(fl_x=30.0, cx=7.0)  # frames are reversed: this is frame_00008

    scene = data_adapters.load(_capture(tmp_path, mutate))
    assert scene.cameras.fx.tolist() == [20.0] * 8 + [30.0]
    assert scene.cameras.cx.tolist() == [8.5] * 8 + [7.0]
    assert scene.cameras.fy.tolist() == [21.0] * 9


@pytest.mark.parametrize(
    "model,code,params",
    [("PINHOLE", Distortion.NONE, [0, 0, 0, 0]), ("OPENCV_FISHEYE", Distortion.FISHEYE, [0.01, 0.02, 0.03, 0.04])],
)
def test_camera_models(tmp_path, model, code, params):
    scene = data_adapters.load(_capture(tmp_path, lambda d: d.update(camera_model=model, k2=0.02, k3=0.03, k4=0.04)))
    assert (scene.cameras.distortion == code).all() and set(scene.camera_models) == {model}
    assert torch.allclose(scene.cameras.dist_params[0], torch.tensor(params, dtype=torch.float32))


def test_ngp_style_angles_and_sizes_from_the_images(tmp_path):
    """No fl_x/w/h and no camera_model: focal from camera_angle_x/y, size from the image header."""

    def mutate(doc):
        for key in ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_model"):
            doc.pop(key)
        doc.update(camera_angle_x=1.0, camera_angle_y=0.8, aabb_scale=16)

    scene = data_adapters.load(_capture(tmp_path, mutate))
    assert scene.format == "instant-ngp" and scene.meta["aabb_scale"] == 16
    cams = scene.cameras
    assert torch.allclose(cams.fx, torch.tensor(8 / math.tan(0.5)))
    assert torch.allclose(cams.fy, torch.tensor(6 / math.tan(0.4)))
    assert cams.width.tolist() == [16] * 9 and cams.cx.tolist() == [8.0] * 9
    assert (cams.distortion == Distortion.OPENCV).all()


# ---------------------------------------------------------------- broken inputs


def _frame0(**kw):
    return lambda doc: doc["frames"][0].update(kw)


def _scaled(doc):
    m = np.array(doc["frames"][1]["transform_matrix"])
    m[:3, :3] *= 1.2
    doc["frames"][1]["transform_matrix"] = m.tolist()


def _reflected(doc):
    m = np.array(doc["frames"][1]["transform_matrix"])
    m[:3, 0] *= -1
    doc["frames"][1]["transform_matrix"] = m.tolist()


def _nan(doc):
    doc["frames"][2]["transform_matrix"][1][3] = float("nan")


BAD_CAPTURES = {
    "relative escape": (_frame0(file_path="../../etc/passwd"), "points outside the folder"),
    "absolute escape": (_frame0(file_path="/etc/passwd"), "points outside the folder"),
    "nan pose": (_nan, r"transform_matrix\[.\] contains NaN"),
    "scaled pose": (_scaled, r"is not a rotation plus translation \(det 1.7"),
    "reflected pose": (_reflected, r"is not a rotation plus translation \(det -1"),
    "no focal": (lambda d: d.pop("fl_x"), "no focal length"),
    "negative focal": (lambda d: d.update(fl_x=-3.0), "fl_x must be a positive"),
    "unknown model": (lambda d: d.update(camera_model="EQUIRECTANGULAR"), "camera_model 'EQUIRECTANGULAR' is not supported"),
    "text cx": (lambda d: d.update(cx="middle"), "non-numeric intrinsics for frame_00000.png"),
    "k3 with OPENCV": (lambda d: d.update(k3=0.1), "k3/k4 with the OPENCV model are not supported"),
    "missing matrix": (lambda d: d["frames"][0].pop("transform_matrix"), "has no transform_matrix"),
    "no frames": (lambda d: d.pop("frames"), "no 'frames' list"),
    "missing ply": (lambda d: d.update(ply_file_path="sparse_pc.ply"), "point cloud file is missing"),
    "ply escape": (lambda d: d.update(ply_file_path="../points.ply"), "points outside the folder"),
}


@pytest.mark.parametrize("case", sorted(BAD_CAPTURES))
def test_bad_capture_is_a_user_error(tmp_path, case):
    mutate, message = BAD_CAPTURES[case]
    root = _capture(tmp_path / "data", mutate)
    with pytest.raises(NerfpipeError, match=message) as err:
        data_adapters.load(root)
    assert err.value.path is not None and err.value.path.is_relative_to(root)


def test_unreadable_json(tmp_path):
    root = _capture(tmp_path)
    (root / "transforms.json").write_text('{"frames": [')
    with pytest.raises(NerfpipeError, match="cannot read JSON") as err:
        data_adapters.load(root)
    assert err.value.path == root / "transforms.json"


def test_image_size_disagreeing_with_camera_names_the_file(tmp_path):
    root = _capture(tmp_path)
    _write_image(root / "images" / "frame_00004.png", h=20, w=20)
    with pytest.raises(NerfpipeError, match="image is 20x20 but its camera says w=16, h=12") as err:
        data_adapters.load(root)
    assert err.value.path == root / "images" / "frame_00004.png"


def test_corrupt_image_names_the_file(tmp_path):
    root = _capture(tmp_path)
    (root / "images" / "frame_00003.png").write_bytes(b"not a png")
    with pytest.raises(NerfpipeError, match="not an image file") as err:
        data_adapters.load(root)
    assert err.value.path == root / "images" / "frame_00003.png"


def test_blender_missing_image_names_it(tmp_path):
    root = _blender_set(tmp_path)
    (root / "train" / "r_1.png").unlink()
    with pytest.raises(NerfpipeError, match="image file is missing") as err:
        data_adapters.load(root)
    assert err.value.path == root / "train" / "r_1.png"


def test_blender_escape_and_bad_pose(tmp_path):
    root = _blender_set(tmp_path / "a", _frame0(file_path="../../../etc/passwd"))
    with pytest.raises(NerfpipeError, match="points outside the folder"):
        data_adapters.load(root)
    root = _blender_set(tmp_path / "b", _scaled)
    with pytest.raises(NerfpipeError, match="not a rotation") as err:
        data_adapters.load(root / "transforms_train.json")
    assert err.value.path == root / "transforms_train.json"
