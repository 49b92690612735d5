"""The ``sfm`` stage on real photos (a few downscaled Sceaux Castle frames), and another pipeline's
in-memory pycolmap SfM handed over to nerfpipe's Python API."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfpipe.pipeline.stages import Pipeline

PHOTOS = ["100_7100.JPG", "100_7101.JPG", "100_7102.JPG", "100_7103.JPG"]
MAX_SIZE = 400
"""Longest side used in these tests (the photos are 2832x2128)."""
FAST = {"max_image_size": MAX_SIZE, "max_num_features": 2048, "candidate_sizes": ()}


def known_focal(root: Path, longest_side: int) -> float:
    """fx of the photos' K.txt, scaled to images whose longest side is ``longest_side``."""
    k = np.loadtxt(root / "K.txt")
    return float(k[0, 0]) * longest_side / 2832


@pytest.fixture(scope="module")
def photos(scene_path, tmp_path_factory) -> Path:
    """A folder with a few of the Sceaux photos (copies: a symlink out of a dataset is refused), as a user would hand over."""
    root = tmp_path_factory.mktemp("sceaux")
    (root / "images").mkdir()
    for name in PHOTOS:
        shutil.copyfile(scene_path("photos_sceaux_castle") / "images" / name, root / "images" / name)
    return root


def test_sfm_stage_on_photos(photos, scene_path, tmp_path):
    pipe = Pipeline(["sfm", "load", "check"], {"sfm": FAST})
    result = pipe.run(photos, tmp_path)
    assert [r.status for r in result.records] == ["ran", "ran", "ran"]
    summary = json.loads((tmp_path / "sfm" / "sfm.json").read_text())
    assert summary["num_photos"] == len(PHOTOS) and summary["num_registered"] >= 3
    assert summary["num_registered"] == result["sfm_reconstruction"].num_reg_images()
    (camera,) = summary["cameras"]  # one shared camera: all photos have the same size and model
    assert camera["model"] == "SIMPLE_RADIAL" and max(camera["width"], camera["height"]) == MAX_SIZE
    assert camera["params"][0] == pytest.approx(known_focal(scene_path("photos_sceaux_castle"), MAX_SIZE), rel=0.1)
    undistorted = result["sfm_reconstruction"]
    assert {c.model.name for c in undistorted.cameras.values()} == {"PINHOLE"}
    scene = result["scene"]
    assert len(scene.cameras) == summary["num_registered"] and scene.points is not None
    # the undistorted model keeps the tracks: every element is one observation of the loaded scene
    assert len(scene.points.track_point) == sum(p.track.length() for p in undistorted.points3D.values()) > 0
    assert result["check"]["failures"] == []
    assert not (tmp_path / "sfm.work" / "images" / PHOTOS[0]).is_symlink()  # downscaled copies, not the originals


def test_sfm_not_needed_for_a_dataset(scene_path, tmp_path):
    result = Pipeline(["sfm", "load"]).run(scene_path("colmap_mouse"), tmp_path)
    assert [r.status for r in result.records] == ["not needed", "ran"]
    assert not (tmp_path / "sfm").exists()


def test_another_pipelines_reconstruction_is_handed_over(photos, tmp_path):
    """pycolmap SfM run by the caller; nerfpipe gets the Reconstruction object and the image folder."""
    import imageio.v3 as iio
    import pycolmap

    from nerfpipe import data_adapters
    from nerfpipe.plugins.sfm import prepare_images

    images = tmp_path / "small"
    prepare_images(sorted((photos / "images").iterdir()), images, MAX_SIZE)
    db = tmp_path / "db.db"
    ext = pycolmap.FeatureExtractionOptions()
    ext.sift.max_num_features, ext.num_threads = 2048, 2
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, extraction_options=ext)
    pycolmap.match_exhaustive(db)
    models = pycolmap.incremental_mapping(db, images, tmp_path / "sparse")
    rec = max(models.values(), key=lambda r: r.num_reg_images())

    arrays = {p.name: iio.imread(p) for p in sorted(images.iterdir())}  # the images in memory too
    result = Pipeline(["load", "check", "export"]).run(None, tmp_path / "run", reconstruction=rec, images=arrays)
    scene = result["scene"]
    assert len(scene.cameras) == rec.num_reg_images() and scene.camera_models == ["SIMPLE_RADIAL"] * len(scene.cameras)
    assert result["check"]["failures"] == []
    exported = data_adapters.load(result["export/transforms.json"])  # OPENCV distortion in nerfstudio's format
    assert torch.equal(exported.cameras.dist_params, scene.cameras.dist_params)
    assert torch.equal(exported.cameras.fx, scene.cameras.fx) and scene.cameras.has_distortion()
    by_name = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    centres = np.stack([by_name[p.name].projection_center() for p in scene.images.paths])
    norm = scene.world_from_input
    assert np.allclose(norm.apply_points(torch.from_numpy(centres)).numpy(), scene.cameras.centers.numpy(), atol=1e-4)


def test_photos_of_two_sizes_get_one_camera_per_size_and_keep_their_names(scene_path, tmp_path):
    from nerfpipe.plugins.sfm import flatten_names, group_photos

    flat = tmp_path / "flat"
    flat.mkdir()
    names = ["a.jpg", "b.jpg", "c.jpg"]
    for n in names:
        (flat / n).write_bytes(b"")
    group_photos(flat, names, [(40, 30, ""), (30, 40, ""), (40, 30, "Pixel 7")], tmp_path / "grouped")
    folders = {p.name: sorted(q.name for q in p.iterdir()) for p in (tmp_path / "grouped").iterdir()}
    assert folders == {"40x30": ["a.jpg"], "30x40": ["b.jpg"], "40x30-Pixel_7": ["c.jpg"]}

    import pycolmap

    rec = pycolmap.Reconstruction(str(scene_path("colmap_mouse") / "sparse" / "0"))  # COLMAP's names carry the folders
    names = {i: im.name for i, im in rec.images.items()}
    for im in rec.images.values():
        im.name = f"1920x1440/{im.name}"
    flatten_names(rec)
    assert {i: im.name for i, im in rec.images.items()} == names


def test_failed_registrations_are_dropped_with_their_lone_points(scene_path):
    """colmap_mouse's model with one camera moved 1,000x away and one given a bogus focal length."""
    import pycolmap

    from nerfpipe.plugins.sfm import drop_failed_registrations

    rec = pycolmap.Reconstruction(str(scene_path("colmap_mouse") / "sparse" / "0"))
    assert drop_failed_registrations(rec, 20.0) == []  # a good model loses nothing
    ids = sorted(rec.reg_image_ids())
    far, bogus = rec.image(ids[0]), rec.image(ids[1])
    pose = far.cam_from_world()
    pose.translation = pose.translation * 1000.0
    rec.frame(far.frame_id).rig_from_world = pose
    bogus.camera.params = np.array(bogus.camera.params) * np.array([100.0, 100.0, 1.0, 1.0])  # fx, fy 100x
    before = rec.num_reg_images()
    assert drop_failed_registrations(rec, 20.0) == sorted([far.name, bogus.name])
    assert rec.num_reg_images() == before - 2
    assert all(p.track.length() >= 2 for p in rec.points3D.values())
    assert all(e.image_id not in (ids[0], ids[1]) for p in rec.points3D.values() for e in p.track.elements)


def test_a_sideways_stored_portrait_photo_is_turned_upright_for_sfm(tmp_path):
    """A phone's portrait photo: landscape pixels and EXIF orientation 6 (turn 90 degrees clockwise to view)."""
    from PIL import Image

    from nerfpipe.data.image_file import read_image_uint8
    from nerfpipe.plugins.sfm import prepare_images

    upright = np.zeros((60, 40, 3), np.uint8)  # what the user sees: 40 wide, 60 high, red on top
    upright[:20, :, 0] = 255
    stored = Image.fromarray(np.ascontiguousarray(np.rot90(upright, k=1)))  # 90 degrees counter-clockwise
    exif = Image.Exif()
    exif[0x0112], exif[0x0110] = 6, "Phone"
    (tmp_path / "in").mkdir()
    stored.save(tmp_path / "in" / "p.jpg", quality=95, exif=exif.tobytes())
    for max_size, shape in ((0, (60, 40)), (30, (30, 20))):
        out = tmp_path / f"out{max_size}"
        (info,) = prepare_images([tmp_path / "in" / "p.jpg"], out, max_size)
        assert info == (shape[1], shape[0], "Phone")
        pixels = read_image_uint8(out / "p.jpg")
        assert pixels.shape[:2] == shape
        top, bottom = pixels[: shape[0] // 4].mean(axis=(0, 1)), pixels[-shape[0] // 4 :].mean(axis=(0, 1))
        assert top[0] > 200 and bottom[0] < 50  # red on top, as the user sees it
        with Image.open(out / "p.jpg") as im:
            assert im.getexif().get(0x0112, 1) == 1  # no second turn by a viewer


def test_rotation_agreement_sees_a_folded_part_of_a_capture_through_a_global_rotation():
    """The measure by which the sfm stage compares reconstructions (and the pose benchmark scores them): a reconstruction equal to the reference up to a rotation of the world agrees
    everywhere; one whose second half is turned 80 degrees agrees on its first half only, and a least-squares
    alignment would have blurred that."""
    from scipy.spatial.transform import Rotation

    from nerfpipe.plugins.sfm import rotation_agreement

    rng = np.random.default_rng(0)
    ref = {f"{i:02d}.jpg": Rotation.random(random_state=rng).as_matrix() for i in range(12)}
    world = Rotation.random(random_state=rng).as_matrix()
    same = {n: r @ world.T for n, r in ref.items()}
    assert rotation_agreement(same, ref) == {"shared": 12, "agree": 12, "median_error": pytest.approx(0.0, abs=1e-4)}
    assert rotation_agreement({}, ref) == {"shared": 0, "agree": 0, "median_error": None}  # written to sfm.json: valid JSON
    fold = Rotation.from_rotvec(np.radians(80.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    folded = {n: (r @ fold if i >= 7 else r) @ world.T for i, (n, r) in enumerate(sorted(ref.items()))}
    noisy = {n: Rotation.from_rotvec(np.radians(1.0) * rng.normal(size=3) / 3).as_matrix() @ r for n, r in folded.items()}
    got = rotation_agreement(noisy, ref)
    assert (got["shared"], got["agree"]) == (12, 7)
    assert rotation_agreement({"x.jpg": np.eye(3)}, ref)["shared"] == 0


@pytest.mark.parametrize(
    ("unfoldings", "placed", "left_out"),
    [
        ({1024: {"conflicts": 4, "conflicts_left": 0, "kept": True}, 640: {"conflicts": 1, "conflicts_left": 1}}, "folded", [640]),
        ({1024: {"conflicts": 4, "conflicts_left": 0, "kept": True}, 640: {"conflicts": 1, "conflicts_left": 1}}, "right", []),
        ({1024: {"conflicts": 0, "conflicts_left": 0}, 640: {"conflicts": 1, "conflicts_left": 1}}, "folded", []),  # no fold seen: the size check decides
        ({1024: {"conflicts": 3, "conflicts_left": 3}, 640: {"conflicts": 1, "conflicts_left": 1}}, "folded", []),  # no candidate without a conflict
    ],
)
def test_a_reconstruction_with_a_conflict_is_left_out_where_one_without_places_the_photos_otherwise(monkeypatch, unfoldings, placed, left_out):
    """In a capture that folded at some image size, a reconstruction keeping one conflict (too few to unfold) that
    disagrees with a reconstruction without any is a second fold (23 of colmap_mouse's photos as HEIC, session 73: a
    640 px one with one conflict, 8 of 19 photos placed as the unfolded 1,024 px one, kept by the size check)."""
    from scipy.spatial.transform import Rotation

    from nerfpipe.plugins import sfm

    rng = np.random.default_rng(1)
    right = {f"{i:02d}.jpg": Rotation.random(random_state=rng).as_matrix() for i in range(20)}
    turn = Rotation.from_rotvec(np.radians(70.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    folded = {n: r @ turn if i >= 9 else r for i, (n, r) in enumerate(sorted(right.items()))}
    rotations = {"first": right, "other": folded if placed == "folded" else right}
    monkeypatch.setattr(sfm, "model_rotations", lambda rec, images=None: rotations[rec])
    candidates = [(1024, "first", Path("a")), (640, "other", Path("b"))]
    assert sfm.with_conflicts(candidates, unfoldings) == left_out


def _mouse_subset(scene_path, root: Path, names: "list[str]", size: int = 240, fold: "list[str]" = ()) -> Path:
    """A COLMAP folder of ``names`` of colmap_mouse's photos at ``size`` px (the model at full size, as a user's
    half-size copies), the cameras of ``fold`` turned 80 degrees about their centres (a folded reconstruction)."""
    import pycolmap
    from PIL import Image
    from scipy.spatial.transform import Rotation

    src = scene_path("colmap_mouse")
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    turn = Rotation.from_rotvec(np.radians(80.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    for image_id, image in list(rec.images.items()):
        if image.name not in names:
            rec.deregister_frame(image.frame_id)
        elif image.name in fold:
            pose = image.cam_from_world()
            rotation = turn @ np.asarray(pose.rotation.matrix())
            rec.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), turn @ np.asarray(pose.translation))
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(str(root / "sparse" / "0"))
    (root / "images").mkdir()
    for name in names:
        with Image.open(src / "images" / name) as im:
            im.thumbnail((size, size))
            im.save(root / "images" / name, quality=95)
    return root


def test_the_photometric_check_tells_a_folded_reconstruction_from_the_right_one(scene_path, tmp_path):
    """The sfm stage's choice between disagreeing reconstructions: a short fit on each, scored on the same held-out
    photographs. Half of the cameras turned 80 degrees (as incremental mapping folds part of a sparse capture) cannot
    be rendered consistently from the others' views."""
    from nerfpipe.plugins.sfm import photometric_check

    names = sorted(p.name for p in (scene_path("colmap_mouse") / "images").iterdir())[::4][:12]
    right = _mouse_subset(scene_path, tmp_path / "right", names)
    folded = _mouse_subset(scene_path, tmp_path / "folded", names, fold=names[1::2])
    good, bad = photometric_check([right, folded], steps=60, work=tmp_path / "work")
    assert good > bad + 1.0


def test_reconstructions_sharing_too_few_photos_are_not_compared(scene_path, tmp_path):
    from nerfpipe.plugins.sfm import photometric_check

    names = sorted(p.name for p in (scene_path("colmap_mouse") / "images").iterdir())[::4]
    a = _mouse_subset(scene_path, tmp_path / "a", names[:6], size=64)
    b = _mouse_subset(scene_path, tmp_path / "b", names[3:9], size=64)  # 3 photos in both
    scores = photometric_check([a, b], steps=1, work=tmp_path / "work")
    assert len(scores) == 2 and all(s != s for s in scores)


def _subset_pair(scene_path, root: Path, fold: bool):
    """(full, subset) for :func:`subset_check`: 16 of colmap_mouse's photos (half of them turned 80 degrees where
    ``fold``: a block attached in the wrong place) and the 8 others alone, as the strict reconstruction leaves them."""
    import pycolmap

    names = sorted(p.name for p in (scene_path("colmap_mouse") / "images").iterdir())[::3][:16]
    full = _mouse_subset(scene_path, root / "full", names, fold=names[1::2] if fold else ())
    subset = _mouse_subset(scene_path, root / "subset", names[0::2])
    return [(pycolmap.Reconstruction(str(f / "sparse" / "0")), f / "images") for f in (full, subset)]


def test_keep_registered_leaves_the_named_photos_and_their_points(scene_path, tmp_path):
    """What the strict mapping registers beyond the chosen reconstruction (a photo dropped there as far off) is
    deregistered before the check, with the points only it saw."""
    import pycolmap

    from nerfpipe.plugins.sfm import keep_registered, model_rotations

    names = sorted(p.name for p in (scene_path("colmap_mouse") / "images").iterdir())[::3][:8]
    rec = pycolmap.Reconstruction(str(_mouse_subset(scene_path, tmp_path / "m", names) / "sparse" / "0"))
    before, kept = rec.num_points3D(), sorted(model_rotations(rec))[:5]
    keep_registered(rec, set(kept))
    assert sorted(model_rotations(rec)) == kept and rec.num_reg_images() == 5
    assert 0 < rec.num_points3D() < before and all(rec.point3D(i).track.length() >= 2 for i in rec.point3D_ids())


def test_keep_consensus_keeps_the_photos_another_reconstruction_places_alike(scene_path, tmp_path):
    """The sfm stage's fold fallback under a short budget: of a reconstruction whose every fourth photo is turned 80
    degrees (a folded block), the photos that a rival reconstruction (the right poses, in another world frame) places
    alike are kept; nothing where all agree or too few would be left."""
    import pycolmap
    from scipy.spatial.transform import Rotation

    from nerfpipe.plugins.sfm import CHECK_VIEWS, keep_consensus, model_rotations

    names = sorted(model_rotations(pycolmap.Reconstruction(str(scene_path("colmap_mouse") / "sparse" / "0"))))[::3][:16]  # posed ones
    folded = pycolmap.Reconstruction(str(_mouse_subset(scene_path, tmp_path / "folded", names, fold=names[1::4]) / "sparse" / "0"))
    right = model_rotations(pycolmap.Reconstruction(str(_mouse_subset(scene_path, tmp_path / "right", names) / "sparse" / "0")))
    world = Rotation.from_euler("xyz", [30.0, -50.0, 10.0], degrees=True).as_matrix()
    rival = {n: r @ world.T for n, r in right.items()}
    assert keep_consensus(folded, {}) is None and keep_consensus(folded, {640: model_rotations(folded)}) is None  # all alike
    assert keep_consensus(folded, {640: {n: rival[n] for n in names[:CHECK_VIEWS + 2]}}) is None  # too few to keep
    assert model_rotations(folded).keys() == set(names)
    record = keep_consensus(folded, {640: rival, 800: {n: rival[n] for n in names[0::4]}})
    assert record == {"max_image_size": 640, "kept": 12, "of": 16, "unshared": False}
    assert sorted(model_rotations(folded)) == sorted(set(names) - set(names[1::4])) and folded.num_points3D() > 0
    part = {n: rival[n] for n in names[:8]}  # a rival that registered half of the photos, two of them folded here
    alike, all_but = sorted(set(names[:8]) - {names[1], names[5]}), sorted(set(names) - {names[1], names[5]})
    # an unfolded rival (a fold undone at its size) vouches only for the photos it places alike: the ones it lacks
    # include the block its unfolding left out
    for keep_unshared, unfolded, kept in ((False, frozenset(), alike), (True, frozenset(), all_but), (True, frozenset({640}), alike),
                                          (True, frozenset({800}), all_but)):
        folded = pycolmap.Reconstruction(str(tmp_path / "folded" / "sparse" / "0"))
        record = keep_consensus(folded, {640: part}, keep_unshared=keep_unshared, unfolded=unfolded)
        assert record == {"max_image_size": 640, "kept": len(kept), "of": 16, "unshared": kept == all_but}, (keep_unshared, unfolded)
        assert sorted(model_rotations(folded)) == kept
    # photos an unfolding's continuation added (they did not pass the unfolding) stay only where the rival places them alike
    added = frozenset(names[8:10])
    folded = pycolmap.Reconstruction(str(tmp_path / "folded" / "sparse" / "0"))
    record = keep_consensus(folded, {640: part}, keep_unshared=True, added=added)
    assert record["kept"] == len(all_but) - 2 and sorted(model_rotations(folded)) == sorted(set(all_but) - added)


def test_photos_an_unfoldings_continuation_added_that_another_size_lacks_count_against_agreement():
    """:func:`nerfpipe.plugins.sfm.added_agreement`: session 91's 640 px continuation that added 4 photos 148-167 degrees
    off beside 11 shared right photos does not corroborate (they count as disagreeing); 2 photos added to 19 are within
    the tenth of the photos that may disagree and are left to the comparison of the others; 3 added to 19 are not."""
    from scipy.spatial.transform import Rotation

    from nerfpipe.plugins.sfm import SAME_POSES, added_agreement

    turns = Rotation.random(21, random_state=0).as_matrix()
    names = [f"p{i}" for i in range(21)]
    ours = dict(zip(names, turns))
    other = {n: r for n, r in ours.items() if n not in ("p19", "p20")}
    assert added_agreement(ours, other) == {"shared": 19, "agree": 19, "median_error": 0.0}  # without additions: as before
    assert added_agreement(ours, other, frozenset({"p19", "p20"})) == {"shared": 19, "agree": 19, "median_error": 0.0}
    three = {n: r for n, r in ours.items() if n not in ("p18", "p19", "p20")}
    a = added_agreement(ours, three, frozenset({"p18", "p19", "p20"}))
    assert (a["shared"], a["agree"]) == (21, 18) and a["agree"] < SAME_POSES * a["shared"]
    assert added_agreement(three, ours, other_added=frozenset({"p18", "p19", "p20"}))["shared"] == 21  # either side's additions
    ours15 = {n: ours[n] for n in names[:15]}
    other11 = {n: ours[n] for n in names[:11]}
    a = added_agreement(ours15, other11, frozenset(names[11:15]))
    assert (a["shared"], a["agree"]) == (15, 11) and a["agree"] < SAME_POSES * a["shared"]
    assert added_agreement({n: ours[n] for n in names[:13]}, other11, frozenset(names[11:13]))["shared"] == 13  # 2 of 13: a block
    assert added_agreement(ours, ours, frozenset({"p19"}))["shared"] == 21  # an addition the other has is compared as usual


MINIATURE_MARGIN = 0.3
"""The margin of these miniature checks (60 steps on 16 small photos): they separate by less than the stage's 400-step
fits (``STRICT_MARGIN``): the fold +0.44 dB, right poses -2.46 (session 31; after 120 steps +0.57 / -2.87)."""


def test_the_strict_reconstruction_is_kept_where_the_photos_it_leaves_out_are_folded(scene_path, tmp_path):
    """The sfm stage's last check (``strict_check``): a reconstruction whose extra photos sit 80 degrees off renders
    the held-out photographs worse than the photos that strong matches tie together alone, so those are kept."""
    from nerfpipe.plugins.sfm import subset_check

    full, subset = _subset_pair(scene_path, tmp_path, fold=True)
    record = subset_check(full, subset, tmp_path / "work", steps=60, margin=MINIATURE_MARGIN)
    assert record["registered"] == subset[0].num_reg_images() == record["agree"] >= 6  # the subset's poses are the right half's
    assert record["kept"] and record["check_psnr"][1] >= record["check_psnr"][0] + MINIATURE_MARGIN


def test_the_strict_reconstruction_is_not_kept_where_the_other_photos_fit(scene_path, tmp_path):
    """Right poses: the extra photos help the fit (or do not hurt it by the margin), so every photo is kept."""
    from nerfpipe.plugins.sfm import subset_check

    full, subset = _subset_pair(scene_path, tmp_path, fold=False)
    record = subset_check(full, subset, tmp_path / "work", steps=60, margin=MINIATURE_MARGIN)
    assert not record["kept"], record
    same = subset_check(full, full, tmp_path / "same", steps=60)  # not a proper subset: nothing to check
    assert "check_psnr" not in same and "kept" not in same
    import pycolmap

    fewer = pycolmap.Reconstruction(full[0])
    for image_id in list(fewer.reg_image_ids())[:2]:  # two weakly attached photos are not a folded block
        fewer.deregister_frame(fewer.image(image_id).frame_id)
    two = subset_check(full, (fewer, full[1]), tmp_path / "two", steps=60)
    assert two["registered"] == full[0].num_reg_images() - 2 and "check_psnr" not in two


def test_the_strict_mapping_reads_the_chosen_image_sizes_own_matches(tmp_path, monkeypatch):
    """Where the size check kept another image size's reconstruction, the strict mapping maps that size's matches and
    photos again (the first size's matches once dropped 9 of 19 right photos of a cut of colmap_mouse: session 31)."""
    import logging

    from nerfpipe.plugins import sfm
    from nerfpipe.util.errors import NerfpipeError

    seen = {"min_inliers": []}

    def mapping(images, work, config, info, time_left=None, matches_from=None, min_inliers=None):
        seen.update(images=images, matches_from=matches_from)
        seen["min_inliers"].append(min_inliers)
        raise NerfpipeError("no reconstruction", work)

    monkeypatch.setattr(sfm, "reconstruct", mapping)
    monkeypatch.setattr(sfm, "model_rotations", lambda rec, images=None: {})
    chosen = object(), tmp_path / "size640" / "images"
    rec, images, record = sfm.strict_check([], tmp_path, sfm.SfmConfig(), chosen, None, logging.getLogger("test"))
    assert (rec, images) == chosen and record == {"registered": 0}
    assert seen == {"images": tmp_path / "size640" / "grouped", "matches_from": tmp_path / "size640" / "database.db", "min_inliers": [60, 50]}


class _Mapped:
    """A reconstruction as far as :func:`nerfpipe.plugins.sfm.remap_unfolded` reads it."""

    def __init__(self, registered: int):
        self.registered = registered

    def num_reg_images(self) -> int:
        return self.registered


@pytest.mark.parametrize(
    ("single", "several", "needed", "kept", "limits"),
    [
        (0, 20, 8, 20, [None, 10.0]),  # the first initial pair grows nothing: several models, briefly
        (11, 20, 8, 11, [None]),  # the one model is enough: no second mapping
        (3, 5, 8, 5, [None, 10.0]),  # neither is enough: the larger, for unfold to refuse
        (6, None, 8, 6, [None, 10.0]),  # the second mapping fails: the first
        (None, None, 8, None, [None, 10.0]),  # neither maps
    ],
)
def test_an_unfoldings_mapping_grows_several_models_where_the_first_is_too_small(tmp_path, monkeypatch, single, several, needed, kept, limits):
    """Without a fold's weak pairs, the one model grown from COLMAP's first initial pair held no photo on every mapping
    of a 1,024 px fold of 23 of colmap_mouse's photos (session 73), so the unfolding was given up and the fold kept;
    the largest of several models, grown within ``UNFOLD_MODELS_SECONDS``, had 20-21 photos, 18 right."""
    from nerfpipe.plugins import sfm
    from nerfpipe.util.errors import NerfpipeError

    calls = []

    def mapping(images, work, config, info, time_left=None, matches_from=None, min_inliers=0, single_model=False):
        calls.append((single_model, time_left, matches_from))
        registered = single if single_model else several
        if registered is None:
            raise NerfpipeError("no reconstruction", work)
        return _Mapped(registered), {}

    monkeypatch.setattr(sfm, "reconstruct", mapping)
    monkeypatch.setattr(sfm, "drop_failed_registrations", lambda rec, spread: [])
    database = tmp_path / "round0.db"
    other = sfm.remap_unfolded(tmp_path, sfm.SfmConfig(), [], database, needed, None)
    assert (None if other is None else other.num_reg_images()) == kept
    assert [c[1] for c in calls] == limits and [c[0] for c in calls] == [True, False][: len(limits)]
    assert all(c[2] == database for c in calls)
    calls.clear()
    sfm.remap_unfolded(tmp_path, sfm.SfmConfig(), [], database, needed, 4.0)  # a budget shorter than the limit bounds it
    assert all(limit <= 4.0 for _, limit, _ in calls)


def test_a_fold_test_skipped_for_time_is_said(tmp_path, monkeypatch, caplog):
    """Under a budget too short for the fold test, the reconstruction is kept untested and the user is told so (a
    23-photo folder of colmap_mouse at ``--time-budget 180`` kept a fold silently: session 40)."""
    import logging

    from nerfpipe.plugins import sfm
    from nerfpipe.util.errors import NerfpipeError

    monkeypatch.setattr(sfm, "reconstruct", lambda *a, **k: pytest.fail("the strict mapping ran without time for it"))
    chosen = object(), tmp_path / "images"
    with caplog.at_level(logging.WARNING, logger="test"):
        rec, images, record = sfm.strict_check([], tmp_path, sfm.SfmConfig(), chosen, 100.0, logging.getLogger("test"))
    assert (rec, images) == chosen and record == {"skipped": "too little time left"}
    assert len(caplog.records) == 1 and "may fold" in caplog.records[0].getMessage() and "--time-budget" in caplog.records[0].getMessage()
    caplog.clear()
    kept, passed = {"max_image_size": 640, "kept": 9, "of": 20, "unshared": False}, []
    monkeypatch.setattr(sfm, "keep_consensus", lambda rec, rivals, keep_unshared=False, unfolded=frozenset(), images=None, added=frozenset(): passed.append(unfolded) or (kept if rivals else None))
    with caplog.at_level(logging.WARNING, logger="test"):  # a rival reconstruction: the photos placed alike, said
        rec, images, record = sfm.strict_check([], tmp_path, sfm.SfmConfig(), chosen, 100.0, logging.getLogger("test"), rivals={640: {}},
                                               unfolded_sizes=frozenset({640}))  # fmt: skip
    assert (rec, images) == chosen and record == {"skipped": "too little time left", "consensus": kept} and passed == [frozenset({640})]
    assert len(caplog.records) == 1 and "9 of its 20 photos" in caplog.records[0].getMessage() and "places alike" in caplog.records[0].getMessage()
    caplog.clear()

    def no_reconstruction(*args, **kwargs):
        raise NerfpipeError("no reconstruction", tmp_path)

    monkeypatch.setattr(sfm, "reconstruct", no_reconstruction)
    monkeypatch.setattr(sfm, "model_rotations", lambda rec, images=None: {})
    with caplog.at_level(logging.WARNING, logger="test"):  # time enough: the test runs (here: its mapping finds nothing)
        assert sfm.strict_check([], tmp_path, sfm.SfmConfig(), chosen, 1000.0, logging.getLogger("test"))[2] == {"registered": 0}
    assert not caplog.records


def test_the_consensus_keeps_the_photos_a_rival_lacks_only_where_not_one_conflict_shows(tmp_path, monkeypatch):
    """Under a budget too short for the fold test, the photos a rival reconstruction does not register stay only where
    the kept one has no conflict at all (a 1,024 px reconstruction of 23 of colmap_mouse's photos with one conflict
    kept 3 photos 5 degrees or more off that the 640 px one lacked: session 74)."""
    import logging

    from nerfpipe.plugins import sfm, unfold

    (tmp_path / "database.db").write_bytes(b"")
    chosen, seen = (object(), tmp_path / "images"), []
    monkeypatch.setattr(unfold, "verified_pairs", lambda database: {})
    monkeypatch.setattr(sfm, "keep_consensus", lambda rec, rivals, keep_unshared=False, unfolded=frozenset(), images=None, added=frozenset(): seen.append(keep_unshared))
    photos = [tmp_path / f"{i}.jpg" for i in range(10)]
    for conflicts, unshared in (([], True), ([("a", "b")], False), ([("a", "b"), ("c", "d")], False)):
        monkeypatch.setattr(unfold, "view_conflicts", lambda rec, pairs, found=conflicts: found)
        sfm.strict_check(photos, tmp_path, sfm.SfmConfig(), chosen, 100.0, logging.getLogger("test"), rivals={640: {}})
        assert seen[-1] is unshared, conflicts


def test_an_unfolded_witness_limits_the_consensus_only_of_a_reconstruction_not_unfolded_itself(tmp_path, monkeypatch):
    """``choose_reconstruction`` hands ``strict_check`` the unfolded image sizes as witnesses that vouch only for the
    photos they place alike, unless the kept reconstruction is one of them (23 of colmap_mouse's photos as HEIC, session
    74: an unfolded 640 px witness of 11 photos cut an unfolded 1,024 px reconstruction's 18-19 right photos to 11)."""
    import logging

    from nerfpipe.plugins import sfm

    seen = []
    monkeypatch.setattr(sfm, "strict_check", lambda photos, work, config, chosen, left, log, others, rivals, witnesses, added:
                        seen.append((witnesses, added)) or (*chosen, {"consensus": {}}))
    for kept, unfolded, witnesses in ((640, [1024], {1024}), (1024, [1024, 640], set()), (1024, [640], {640}), (1024, None, set()),
                                      (640, [1024, 640], set())):
        # (and the photos an unfolding's continuation added to the kept one: session 91)
        record = {"kept_max_image_size": kept, **({"unfolded": unfolded} if unfolded else {}), "added": {640: ["b.jpg"]}}
        monkeypatch.setattr(sfm, "_choose_by_size", lambda *args, r=record: ("rec", tmp_path / "images", dict(r), {640: {}}))
        sfm.choose_reconstruction([], tmp_path, sfm.SfmConfig(), ("rec", tmp_path / "images"), 100.0, logging.getLogger("test"))
        assert seen[-1] == (witnesses, {"b.jpg"} if kept == 640 else set()), (kept, unfolded)


def test_photos_an_unfoldings_continuation_added_are_left_out_where_no_other_size_vouched_for_them(scene_path, tmp_path, monkeypatch):
    """``choose_reconstruction``: the photos :func:`nerfpipe.plugins.unfold.extended` added to the kept reconstruction
    stay where another image size corroborates it or the consensus vetted them, and are left out where neither happened
    (session 91: a 1,024 px fold not undone, so no witness, and a 640 px continuation adding 3 photos 147-162 degrees off)."""
    import logging

    import pycolmap

    from nerfpipe.plugins import sfm

    model = scene_path("colmap_mouse") / "sparse" / "0"
    names = sorted(sfm.model_rotations(pycolmap.Reconstruction(str(model))))
    added = names[:2]
    for corroborated, strict, left_out in ((False, {"skipped": "too little time left"}, added), (True, None, []),
                                           (False, {"skipped": "too little time left", "consensus": {"kept": 10}}, [])):
        rec = pycolmap.Reconstruction(str(model))
        record = {"kept_max_image_size": 640, "added": {640: added}, "corroborated": corroborated}
        monkeypatch.setattr(sfm, "_choose_by_size", lambda *args, r=record, m=rec: (m, tmp_path / "images", dict(r), {}))
        monkeypatch.setattr(sfm, "strict_check", lambda photos, work, config, chosen, *args, s=strict: (*chosen, dict(s)))
        kept, _, out = sfm.choose_reconstruction([], tmp_path, sfm.SfmConfig(), (rec, tmp_path / "images"), 100.0, logging.getLogger("test"))
        assert sorted(set(names) - set(sfm.model_rotations(kept))) == left_out, (corroborated, strict)
        assert out.get("added_left_out", []) == left_out


class _Counted:
    """A stand-in reconstruction for ``strict_check``'s tests: only its count of registered photos."""

    def __init__(self, n: int) -> None:
        self.n = n

    def num_reg_images(self) -> int:
        return self.n


def _strict_without_colmap(monkeypatch, mapping, check) -> None:
    """``strict_check`` with ``mapping`` for ``reconstruct``, ``check`` for ``subset_check`` and the rest of COLMAP left out."""
    from nerfpipe.plugins import sfm

    monkeypatch.setattr(sfm, "reconstruct", mapping)
    monkeypatch.setattr(sfm, "flatten_names", lambda rec: None)
    monkeypatch.setattr(sfm, "drop_failed_registrations", lambda rec, spread: [])
    monkeypatch.setattr(sfm, "keep_registered", lambda rec, names: None)
    monkeypatch.setattr(sfm, "model_rotations", lambda rec, images=None: {})
    monkeypatch.setattr(sfm, "subset_check", check)


@pytest.mark.parametrize("start, registered, tried", [(70, {70: 2, 60: 2, 50: 7}, [70, 60, 50]), (60, {60: 7, 50: 9}, [60]), (60, {60: 2, 50: 3}, [60, 50])])
def test_the_strict_mapping_lowers_its_requirement_until_enough_photos_remain(tmp_path, monkeypatch, start, registered, tried):
    """The strict mapping (``strict_check``) tries ``strict_min_inliers``, then 10 fewer each time down to 50, and checks the
    first that leaves more than CHECK_VIEWS + 2 photos (at 60 three folded reconstructions of colmap_mouse's photos kept
    two photos, at 50 seven right ones): its requirement is recorded; where none does, the last one is checked."""
    import logging

    from nerfpipe.plugins import sfm

    calls = []

    def mapping(images, work, config, info, time_left=None, matches_from=None, min_inliers=None):
        calls.append(min_inliers)
        return _Counted(registered[min_inliers]), {}

    _strict_without_colmap(monkeypatch, mapping, lambda full, subset, *args, **kwargs: {"registered": subset[0].num_reg_images()})
    chosen = object(), tmp_path / "images"
    rec, images, record = sfm.strict_check([], tmp_path, sfm.SfmConfig(strict_min_inliers=start), chosen, None, logging.getLogger("test"))
    assert calls == tried and record == {"min_inliers": tried[-1], "registered": registered[tried[-1]]}
    assert (rec, images) == chosen  # not kept: the check found nothing


def test_the_strict_mapping_falls_back_on_another_image_sizes_matches(tmp_path, monkeypatch):
    """Where the chosen image size's matches leave too few photos at every requirement (colmap_mouse's 23 photos at 640 px:
    two), the strict mapping maps the other sizes' matches, and a kept strict reconstruction comes with its own photos."""
    import logging

    from nerfpipe.plugins import sfm

    calls = []

    def mapping(images, work, config, info, time_left=None, matches_from=None, min_inliers=None):
        calls.append((matches_from.parent.name, min_inliers))
        return _Counted(2 if matches_from.parent.name == "size640" else 7), {}

    checked = {}

    def check(full, subset, *args, **kwargs):
        checked.update(images=subset[1])
        return {"registered": 7, "kept": True, "check_psnr": [20.0, 21.0]}

    _strict_without_colmap(monkeypatch, mapping, check)
    chosen = _Counted(14), tmp_path / "size640" / "images"
    rec, images, record = sfm.strict_check([], tmp_path, sfm.SfmConfig(), chosen, None, logging.getLogger("test"),
                                           (tmp_path, tmp_path / "size640"))
    assert calls == [("size640", 60), ("size640", 50), (tmp_path.name, 60)]
    assert rec.n == 7 and images == tmp_path / "images" == checked["images"]
    assert record["min_inliers"] == 60 and record["matches_of"] == tmp_path.name and record["kept"]


def test_similar_pairs_are_the_photos_that_share_features():
    """The pairs the sfm stage matches in a large capture (``similar_pairs``): photos whose features are noisy copies
    of each other's score far above unrelated ones (one block of 3 photos per place, 4 places), symmetric."""
    from nerfpipe.plugins.sfm import similarity_scores

    rng = np.random.default_rng(0)
    places = [rng.integers(0, 256, size=(200, 128)).astype(np.float32) for _ in range(4)]
    photos = [np.clip(p + rng.normal(0, 12, size=p.shape), 0, 255) for p in places for _ in range(3)]
    scores = similarity_scores(photos)
    assert scores.shape == (12, 12) and np.allclose(scores, scores.T) and (np.diag(scores) == -1).all()
    same = np.kron(np.eye(4), np.ones((3, 3))).astype(bool) & ~np.eye(12, dtype=bool)
    assert scores[same].min() > 100 and scores[~same & ~np.eye(12, dtype=bool)].max() < 10
    for i in range(12):  # each photo's two best are its own place's
        assert set(np.argsort(-scores[i])[:2]) == set(np.flatnonzero(same[i]))


def test_sfm_stage_matching_similar_pairs_only(photos, tmp_path):
    """Above ``exhaustive_max_photos`` each photo is matched with its most similar ones only: the four Sceaux photos
    with 2 neighbours each still register."""
    pipe = Pipeline(["sfm"], {"sfm": {**FAST, "exhaustive_max_photos": 2, "match_neighbours": 2, "strict_min_inliers": 0}})
    pipe.run(photos, tmp_path)
    summary = json.loads((tmp_path / "sfm" / "sfm.json").read_text())
    assert summary["num_registered"] == len(PHOTOS)
    pairs = (tmp_path / "sfm.work" / "pairs.txt").read_text().split("\n")
    assert 3 <= len([p for p in pairs if p]) < 6  # not all 6 pairs


def test_colmaps_own_warnings_are_quiet_unless_verbose():
    """COLMAP's mapper warnings ("Discarding reconstruction due to insufficient size") stay out of a run's console;
    ``--sfm.verbose`` shows them; the level is restored afterwards."""
    import pycolmap

    from nerfpipe.plugins.sfm import _colmap_log

    before = pycolmap.logging.minloglevel
    with _colmap_log(pycolmap, verbose=False):
        assert pycolmap.logging.minloglevel >= 2
    assert pycolmap.logging.minloglevel == before
    with _colmap_log(pycolmap, verbose=True):
        assert pycolmap.logging.minloglevel == before


def test_the_rarer_orientation_of_one_camera_is_turned():
    from nerfpipe.plugins.sfm import photos_to_turn

    info = [(40, 30, ""), (30, 40, ""), (40, 30, ""), (40, 30, "Pixel 7"), (30, 40, "X"), (30, 30, "")]
    assert photos_to_turn(info) == {1}  # "Pixel 7" and "X" are other cameras; a square photo has no other orientation
    assert photos_to_turn([(40, 30, "A"), (30, 40, "A")]) == {1}  # a tie: the portrait photo
    assert photos_to_turn([(40, 30, "A"), (30, 40, "A"), (30, 40, "A")]) == {0}


def test_a_turned_photos_reconstruction_is_turned_back_exactly(tmp_path):
    """A reconstruction mapped on a photo turned a quarter counter-clockwise (as :func:`turn_photos` turns it) turned
    back: its keypoints and points project where the upright photo shows them, its centre stays, its pixels agree."""
    import pycolmap
    from PIL import Image

    from nerfpipe.plugins.sfm import UPRIGHT_DIR, unturn

    # the pixels: upright photo P (W wide), turned L = P turned a quarter; L's pixel (row r, col j) is P's (j, W-1-r)
    rng = np.random.default_rng(0)
    p = rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)
    turned_pixels = np.asarray(Image.fromarray(p).transpose(Image.Transpose.ROTATE_90))
    rows, cols = np.meshgrid(np.arange(40), np.arange(30), indexing="ij")
    assert np.array_equal(turned_pixels[rows, cols], p[cols, 40 - 1 - rows])
    # the geometry: two photos of one SIMPLE_RADIAL camera (the turned one's size), the first of them turned
    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=30, height=40, params=[35.0, 14.0, 21.0, 0.05], camera_id=1)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    xyz = rng.uniform(-0.5, 0.5, (12, 3))
    poses = [pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.1, -0.2, 0.05])), np.array([0.1, 0.0, 3.0])),
             pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([-0.1, 0.3, 0.0])), np.array([0.0, 0.2, 3.2]))]
    for image_id, (name, pose) in enumerate(zip(["t.jpg", "u.jpg"], poses), start=1):
        keypoints = np.array([cam.img_from_cam(pose * x) for x in xyz])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=image_id), pose)
    for k, x in enumerate(xyz):
        track = pycolmap.Track()
        track.add_element(1, k)
        track.add_element(2, k)
        rec.add_point3D(x, track)
    images = tmp_path / "images"
    (tmp_path / UPRIGHT_DIR).mkdir(parents=True)
    images.mkdir()
    for name in ("t.jpg", "u.jpg"):
        (images / name).write_bytes(b"turned" if name == "t.jpg" else b"as taken")
    (tmp_path / UPRIGHT_DIR / "t.jpg").write_bytes(b"upright")
    out, folder = unturn(rec, images)
    assert (folder / "t.jpg").read_bytes() == b"upright" and (folder / "u.jpg").read_bytes() == b"as taken"
    t, u = (out.find_image_with_name(n) for n in ("t.jpg", "u.jpg"))
    assert (t.camera.width, t.camera.height) == (40, 30) and t.camera_id != u.camera_id == 1
    assert np.allclose(t.camera.params, [35.0, 40 - 21.0, 14.0, 0.05])
    before = rec.find_image_with_name("t.jpg")
    kp = np.array([q.xy for q in before.points2D])
    assert np.allclose([q.xy for q in t.points2D], np.c_[40 - kp[:, 1], kp[:, 0]])  # (x, y) -> (W - y, x), W the upright width
    assert np.allclose(t.projection_center(), before.projection_center())
    for point in out.points3D.values():  # every observation where the photo shows it
        for el in point.track.elements:
            image = out.image(el.image_id)
            assert np.allclose(image.camera.img_from_cam(image.cam_from_world() * point.xyz), image.points2D[el.point2D_idx].xy, atol=1e-9)
    assert out.num_points3D() == 12 and out.compute_mean_reprojection_error() < 1e-9
    assert unturn(rec, tmp_path / "nothing" / "images") == (rec, tmp_path / "nothing" / "images")  # nothing turned


def test_the_rotations_of_a_turned_photo_compare_upright(tmp_path):
    """Reconstructions at two image sizes can turn different photos (sizes that round to swapped ones at one size and
    not at another: the Sacre Coeur's, session 90): their rotations compare as the upright cameras, as :func:`unturn`
    gives the reconstruction back, so a turned photo is not a quarter turn of disagreement."""
    import pycolmap

    from nerfpipe.plugins.sfm import UPRIGHT_DIR, model_rotations, rotation_agreement, unturn

    rng = np.random.default_rng(2)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=30, height=40, params=[35.0, 14.0, 21.0, 0.0], camera_id=1))
    names = ["a.jpg", "t.jpg", "u.jpg", "v.jpg"]
    for image_id, name in enumerate(names, start=1):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rng.normal(0.0, 0.5, 3)), rng.normal(0.0, 1.0, 3))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=image_id), pose)
    images = tmp_path / "images"
    images.mkdir()
    (tmp_path / UPRIGHT_DIR).mkdir()
    for name in names:
        (images / name).write_bytes(b"photo")
    (tmp_path / UPRIGHT_DIR / "t.jpg").write_bytes(b"upright")
    upright = model_rotations(unturn(rec, images)[0])
    got, as_mapped = model_rotations(rec, images), model_rotations(rec)
    assert got.keys() == upright.keys() == set(names)
    assert all(np.allclose(got[n], upright[n], atol=1e-9) for n in names)
    assert np.allclose(as_mapped["a.jpg"], upright["a.jpg"]) and not np.allclose(as_mapped["t.jpg"], upright["t.jpg"], atol=0.1)
    assert rotation_agreement(got, upright)["agree"] == 4 and rotation_agreement(as_mapped, upright)["agree"] == 3
    assert model_rotations(rec, tmp_path / "nothing" / "images").keys() == set(names)  # nothing turned there


def _posed(names: "list[str]", rotations: "list[np.ndarray]"):
    """A pycolmap reconstruction of ``names`` around the origin, ``cam_from_world`` rotations ``rotations``, no points."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=40, height=30, params=[35.0, 20.0, 15.0, 0.0], camera_id=1))
    for image_id, (name, r) in enumerate(zip(names, rotations), start=1):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(r), np.array([0.0, 0.0, 3.0]))  # each camera 3 from the origin
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=image_id), pose)
    return rec


def test_sizes_that_turned_different_photos_corroborate_each_other(tmp_path, monkeypatch):
    """The size check sees the same poses where the 640 px reconstruction mapped a photo turned and the 1,024 px one
    did not (photos_sacre_coeur, session 90: they read 90 degrees apart on it, disagreed, and a run kept 7 of 10)."""
    import logging

    from scipy.spatial.transform import Rotation

    from nerfpipe.plugins import sfm

    names = [f"{i:02d}.jpg" for i in range(10)]
    upright = list(Rotation.random(len(names), random_state=3).as_matrix())
    turned = {names[4]}
    as_mapped = [np.array(sfm.QUARTER).T @ r if n in turned else r for n, r in zip(names, upright)]
    folders = {}
    for size in (1024, 640):
        images = (tmp_path if size == 1024 else sfm.size_work(tmp_path, size)) / "images"
        images.mkdir(parents=True)
        if size == 640:
            (images.parent / sfm.UPRIGHT_DIR).mkdir()
            for name in turned:
                (images.parent / sfm.UPRIGHT_DIR / name).write_bytes(b"upright")
        folders[size] = images
    other = _posed(names, as_mapped)
    monkeypatch.setattr(sfm, "_candidate", lambda photos, work, config, left, log=None: (other, {}, folders[640], {"conflicts": 0, "conflicts_left": 0}))
    config = sfm.SfmConfig(candidate_sizes=(640,))
    rec, images, record, rivals = sfm._choose_by_size([Path(n) for n in names], tmp_path, config, (_posed(names, upright), folders[1024]), None,
                                                      logging.getLogger("test"), {"conflicts": 0, "conflicts_left": 0})  # fmt: skip
    assert record["corroborated"] and record["candidates"][1]["agree"] == 10 and rivals == {}, record
    assert images == folders[1024] and "check_psnr" not in record["candidates"][1]
    # what the comparison read before: the turned photo a quarter turn off, 9 of 10 alike (fewer than SAME_POSES asks)
    assert sfm.rotation_agreement(sfm.model_rotations(other), sfm.model_rotations(rec))["agree"] == 9


def test_a_portrait_photo_among_landscape_ones_shares_their_camera_and_keeps_its_pose(photos, tmp_path):
    """One of the Sceaux photos stored as a portrait (turned a quarter clockwise, as the same camera held upright
    would take it): mapped turned back with the others' camera, then given back upright, its camera is the others'
    turned, and its pose relative to another photo the landscape photo's turned a quarter about its optical axis."""
    from PIL import Image

    portrait = tmp_path / "portrait"
    (portrait / "images").mkdir(parents=True)
    for name in PHOTOS:
        with Image.open(photos / "images" / name) as im:
            (im.transpose(Image.Transpose.ROTATE_270) if name == PHOTOS[1] else im).save(portrait / "images" / name, quality=95)
    runs = {}
    for label, folder in (("landscape", photos), ("portrait", portrait)):
        result = Pipeline(["sfm"], {"sfm": FAST}).run(folder, tmp_path / label)
        rec = result["sfm_reconstruction"]
        runs[label] = ({rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}, json.loads((tmp_path / label / "sfm" / "sfm.json").read_text()))
    (images, summary), (upright, _) = runs["portrait"], runs["landscape"]
    assert summary["turned"] == [PHOTOS[1]] and len(summary["cameras"]) == 2
    a, b = (c["params"] for c in summary["cameras"])
    assert a[0] == b[0] and sorted([a[1], a[2]]) == sorted([b[1], b[2]])  # one focal length, the same camera turned
    if {PHOTOS[0], PHOTOS[1]} - images.keys() or {PHOTOS[0], PHOTOS[1]} - upright.keys():
        pytest.skip("a photo was not registered")
    cam = images[PHOTOS[1]].camera
    assert cam.height > cam.width and images[PHOTOS[0]].camera.width > images[PHOTOS[0]].camera.height
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # the upright camera from the landscape one

    def relative(by_name) -> np.ndarray:
        rot = {n: np.asarray(by_name[n].cam_from_world().rotation.matrix()) for n in (PHOTOS[0], PHOTOS[1])}
        return rot[PHOTOS[1]] @ rot[PHOTOS[0]].T

    turned_back = quarter.T @ relative(images)
    angle = np.degrees(np.arccos(np.clip((np.trace(turned_back @ relative(upright).T) - 1) / 2, -1, 1)))
    assert angle < 1.0


def test_heic_photos_are_reconstructed_under_their_own_names(photos, tmp_path):
    """An iPhone's HEIC photos (the Sceaux photos encoded so, one of them held as a portrait: its rotation in the HEIF
    file, EXIF orientation 6 when written): read upright, mapped as JPEG copies named ``NAME.HEIC.jpg``, the photos
    the reconstruction leaves out named as the user's files; a broken one is one error naming it."""
    pillow_heif = pytest.importorskip("pillow_heif")
    from PIL import Image

    from nerfpipe.util.errors import NerfpipeError

    heic = tmp_path / "heic"
    (heic / "images").mkdir(parents=True)
    for name in PHOTOS:
        with Image.open(photos / "images" / name) as im:
            small = im.convert("RGB").resize((MAX_SIZE, round(MAX_SIZE * im.height / im.width)))
        file = pillow_heif.from_pillow(small)
        if name == PHOTOS[2]:  # the same camera (its EXIF kept), shown turned a quarter clockwise: a portrait
            exif = small.getexif()
            exif.get_ifd(0x8769)  # the focal length, part of the camera's tag, written back with it
            exif[0x0112] = 6
            file.info["exif"] = exif.tobytes()
        file.save(heic / "images" / (Path(name).stem + ".HEIC"), quality=90)
    result = Pipeline(["sfm", "load", "check"], {"sfm": {**FAST, "candidate_sizes": (320,)}}).run(heic, tmp_path / "run")
    summary = json.loads((tmp_path / "run" / "sfm" / "sfm.json").read_text())
    names = sorted(Path(n).stem + ".HEIC" for n in PHOTOS)
    from nerfpipe.plugins.sfm import prepared_sources

    first = tmp_path / "run" / "sfm.work" / "images"  # the smaller size downscales the first size's JPEG copies, upright
    sources = prepared_sources(sorted((heic / "images").iterdir()), first)
    assert [p.name for p in sources] == [n + ".jpg" for n in names]
    assert sources[2].parent.name == "upright" and all(p.parent == first for k, p in enumerate(sources) if k != 2)
    with Image.open(tmp_path / "run" / "sfm.work" / "size320" / "images" / sources[2].name) as im:
        assert im.size == (320, round(301 * 320 / 400))  # the portrait, turned again for its mapping there
    assert [c["max_image_size"] for c in summary["candidates"]][:1] == [MAX_SIZE]
    registered = {result["sfm_reconstruction"].image(i).name for i in result["sfm_reconstruction"].reg_image_ids()}
    assert registered <= {n + ".jpg" for n in names} and len(registered) >= 3
    assert sorted(summary["unregistered"]) == sorted(n for n in names if n + ".jpg" not in registered)
    assert summary["turned"] == [Path(PHOTOS[2]).stem + ".HEIC.jpg"]  # upright, so a portrait among landscapes
    assert result["check"]["failures"] == []
    (heic / "images" / names[0]).write_bytes(b"ftypheic but nothing more")
    with pytest.raises(NerfpipeError, match="cannot decode HEIF image") as info:
        Pipeline(["sfm"], {"sfm": FAST}).run(heic, tmp_path / "broken")
    assert info.value.path is not None and info.value.path.name == names[0]


def test_a_mapping_continued_from_a_reconstruction_registers_the_photos_it_lacks(photos, tmp_path):
    """:func:`nerfpipe.plugins.sfm.extend_mapping` (an unfolding's reconstruction continued with every photo pair:
    :func:`nerfpipe.plugins.unfold.extended`), through pycolmap: a reconstruction of the Sceaux photos with one of them
    deregistered gets it back, and the photos it had stay where they were."""
    import pycolmap

    from nerfpipe.plugins import sfm, unfold

    config = sfm.SfmConfig(**FAST)
    sources = sorted((photos / "images").iterdir())
    names = [sfm.sfm_name(p) for p in sources]
    info = sfm.prepare_images(sources, tmp_path / "images", MAX_SIZE)
    sfm.group_photos(tmp_path / "images", names, info, tmp_path / "grouped")
    full, _ = sfm.reconstruct(tmp_path / "grouped", tmp_path, config, info)
    posed = sorted(Path(i.name).name for i in full.images.values() if i.has_pose)
    assert len(posed) >= 3
    (tmp_path / "full").mkdir()
    full.write(tmp_path / "full")
    kept = pycolmap.Reconstruction(tmp_path / "full")
    sfm.keep_registered(kept, set(posed[1:]))
    assert kept.num_reg_images() == len(posed) - 1
    other = sfm.extend_mapping(tmp_path, config, kept, tmp_path / "database.db", None)
    assert other is not None and sorted(Path(i.name).name for i in other.images.values() if i.has_pose) == posed
    assert unfold.same_poses(other, kept)
