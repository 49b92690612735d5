"""The free-space violation catches fog: the ground-truth mesh of a synthetic scene blocks almost
none of its own sight lines, a closed box around the points (a fog box) blocks most, and the
figure reaches eval-mesh and the mesh stage's references."""

import numpy as np
import pytest

from nerfpipe.data.synthetic import SynthConfig, generate
from nerfpipe.data_adapters import load
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.metrics import free_space_violation
from nerfpipe.mesh.reference import dataset_references, reference_figures, sight_lines


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


def _wall(x: float, offset, half: float = 10.0) -> TriangleMesh:
    """A square in the plane ``x = const`` (two triangles), spanning ``[-half, half]`` in y and z, moved by ``offset``."""
    v = np.array([[x, -half, -half], [x, half, -half], [x, half, half], [x, -half, half]]) + offset
    return TriangleMesh(vertices=v, faces=np.array([[0, 1, 2], [0, 2, 3]]))


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (4_123_456.7, 5_234_567.3, 312.9)], ids=["origin", "utm"])
def test_golden_sight_lines_across_a_wall(offset):
    """Camera at x=-0.37, wall at x=1: points at x = 0.5 (in front), 1 + tau/2 (on the wall, within the slack)
    and 1 + 2 tau (behind) score 0, 0 and 1, also far from the origin (float32 casting)."""
    tau, offset = 0.01, np.asarray(offset)
    points = np.array([[0.5, 0.1, 0.0], [1.0 + tau / 2, -0.2, 0.1], [1.0 + 2 * tau, 0.0, 0.3]]) + offset
    centers = np.array([[-0.37, 0.0, 0.0]]) + offset
    wall = _wall(1.0, offset)
    one = lambda *i: np.array(i, dtype=np.int64)  # noqa: E731
    each = [free_space_violation(wall, points, centers, one(i), one(0), tau=tau)["free_space_violation"] for i in range(3)]
    assert each == [0.0, 0.0, 1.0]
    both = free_space_violation(wall, points, centers, one(0, 1, 2, 2), one(0, 0, 0, 0), tau=tau)
    assert both == {"free_space_violation": 0.5, "sight_lines": 4, "free_space_tau": tau}
