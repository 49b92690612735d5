"""Folds of a structure-from-motion reconstruction (``nerfpipe.plugins.unfold``) on COLMAP's model of colmap_mouse:
its own tracks as the verified matches, and the same model with a block of cameras turned about the scene centre
(as incremental mapping folds part of a capture with repeated structure)."""

from pathlib import Path

import numpy as np
import pytest

from nerfpipe.plugins import unfold


def _model(scene_path):
    import pycolmap

    return pycolmap.Reconstruction(str(scene_path("colmap_mouse") / "sparse" / "0"))


def _track_pairs(rec) -> dict:
    """Verified pairs as :func:`unfold.verified_pairs` returns them, from the model's tracks (each point seen in two
    photos is one match between them)."""
    points: dict = {}
    names = {i: Path(image.name).name for i, image in rec.images.items()}
    for point in rec.points3D.values():
        elements = [(names[e.image_id], np.asarray(rec.images[e.image_id].points2D[e.point2D_idx].xy)) for e in point.track.elements]
        for i, (a, xa) in enumerate(elements):
            for b, xb in elements[i + 1 :]:
                if a != b:
                    key, xy = ((a, b), (xa, xb)) if a < b else ((b, a), (xb, xa))
                    points.setdefault(key, []).append(xy)
    return {k: (np.array([x for x, _ in v]), np.array([y for _, y in v])) for k, v in points.items()}


def _points_per_match_as_verified(monkeypatch, rec, pairs: dict) -> None:
    """Matches from the tracks count every pair of a long track: fewer points per match than verified matches give
    (every photo of COLMAP's model under :data:`unfold.WEAK_POINTS_PER_MATCH`). The bound set to half the fewest of
    the model's photos, as the right photos of real reconstructions stand to it."""
    matches: dict = {}
    for (a, b), (xa, _) in pairs.items():
        for name in (a, b):
            matches[name] = matches.get(name, 0) + len(xa)
    per_match = min(image.num_points3D / matches[Path(image.name).name] for image in rec.images.values() if image.has_pose)
    monkeypatch.setattr(unfold, "WEAK_POINTS_PER_MATCH", 0.5 * per_match)


def _folded(rec, block: "set[str]", degrees: float = 80.0):
    """``rec`` with the cameras of ``block`` turned ``degrees`` about the vertical through the points' median (the
    world turned under them): a block placed elsewhere, right in itself."""
    import pycolmap
    from scipy.spatial.transform import Rotation

    centre = np.median(np.array([p.xyz for p in rec.points3D.values()]), axis=0)
    up = -np.mean([np.asarray(image.cam_from_world().rotation.matrix())[1] for image in rec.images.values() if image.has_pose], axis=0)
    turn = Rotation.from_rotvec(np.radians(degrees) * up / np.linalg.norm(up)).as_matrix()
    for image in rec.images.values():
        if image.has_pose and Path(image.name).name in block:
            pose = image.cam_from_world()
            r, t = np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)
            # world point x seen as before from turn(x - c) + c: cam_from_world' = cam_from_world o turn^-1 about c
            rotation = r @ turn.T
            translation = t + r @ centre - rotation @ centre
            rec.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation)
    return rec


def test_the_right_model_agrees_with_its_matches_and_has_no_conflicts(scene_path):
    """Every pair of COLMAP's model agrees with its epipolar geometry (its reprojection error is 0.63 px); photographs
    it shows from nearly the same side share matches, and a close pair whose matches are taken away is a conflict."""
    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    agreement = unfold.pair_agreement(rec, pairs)
    assert len(agreement) == len(pairs) > 500
    assert np.mean(list(agreement.values())) > 0.97 and min(agreement.values()) > 0.5
    assert unfold.view_conflicts(rec, pairs) == []
    close = unfold.view_conflicts(rec, {}, min_inliers=1)  # no matches at all: every close pair
    assert len(close) > 20
    taken = dict(pairs)
    del taken[close[0]]
    assert unfold.view_conflicts(rec, taken) == [close[0]]


def test_a_folded_block_contradicts_the_matches_between_the_blocks_and_sits_beside_photos_it_shares_nothing_with(scene_path):
    """Half of the cameras turned 80 degrees about the scene: the pairs within each block still agree, those across
    do not; the turned cameras land beside cameras whose photographs they do not match (conflicts); the weak pairs that
    agree with the fold lie within the blocks (but for a few matches agreeing by chance)."""
    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    names = sorted(Path(image.name).name for image in rec.images.values() if image.has_pose)
    block = set(names[::2])
    folded = _folded(rec, block)
    agreement = unfold.pair_agreement(folded, pairs)
    within = [s for (a, b), s in agreement.items() if (a in block) == (b in block)]
    across = [s for (a, b), s in agreement.items() if (a in block) != (b in block)]
    assert np.mean(within) > 0.97 and np.mean(across) < 0.1
    conflicts = unfold.view_conflicts(folded, pairs)
    assert conflicts and all((a in block) != (b in block) for a, b in conflicts)
    supporting = unfold.pairs_supporting(folded, pairs)
    assert supporting and all(len(pairs[k][0]) < unfold.WEAK_INLIERS for k in supporting)
    across = [(a, b) for a, b in supporting if (a in block) != (b in block)]  # by chance only (one of 367: 2 of 3 matches)
    assert len(across) <= 0.01 * len(supporting) and all(len(pairs[k][0]) <= 5 for k in across)


def test_unfold_keeps_a_remapped_reconstruction_only_without_conflicts_and_with_a_third_of_the_photos(scene_path, tmp_path, monkeypatch):
    """The choice of :func:`unfold.unfold`, with the mapping and the database replaced by the model itself: the right
    model mapped again is kept over a fold; the fold mapped again as it was, a mapping that failed or one that
    registers less than a third of the photos are not; a reconstruction without conflicts is left alone."""
    from nerfpipe.plugins.sfm import keep_registered

    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    names = sorted(Path(image.name).name for image in rec.images.values() if image.has_pose)
    monkeypatch.setattr(unfold, "verified_pairs", lambda database: pairs)
    _points_per_match_as_verified(monkeypatch, rec, pairs)
    deleted = []
    monkeypatch.setattr(unfold, "delete_pairs", lambda database, drop: deleted.append(list(drop)))
    database = tmp_path / "database.db"
    database.write_bytes(b"")

    def fold():
        return _folded(_model(scene_path), set(names[::2]))

    kept, record = unfold.unfold(rec, database, tmp_path / "work", remap=lambda path: pytest.fail("no conflict: no mapping"))
    assert kept is rec and record == {"conflicts": 0, "registered": len(names), "conflicts_left": 0}
    folded = fold()
    kept, record = unfold.unfold(folded, database, tmp_path / "work", remap=lambda path: _model(scene_path))
    assert record["kept"] and record["conflicts"] > 0 and record["rounds"] == [{"pairs_left_out": len(deleted[-1]), "registered": len(names), "conflicts": 0, "moved": True, "kept": True}]
    assert unfold.view_conflicts(kept, pairs) == [] and deleted[-1] == unfold.pairs_supporting(folded, pairs)
    assert record["conflicts_left"] == 0 and "misplaced" not in record and not unfold.still_folded(record)
    misplaced_one = _folded(_model(scene_path), {names[7]})  # the right model mapped again but for one photo
    kept, record = unfold.unfold(folded, database, tmp_path / "work", remap=lambda path: misplaced_one)
    assert record["misplaced"] == [names[7]] and kept is misplaced_one and kept.num_reg_images() == len(names) - 1
    for remap in (lambda path: fold(), lambda path: None):
        kept, record = unfold.unfold(folded, database, tmp_path / "work", remap=remap)
        assert kept is folded and not record["kept"] and unfold.still_folded(record)
    assert len(record["rounds"]) == 0  # the failed mapping
    few = _model(scene_path)
    keep_registered(few, set(names[: len(names) // 3]))
    kept, record = unfold.unfold(folded, database, tmp_path / "work", remap=lambda path: few)
    assert kept is folded and not record["kept"] and record["rounds"][0]["registered"] == len(names) // 3


def test_a_lone_misplaced_photo_is_the_one_whose_matches_disagree(scene_path):
    """One camera of COLMAP's model turned 80 degrees about the scene: most of its matches disagree with where it
    sits, while every other photo keeps most of its own (its pairs with the turned one are a small part)."""
    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    assert unfold.misplaced(rec, pairs) == []
    names = sorted(Path(image.name).name for image in rec.images.values() if image.has_pose)
    assert unfold.misplaced(_folded(rec, {names[7]}), pairs) == [names[7]]


def test_a_reconstruction_without_a_fold_loses_only_the_photos_whose_matches_disagree(scene_path, tmp_path, monkeypatch):
    """Where :func:`unfold.unfold` finds no fold, it maps nothing again, but a photo placed where its matches disagree
    (one camera turned 80 degrees) and that sees few points for its matches (as mapping leaves a misplaced photo: most
    of its observations taken away) is deregistered, with the points only it saw; COLMAP's own model loses none, and a
    turned photo that keeps its points stays (a right photo whose matches are mostly wrong looks alike)."""
    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    names = sorted(Path(image.name).name for image in rec.images.values() if image.has_pose)
    monkeypatch.setattr(unfold, "verified_pairs", lambda database: pairs)
    monkeypatch.setattr(unfold, "view_conflicts", lambda rec, pairs: [])  # no fold seen
    database = tmp_path / "database.db"
    database.write_bytes(b"")
    no_remap = lambda path: pytest.fail("no fold: no mapping")  # noqa: E731
    _points_per_match_as_verified(monkeypatch, rec, pairs)
    kept, record = unfold.unfold(rec, database, tmp_path / "work", remap=no_remap)
    assert kept is rec and "misplaced" not in record and rec.num_reg_images() == len(names)
    turned = _folded(_model(scene_path), {names[7]})
    kept, record = unfold.unfold(turned, database, tmp_path / "work", remap=no_remap)
    assert "misplaced" not in record and kept.num_reg_images() == len(names)  # its points are still many
    image = next(i for i in turned.images.values() if Path(i.name).name == names[7])
    seen = [k for k, p in enumerate(image.points2D) if p.has_point3D()]
    for k in seen[10:]:  # ten points left of its hundreds
        turned.delete_observation(image.image_id, k)
    points = turned.num_points3D()
    kept, record = unfold.unfold(turned, database, tmp_path / "work", remap=no_remap)
    assert kept is turned and record["misplaced"] == [names[7]] and record["conflicts"] == 0
    assert kept.num_reg_images() == len(names) - 1 and names[7] not in {Path(i.name).name for i in kept.images.values() if i.has_pose}
    assert kept.num_points3D() <= points
    block = set(names[: len(names) // 3])  # a third turned: a fold's block, not a photo or two, is left to the other tests
    kept, record = unfold.unfold(_folded(_model(scene_path), block), database, tmp_path / "work", remap=no_remap)
    assert "misplaced" not in record and kept.num_reg_images() == len(names)


def test_conflicts_are_explained_only_by_photos_attached_by_few_points(scene_path, monkeypatch):
    """:func:`unfold.conflicts_explained`: conflicts that all involve a photo the reconstruction attaches by few points
    (a turned camera whose observations mapping mostly left out) name it; one conflict between two well attached photos,
    or a turned photo that keeps its points, leaves them unexplained."""
    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    _points_per_match_as_verified(monkeypatch, rec, pairs)
    names = sorted(Path(image.name).name for image in rec.images.values() if image.has_pose)
    turned = _folded(_model(scene_path), {names[7]})
    conflicts = [(names[7], names[20]), (names[3], names[7])]
    assert unfold.conflicts_explained(turned, pairs, conflicts, unfold.WEAK_POINTS_PER_MATCH) == []  # its points still many
    image = next(i for i in turned.images.values() if Path(i.name).name == names[7])
    for k in [k for k, p in enumerate(image.points2D) if p.has_point3D()][10:]:
        turned.delete_observation(image.image_id, k)
    assert unfold.conflicts_explained(turned, pairs, conflicts, unfold.WEAK_POINTS_PER_MATCH) == [names[7]]
    both = conflicts + [(names[20], names[30])]
    assert unfold.conflicts_explained(turned, pairs, both, unfold.WEAK_POINTS_PER_MATCH) == []
    evidence = unfold.placement_evidence(turned, pairs)
    assert unfold.weakly_placed(evidence, unfold.WEAK_SHARE, unfold.WEAK_POINTS_PER_MATCH) == [names[7]]
    assert evidence[names[7]][0] < 0.5 < min(share for name, (share, _) in evidence.items() if name != names[7])


def test_a_remap_whose_conflicts_are_one_weakly_attached_photo_is_kept_without_it(scene_path, tmp_path, monkeypatch):
    """A round of :func:`unfold.unfold` whose remap leaves conflicts, all with one photo attached by few points (turned
    and most of its observations taken away), keeps that remap without the photo instead of mapping again."""
    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    monkeypatch.setattr(unfold, "verified_pairs", lambda database: pairs)
    monkeypatch.setattr(unfold, "delete_pairs", lambda database, drop: None)
    _points_per_match_as_verified(monkeypatch, rec, pairs)
    database = tmp_path / "database.db"
    database.write_bytes(b"")
    names = sorted(Path(image.name).name for image in rec.images.values() if image.has_pose)
    remapped = _folded(_model(scene_path), {names[20]})
    assert unfold.view_conflicts(remapped, pairs) and all(names[20] in c for c in unfold.view_conflicts(remapped, pairs))
    image = next(i for i in remapped.images.values() if Path(i.name).name == names[20])
    for k in [k for k, p in enumerate(image.points2D) if p.has_point3D()][10:]:
        remapped.delete_observation(image.image_id, k)
    kept, record = unfold.unfold(_folded(_model(scene_path), set(names[::2])), database, tmp_path / "work", remap=lambda path: remapped)
    assert kept is remapped and record["kept"] and record["rounds"][0]["weakly_attached"] == [names[20]]
    assert kept.num_reg_images() == len(names) - 1 and unfold.view_conflicts(kept, pairs) == []


def test_an_unfolding_that_left_photos_out_is_extended_with_those_placed_where_their_matches_agree(scene_path, tmp_path, monkeypatch):
    """:func:`unfold.extended` and ``unfold.unfold(..., extend=)``: a remap that left a third of the photos out is
    continued (the model itself standing in for the continued mapping); the continuation is kept with its photos,
    without one whose matches disagree with where it sits; not where it moves the photos kept, leaves conflicts,
    adds nothing once its misplaced photos are gone, or fails. A remap that registers every photo is not extended."""
    from nerfpipe.plugins.sfm import keep_registered

    rec = _model(scene_path)
    pairs = _track_pairs(rec)
    names = sorted(Path(image.name).name for image in rec.images.values() if image.has_pose)
    monkeypatch.setattr(unfold, "verified_pairs", lambda database: pairs)
    monkeypatch.setattr(unfold, "delete_pairs", lambda database, drop: None)
    _points_per_match_as_verified(monkeypatch, rec, pairs)
    database = tmp_path / "database.db"
    database.write_bytes(b"")
    left_out = set(names[2::3])

    def remapped():  # what an unfolding kept: the right model without a third of its photos
        part = _model(scene_path)
        keep_registered(part, set(names) - left_out)
        return part

    extensions = []

    def extend(kept):
        assert {Path(i.name).name for i in kept.images.values() if i.has_pose} == set(names) - left_out
        extensions.append(_model(scene_path))
        return extensions[-1]

    folded = _folded(_model(scene_path), set(names[::2]))
    kept, record = unfold.unfold(folded, database, tmp_path / "work", remap=lambda path: remapped(), extend=extend)
    assert record["kept"] and kept is extensions[-1] and kept.num_reg_images() == len(names)
    row = record["extended"]
    assert row["kept"] and row["registered"] == row["final"] == len(names) and row["conflicts"] == 0 and not row["moved"]
    assert set(row["new"]) == left_out and min(row["new"].values()) > unfold.WEAK_SHARE and "doubtful" not in row
    kept, record = unfold.unfold(folded, database, tmp_path / "work", remap=lambda path: _model(scene_path), extend=extend)
    assert kept.num_reg_images() == len(names) and "extended" not in record and len(extensions) == 1  # nothing left out

    part = remapped()
    wrong = names[20]  # (as in the test above: one whose neighbours keep their points)
    one_misplaced = _folded(_model(scene_path), {wrong})  # a new photo placed where its matches disagree
    image = next(i for i in one_misplaced.images.values() if Path(i.name).name == wrong)
    for k in [k for k, p in enumerate(image.points2D) if p.has_point3D()][10:]:
        one_misplaced.delete_observation(image.image_id, k)
    record = {}
    kept = unfold.extended(part, one_misplaced, pairs, record)
    dropped = record["extended"].get("misplaced", []) + record["extended"].get("weakly_attached", [])
    assert kept is one_misplaced and dropped == [wrong] and kept.num_reg_images() == len(names) - 1
    moved = _folded(_model(scene_path), set(names[::2]))  # the photos kept placed otherwise: a fold again
    record = {}
    assert unfold.extended(part, moved, pairs, record) is part and record["extended"]["moved"] and not record["extended"]["kept"]
    record = {}
    assert unfold.extended(part, None, pairs, record) is part and record["extended"] == {"kept": False}
    monkeypatch.setattr(unfold, "WEAK_SHARE", 1.01)  # every new photo's matches too few for one the fold had attached
    record = {}
    assert unfold.extended(part, _model(scene_path), pairs, record) is part and record["extended"]["doubtful"] == sorted(left_out)
    monkeypatch.setattr(unfold, "view_conflicts", lambda rec, pairs: [(names[0], names[2])])  # two well attached photos
    record = {}
    assert unfold.extended(part, _model(scene_path), pairs, record) is part and record["extended"]["conflicts"] == 1
