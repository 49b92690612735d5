"""Posed photographs without sparse points (instant-ngp's fox, downscaled) get points triangulated by the
``sfm`` stage with their poses fixed; the ``load`` stage adds them to the scene."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from nerfpipe import data_adapters
from nerfpipe.data.normalize import bounds_from_points
from nerfpipe.training.runs import load_run
from nerfpipe.training.trainer import scene_info
from nerfpipe.pipeline.stages import Pipeline
from nerfpipe.plugins.triangulate import chosen_photos, flat_border_fraction, neighbour_pairs, wants_points

SCALE = 0.25
"""The fox's 1080x1920 photos at a quarter of their size (270x480)."""
FAST = {"triangulate_max_image_size": 480, "triangulate_max_features": 2048, "triangulate_neighbours": 4}


@pytest.fixture(scope="module")
def fox_subset(scene_path, tmp_path_factory) -> Path:
    """Every 4th of the fox's first 40 frames, downscaled, as an instant-ngp transforms.json with scaled intrinsics."""
    src = scene_path("ngp_fox")
    doc = json.loads((src / "transforms.json").read_text())
    root = tmp_path_factory.mktemp("fox")
    (root / "images").mkdir()
    frames = doc["frames"][:40:4]
    for f in frames:
        with Image.open(src / f["file_path"]) as im:
            im.resize((round(im.width * SCALE), round(im.height * SCALE)), Image.LANCZOS).save(root / f["file_path"], quality=95)
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        doc[key] = doc[key] * SCALE
    doc["frames"] = frames
    (root / "transforms.json").write_text(json.dumps(doc))
    return root


def test_posed_photos_get_points_that_reproject_onto_their_tracks(fox_subset, tmp_path):
    assert data_adapters.load(fox_subset).points is None
    result = Pipeline(["sfm", "load"], {"sfm": FAST}).run(fox_subset, tmp_path)
    assert [r.status for r in result.records] == ["ran", "ran"]
    summary = json.loads((tmp_path / "sfm" / "sfm.json").read_text())
    assert summary["num_photos"] == 10 and summary["num_points3D"] > 200
    assert summary["mean_reprojection_error_px"] < 1.5  # the poses and distortion reached COLMAP in its conventions
    scene = result["scene"]
    pts = scene.points
    assert pts is not None and pts.has_tracks and len(pts.xyz) == summary["num_points3D"]
    # in nerfpipe's world, every observation lies where the scene's own camera (full size, with distortion) sees its point
    cams = scene.cameras[pts.track_camera]
    uv, z = cams.project(pts.xyz[pts.track_point].float())
    err = (uv - pts.track_xy.float()).norm(dim=-1)
    assert bool((z > 0).all()) and float(err.median()) < 1.0 and float(err.quantile(0.9)) < 3.0
    # near, far and the box come from the points, as for a COLMAP capture (and the model treats it as one)
    near, far, aabb = bounds_from_points(scene.cameras, pts.xyz)
    assert (scene.near, scene.far) == (near, far) and torch.equal(scene.aabb, aabb)
    assert scene_info(scene).unbounded
    # a resumed run (or a later stage) reloads the same points
    again = Pipeline(["sfm", "load"], {"sfm": FAST}).run(fox_subset, tmp_path)
    assert [r.status for r in again.records] == ["skipped", "skipped"]
    assert torch.equal(again.context.get("scene").points.xyz, pts.xyz)


def test_many_photos_are_triangulated_from_an_even_subset(fox_subset, tmp_path):
    assert chosen_photos(10, 0) == list(range(10)) and chosen_photos(4, 6) == [0, 1, 2, 3]
    chosen = chosen_photos(10, 6)
    assert len(chosen) == 6 and chosen[0] == 0 and chosen[-1] == 9
    result = Pipeline(["sfm", "load"], {"sfm": {**FAST, "triangulate_max_photos": 6}}).run(fox_subset, tmp_path)
    scene, summary = result["scene"], json.loads((tmp_path / "sfm" / "sfm.json").read_text())
    assert summary["num_photos"] == 10 and summary["num_triangulated_photos"] == 6
    pts = scene.points
    assert set(pts.track_camera.tolist()) <= set(chosen) and len(pts.xyz) > 100
    uv, _ = scene.cameras[pts.track_camera].project(pts.xyz[pts.track_point].float())
    assert float((uv - pts.track_xy.float()).norm(dim=-1).median()) < 1.0  # each observation on its own camera's pixel


def test_a_trained_run_reloads_with_the_triangulated_points(fox_subset, tmp_path):
    train = {"model": "fast", "model_options": {"preset": "small"},
             "trainer": {"iters": 2, "rays_per_step": 64, "eval_every": 0, "final_eval_views": 1, "eval_scale": 0.1, "write_outputs": False}}  # fmt: skip
    result = Pipeline(["sfm", "load", "train"], {"sfm": FAST, "train": train}).run(fox_subset, tmp_path)
    assert result["model"].behind is not None  # a real capture: the field behind the box is built
    scene, model, cfg = load_run(tmp_path, "cpu")
    assert Path(cfg["points"]) == (tmp_path / "sfm" / "points").resolve()
    assert torch.equal(scene.points.xyz, result["scene"].points.xyz) and torch.equal(scene.aabb, result["scene"].aabb)
    assert model.behind is not None


def test_nerfpipe_train_says_that_nerfpipe_run_would_triangulate_the_points(fox_subset, tmp_path, capsys):
    from nerfpipe.cli import main

    argv = ["train", str(fox_subset), "--iters", "1", "--rays-per-step", "64", "--video-frames", "0", "--eval-every", "0",
            "--final-eval-views", "1", "--eval-max-size", "32", "--no-write-outputs", "--out", str(tmp_path / "run")]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "no sparse points" in err and "`nerfpipe run` triangulates" in err


def test_renders_on_a_flat_background_and_scenes_with_points_get_none(scene_path):
    assert not wants_points(data_adapters.load(scene_path("colmap_mouse")))  # it has points
    assert not wants_points(data_adapters.load(scene_path("blender_lego")))  # alpha: a render
    assert not wants_points(data_adapters.load(scene_path("lego_200x200")))  # arrays, no photographs
    assert wants_points(data_adapters.load(scene_path("ngp_fox")))
    render = np.zeros((100, 80, 3), np.uint8)
    render[30:70, 20:60] = np.random.default_rng(0).integers(0, 255, (40, 40, 3))
    assert flat_border_fraction(render) == 1.0
    photo = np.random.default_rng(1).integers(0, 255, (100, 80, 3)).astype(np.uint8)
    assert flat_border_fraction(photo) < 0.05


def test_each_camera_is_matched_with_its_nearest_views(scene_path):
    scene = data_adapters.load(scene_path("ngp_fox"))
    pairs = neighbour_pairs(scene, 5)
    assert all(a < b for a, b in pairs) and len(set(pairs)) == len(pairs)
    seen = {i: {b if a == i else a for a, b in pairs if i in (a, b)} for i in range(len(scene.cameras))}
    assert all(len(s) >= 5 for s in seen.values())  # each camera's 5 nearest, and the pairs that name it
    assert len(pairs) < len(scene.cameras) * 5  # far fewer than exhaustive matching (2,211 pairs)
