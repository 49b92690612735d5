"""COLMAP adapter: synthetic models written by pycolmap read back exactly, plus colmap_mouse."""

from pathlib import Path

import numpy as np
import pytest
import torch

pycolmap = pytest.importorskip("pycolmap")

from nerfpipe import data_adapters  # noqa: E402
from colmap_synth import PARAMS, make_scene, synthesize, write_scene  # noqa: E402
from nerfpipe.data.scene import holdout_split  # noqa: E402
from nerfpipe.data_adapters import colmap  # noqa: E402
from nerfpipe.functional.distortion import Distortion  # noqa: E402
from nerfpipe.util.errors import NerfpipeError  # noqa: E402

# COLMAP model -> (nerfpipe code, the 4 nerfpipe distortion params from COLMAP's params p)
EXPECTED = {
    "SIMPLE_PINHOLE": (Distortion.NONE, lambda p: [0, 0, 0, 0]),
    "PINHOLE": (Distortion.NONE, lambda p: [0, 0, 0, 0]),
    "SIMPLE_RADIAL": (Distortion.OPENCV, lambda p: [p[3], 0, 0, 0]),
    "RADIAL": (Distortion.OPENCV, lambda p: [p[3], p[4], 0, 0]),
    "OPENCV": (Distortion.OPENCV, lambda p: p[4:8]),
    "OPENCV_FISHEYE": (Distortion.FISHEYE, lambda p: p[4:8]),
}


def _reference(rec):
    """Registered images sorted by name, their world_from_cam (float64) and cameras, from pycolmap."""
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    w2c = []
    for im in images:
        m = np.eye(4)
        m[:3] = im.cam_from_world().matrix()
        w2c.append(np.linalg.inv(m))
    return images, torch.tensor(np.stack(w2c))


def _focal_centre(model, p):
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        return p[0], p[0], p[1], p[2]
    return p[0], p[1], p[2], p[3]


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
@pytest.mark.parametrize("model", list(EXPECTED))
def test_round_trip(tmp_path, model, text):
    rec = synthesize(model, frames=9)
    scene = data_adapters.load(write_scene(rec, tmp_path, text=text))
    images, w2c_ref = _reference(rec)
    assert scene.format == "colmap" and scene.camera_models == [model] * len(images)
    assert [p.name for p in scene.images.paths] == [im.name for im in images]
    # poses: undo the normalisation and compare with pycolmap (float32 storage)
    back = scene.world_from_input.inverse().apply_world_from_cam(scene.cameras.world_from_cam.double())
    torch.testing.assert_close(back, w2c_ref, atol=1e-5 * float(w2c_ref[:, :3, 3].abs().max()), rtol=0)
    p = PARAMS[model]
    code, dist = EXPECTED[model]
    f32 = lambda v: torch.tensor(v, dtype=torch.float32).expand(len(images))  # noqa: E731
    for name, value in zip(("fx", "fy", "cx", "cy"), _focal_centre(model, p)):
        assert torch.equal(getattr(scene.cameras, name), f32(value)), name
    assert (scene.cameras.distortion == int(code)).all()
    expected = torch.tensor([float(x) for x in dist(p)], dtype=torch.float32).expand(len(images), 4)
    assert torch.equal(scene.cameras.dist_params, expected)
    assert (scene.cameras.width == 64).all() and (scene.cameras.height == 48).all()


def test_points_and_observations(tmp_path):
    rec = synthesize("OPENCV", frames=6, points=50)
    scene = data_adapters.load(write_scene(rec, tmp_path))
    ids = sorted(rec.points3D)
    xyz_ref = torch.tensor(np.array([rec.points3D[i].xyz for i in ids]))
    xyz_back = scene.world_from_input.inverse().apply_points(scene.points.xyz.double())
    torch.testing.assert_close(xyz_back, xyz_ref, atol=1e-5 * float(xyz_ref.abs().max()), rtol=0)
    rgb_ref = torch.tensor(np.array([rec.points3D[i].color for i in ids]), dtype=torch.uint8)
    assert torch.equal(scene.points.rgb, rgb_ref)
    pts = scene.points
    images, _ = _reference(rec)
    assert pts.track_point.dtype == pts.track_camera.dtype == torch.int64
    assert len(pts.track_xy) == sum(im.num_points3D for im in images) == sum(rec.points3D[i].track.length() for i in ids)
    first = images[1].get_observation_points2D()
    sel = (pts.track_camera == 1).numpy()
    np.testing.assert_array_equal(pts.track_xy.numpy()[sel], np.array([q.xy for q in first]))
    np.testing.assert_array_equal(np.array(ids)[pts.track_point.numpy()[sel]], [q.point3D_id for q in first])
    # every track element, as pycolmap lists it per point, is one observation
    image_of = [im.image_id for im in images]
    from_tracks = sorted((r, e.image_id) for r, i in enumerate(ids) for e in rec.points3D[i].track.elements)
    assert sorted(zip(pts.track_point.tolist(), [image_of[c] for c in pts.track_camera.tolist()])) == from_tracks


def test_split_rule_and_layouts(tmp_path):
    rec = synthesize("PINHOLE", frames=17)
    for layout in ("sparse/0", "sparse", "."):
        root = write_scene(rec, tmp_path / layout.replace("/", "_").replace(".", "root"), model_dir=layout)
        assert colmap.detect(root) > 0
        scene = data_adapters.load(root)
        names = sorted(rec.image(i).name for i in rec.reg_image_ids())
        expected = holdout_split(len(names))
        assert [scene.images.paths[i].name for i in scene.splits["val"]] == [names[i] for i in expected["val"]]
        assert len(scene.splits["val"]) == 3 and len(scene.splits["train"]) == 14
    assert colmap.detect(tmp_path) == 0


def test_largest_of_several_models(tmp_path):
    """COLMAP's mapper writes one model per connected group of photos: the one with the most registered images is read,
    whichever its number."""
    write_scene(synthesize("PINHOLE", frames=6, seed=1), tmp_path, model_dir="sparse/0")
    write_scene(synthesize("PINHOLE", frames=11, seed=2), tmp_path, model_dir="sparse/1")
    write_scene(synthesize("PINHOLE", frames=4, seed=3), tmp_path, model_dir="sparse/2")
    assert colmap.find_model_dir(tmp_path) == tmp_path / "sparse" / "1"
    assert len(data_adapters.load(tmp_path).cameras) == 11
    (tmp_path / "sparse" / "1" / "points3D.bin").unlink()  # an incomplete model is not a candidate
    assert colmap.find_model_dir(tmp_path) == tmp_path / "sparse" / "0"


def test_photos_beside_the_model(tmp_path):
    """COLMAP run with the photos' own folder as its image path writes the model beside them: no ``images/`` folder,
    the names relative to the folder itself. With an ``images/`` folder its names are looked up there as always."""
    rec = synthesize("PINHOLE", frames=9)
    root = write_scene(rec, tmp_path / "beside")
    for f in sorted((root / "images").iterdir()):
        f.rename(root / f.name)
    (root / "images").rmdir()
    scene = data_adapters.load(root)
    assert len(scene.cameras) == 9 and all(p.parent == root and p.is_file() for p in scene.images.paths)
    (root / "images").mkdir()  # an images/ folder is where the names are looked up, even an empty one
    assert "missing" in _error(root).problem


def test_bounds_contain_points(tmp_path):
    scene = data_adapters.load(make_scene(tmp_path, "PINHOLE"))
    assert 0 < scene.near < scene.far
    inside = ((scene.points.xyz >= scene.aabb[0]) & (scene.points.xyz <= scene.aabb[1])).all(-1)
    assert inside.float().mean() > 0.9
    n, m = len(scene.cameras), len(scene.points.xyz)
    cams = scene.cameras[torch.arange(n)[:, None].expand(n, m)]
    _, z = cams.project(scene.points.xyz[None].expand(n, m, 3))
    z = z[z > 0]
    assert scene.near <= float(torch.quantile(z, 0.01)) and scene.far >= float(torch.quantile(z, 0.99))


def test_colmap_mouse(scene_path):
    root = scene_path("colmap_mouse")
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    scene = data_adapters.load(root)
    images, w2c_ref = _reference(rec)
    assert len(scene.cameras) == rec.num_reg_images() == len(images)
    registered = {im.name for im in images}
    assert len(list((root / "images").glob("*.jpg"))) > len(registered)  # unregistered files are skipped
    assert {p.name for p in scene.images.paths} == registered
    assert set(scene.camera_models) == {"PINHOLE"}
    back = scene.world_from_input.inverse().apply_world_from_cam(scene.cameras.world_from_cam.double())
    torch.testing.assert_close(back, w2c_ref, atol=1e-5 * float(w2c_ref[:, :3, 3].abs().max()), rtol=0)
    for i, im in enumerate(images):
        cam = rec.camera(im.camera_id)
        assert (int(scene.cameras.width[i]), int(scene.cameras.height[i])) == (cam.width, cam.height)
        assert float(scene.cameras.fx[i]) == pytest.approx(cam.params[0], rel=1e-6)
    assert scene.points is not None and len(scene.points.xyz) == rec.num_points3D()
    reported = rec.compute_mean_reprojection_error()
    assert scene.meta["colmap_mean_reprojection_error"] == pytest.approx(reported, rel=1e-6)


def test_colmap_mouse_tracks(scene_path):
    """4,443 points, mean track length 5.77 (PROVENANCE.md): every track element is one observation,
    and each reprojects through our cameras (normalised world, float32) onto its keypoint."""
    root = scene_path("colmap_mouse")
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    scene = data_adapters.load(root)
    pts = scene.points
    lengths = np.bincount(pts.track_point.numpy(), minlength=len(pts.xyz))
    assert len(pts.xyz) == 4443 and len(pts.track_point) == sum(p.track.length() for p in rec.points3D.values()) == 25656
    assert lengths.min() >= 2 and lengths.mean() == pytest.approx(5.77, abs=0.005)
    uv, z = scene.cameras[pts.track_camera].project(pts.xyz[pts.track_point])
    err = (uv.double() - pts.track_xy).norm(dim=-1)
    assert bool((z > 0).all()) and float(err.median()) < 2.0 and float(err.mean()) < 2.0


def test_select_renumbers_tracks(tmp_path):
    scene = data_adapters.load(make_scene(tmp_path, "PINHOLE", frames=6, points=40))
    pts = scene.points
    keep = torch.arange(len(pts.xyz)) % 3 != 1
    sub = pts.select(keep)
    obs = keep[pts.track_point]
    assert len(sub.xyz) == int(keep.sum()) and len(sub.track_point) == int(obs.sum()) > 0
    assert torch.equal(sub.xyz[sub.track_point], pts.xyz[pts.track_point[obs]])
    assert torch.equal(sub.track_camera, pts.track_camera[obs]) and torch.equal(sub.track_xy, pts.track_xy[obs])
    with pytest.raises(ValueError, match="index the"):
        type(pts)(pts.xyz[:2], pts.rgb[:2], None, pts.track_point, pts.track_camera, pts.track_xy)
    with pytest.raises(ValueError, match="or none"):
        type(pts)(pts.xyz, pts.rgb, None, pts.track_point, None, None)


# ---------------------------------------------------------------- errors, each naming the file


def _error(path) -> NerfpipeError:
    with pytest.raises(NerfpipeError) as info:
        data_adapters.load(path)
    return info.value


def test_error_empty_model(tmp_path):
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction().write_binary(str(tmp_path / "sparse" / "0"))
    err = _error(tmp_path)
    assert "no registered images" in err.problem and err.path == tmp_path / "sparse" / "0" / "images.bin"


def test_error_unsupported_model(tmp_path):
    err = _error(make_scene(tmp_path, "FULL_OPENCV"))
    assert "FULL_OPENCV" in err.problem and err.path == tmp_path / "sparse" / "0" / "cameras.bin"


def test_images_whose_file_is_missing_are_left_out_with_one_warning(tmp_path):
    """A photograph deleted after the reconstruction: its camera and its track elements are left out, the rest load as
    before; every file missing (the wrong folder) is one error naming the folder."""
    root = make_scene(tmp_path, "PINHOLE")
    whole = data_adapters.load(root)
    files = sorted((root / "images").iterdir())
    for victim in files[3], files[5]:
        victim.unlink()
    with pytest.warns(UserWarning, match=rf"2 of the {len(files)} images .* have no file there and are left out \(first: {files[3].name}, {files[5].name}"):
        scene = data_adapters.load(root)
    keep = [k for k in range(len(files)) if k not in (3, 5)]
    assert [p.name for p in scene.images.paths] == [files[k].name for k in keep]
    torch.testing.assert_close(scene.cameras.fx, whole.cameras.fx[keep])
    seen = {int(c) for c in scene.points.track_camera}
    assert seen <= set(range(len(keep))) and len(scene.points.track_camera) < len(whole.points.track_camera)
    for f in files:
        f.unlink(missing_ok=True)
    err = _error(root)
    assert f"all {len(files)} images" in err.problem and "missing" in err.problem and err.path == root / "images"


def test_error_image_size_mismatch(tmp_path):
    import imageio.v3 as iio

    root = make_scene(tmp_path, "PINHOLE")
    victim = sorted((root / "images").iterdir())[2]
    iio.imwrite(victim, np.zeros((10, 20, 3), np.uint8))
    err = _error(root)
    assert "20x10" in err.problem and "64x48" in err.problem and "nor a downscaled copy" in err.problem and err.path == victim


def test_downscaled_images_scale_their_cameras_and_keypoints(scene_path, tmp_path):
    """``images/`` replaced by smaller copies after SfM (LLFF's / mip-NeRF 360's ``images_N``), at two scales in one
    folder: each camera and its keypoints are scaled to its image, the points reproject onto the keypoints at
    COLMAP's error in the smaller pixels, and the cameras see the same rays."""
    from PIL import Image

    from nerfpipe.data.consistency import check_scene

    src = scene_path("colmap_mouse")
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    keep = sorted(rec.images.values(), key=lambda im: im.name)[:6]
    for im in rec.images.values():
        if im.image_id not in {k.image_id for k in keep}:
            rec.deregister_frame(im.frame_id)
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write(str(tmp_path / "sparse" / "0"))
    (tmp_path / "images").mkdir()
    for k, im in enumerate(keep):
        photo = Image.open(src / "images" / im.name)
        factor = 2 if k == 0 else 4
        photo.resize((photo.width // factor, photo.height // factor), Image.BOX).save(tmp_path / "images" / im.name)
    full, small = data_adapters.load(src), data_adapters.load(tmp_path)
    assert len(small.cameras) == 6 and small.meta[colmap.IMAGE_SCALE] == [0.5] + [0.25] * 5
    names = [Path(p).name for p in full.images.paths]
    for k, im in enumerate(keep):
        i, s = names.index(im.name), (0.5 if k == 0 else 0.25)
        assert int(small.cameras.width[k]) == int(full.cameras.width[i]) * s
        for name in ("fx", "fy", "cx", "cy"):
            assert float(getattr(small.cameras, name)[k]) == pytest.approx(float(getattr(full.cameras, name)[i]) * s, rel=1e-6)
    report = check_scene(small)
    assert report.failures == []
    colmap_px = rec.compute_mean_reprojection_error()
    assert 0.25 * colmap_px < report.reproj_point_mean_px < 0.5 * colmap_px  # in the smaller images' pixels


def test_error_nan_pose(tmp_path):
    rec = synthesize("PINHOLE")
    frame = rec.frame(rec.reg_frame_ids()[0])
    frame.rig_from_world = pycolmap.Rigid3d(frame.rig_from_world.rotation, np.array([np.nan, 0.0, 0.0]))
    err = _error(write_scene(rec, tmp_path))
    assert "non-finite pose" in err.problem and err.path == tmp_path / "sparse" / "0" / "images.bin"


def test_error_unparsable_text_model(tmp_path):
    root = make_scene(tmp_path, "PINHOLE", text=True)
    path = root / "sparse" / "0" / "images.txt"
    lines = path.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line and not line.startswith("#"))
    parts = lines[i].split()
    lines[i] = " ".join(parts[:5] + ["oops"] + parts[6:])  # TX is not a number
    path.write_text("\n".join(lines) + "\n")
    err = _error(root)
    assert "cannot read COLMAP model" in err.problem and err.path == root / "sparse" / "0"


def test_error_no_model(tmp_path):
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    with pytest.raises(NerfpipeError) as info:
        colmap.read(tmp_path)
    assert "no COLMAP model" in info.value.problem and info.value.path == Path(tmp_path)
