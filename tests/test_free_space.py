"""The free-space violation catches fog: the ground-truth mesh of a synthetic scene blocks almost
none of its own sight lines, a closed box around the points (a fog box) blocks most, and the
figure reaches eval-mesh and the mesh stage's references."""

import numpy as np
import pytest

from data_adapters import load
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.metrics import free_space_violation
from nerfpipe.mesh.reference import dataset_references, reference_figures, sight_lines
from nerfpipe.synthetic import SynthConfig, generate


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    root = tmp_path_factory.mktemp("fs")
    generate(root / "scene", SynthConfig(views=16, width=48, height=48, num_points=800))
    return root / "scene"


def box_mesh(lo, hi) -> TriangleMesh:
    import trimesh

    box = trimesh.creation.box(extents=np.asarray(hi) - np.asarray(lo))
    box.apply_translation(0.5 * (np.asarray(lo) + np.asarray(hi)))
    return TriangleMesh(vertices=np.asarray(box.vertices, dtype=np.float64), faces=np.asarray(box.faces, dtype=np.int64))


def test_ground_truth_is_free_and_a_fog_box_is_not(synthetic):
    scene = load(synthetic)
    gt, points = dataset_references(scene, synthetic)
    lines = sight_lines(scene)
    assert lines is not None and len(lines.point_idx) > 1000
    truth = free_space_violation(gt, points, lines.centers, lines.point_idx, lines.cam_idx)
    assert truth["free_space_violation"] <= 0.005 and truth["sight_lines"] == len(lines.point_idx)
    lo, hi = np.quantile(points, [0.0, 1.0], axis=0)
    pad = 0.1 * (hi - lo)
    fog = free_space_violation(box_mesh(lo - pad, hi + pad), points, lines.centers, lines.point_idx, lines.cam_idx)
    assert fog["free_space_violation"] > 0.9  # every camera is outside the box, every point inside
    figures = reference_figures(gt, None, points, sight_lines=lines)
    assert figures["free_space_violation"] == pytest.approx(truth["free_space_violation"])


def test_mouse_tracks_are_cast(scene_path):
    scene = load(scene_path("colmap_mouse"))
    lines = sight_lines(scene)
    # 4,443 points with a mean track length of 5.77 (PROVENANCE.md): 25,656 observations
    assert len(lines.point_idx) == 25656 and lines.centers.shape == (56, 3)
    _, points = dataset_references(scene, None)
    lo, hi = np.quantile(points, [0.02, 0.98], axis=0)
    empty = box_mesh(hi + 100.0, hi + 101.0)  # far from every sight line
    assert free_space_violation(empty, points, lines.centers, lines.point_idx, lines.cam_idx)["free_space_violation"] == 0.0
