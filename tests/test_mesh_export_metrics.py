"""PLY export in the input frame (round trip through trimesh and Open3D) and geometry metrics."""

import math

import numpy as np
import pytest
import torch

from nerfpipe.data.scene import Similarity
from nerfpipe.mesh import export
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.export import read_mesh, to_input_frame, write_ply
from nerfpipe.mesh.metrics import compare_meshes, point_fraction, sample_surface
from nerfpipe.util.errors import NerfpipeError


def box_mesh(extents=(1.0, 2.0, 0.5)) -> TriangleMesh:
    import trimesh

    b = trimesh.creation.box(extents=extents)
    rng = np.random.default_rng(0)
    return TriangleMesh(b.vertices, b.faces, rng.integers(0, 256, (len(b.vertices), 3), dtype=np.uint8))


def square(z: float, n: int = 8) -> TriangleMesh:
    """A unit square in the plane ``z``, ``2 n²`` triangles, normal +z."""
    g = np.linspace(0, 1, n + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return TriangleMesh(v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))


def random_similarity(seed=0) -> Similarity:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    return Similarity(torch.from_numpy(q), torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64), 0.37)


def test_export_round_trip_maps_to_the_input_frame(tmp_path):
    import open3d as o3d
    import trimesh

    world_from_input = random_similarity()
    world = box_mesh()
    path = write_ply(to_input_frame(world, world_from_input), tmp_path / "mesh.ply")
    expected = world_from_input.inverse().apply_points(torch.from_numpy(world.vertices)).numpy()
    tm = trimesh.load(path, process=False)
    np.testing.assert_allclose(tm.vertices, expected, atol=1e-5)
    np.testing.assert_array_equal(tm.faces, world.faces)
    np.testing.assert_array_equal(tm.visual.vertex_colors[:, :3], world.vertex_colors)
    assert tm.volume == pytest.approx(0.37**-3 * 1.0 * 2.0 * 0.5, rel=1e-5)  # outward winding kept
    om = o3d.io.read_triangle_mesh(str(path))
    np.testing.assert_allclose(np.asarray(om.vertices), expected, atol=1e-5)
    np.testing.assert_allclose(np.asarray(om.vertex_colors) * 255, world.vertex_colors, atol=0.5)
    back = read_mesh(path).transformed(world_from_input)
    np.testing.assert_allclose(back.vertices, world.vertices, atol=1e-5)


def test_a_reflection_keeps_the_faces_outward():
    refl = Similarity(torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)))
    assert box_mesh().transformed(refl).to_trimesh().volume > 0


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    def broken(_mesh):
        raise RuntimeError("disk full")

    write_ply(box_mesh(), tmp_path / "mesh.ply")
    before = (tmp_path / "mesh.ply").read_bytes()
    monkeypatch.setattr(export, "ply_bytes", lambda m: b"partial" + broken(m))
    with pytest.raises(RuntimeError):
        write_ply(box_mesh(), tmp_path / "mesh.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.ply"]
    assert (tmp_path / "mesh.ply").read_bytes() == before
    with pytest.raises(NerfpipeError, match="empty"):
        write_ply(TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)), tmp_path / "empty.ply")
    assert not (tmp_path / "empty.ply").exists()


def test_read_mesh_errors(tmp_path):
    with pytest.raises(NerfpipeError, match="not found"):
        read_mesh(tmp_path / "nope.ply")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(NerfpipeError, match="cannot read|no triangles"):
        read_mesh(tmp_path / "bad.ply")


def test_metrics_of_a_mesh_against_itself():
    m = box_mesh()
    r = compare_meshes(m, m, num_samples=20_000)
    assert r.fscore == 1.0 and r.precision == 1.0 and r.recall == 1.0
    assert r.chamfer_l1 < 1e-6 and r.normal_consistency == pytest.approx(1.0, abs=1e-6)
    assert r.threshold == pytest.approx(0.01 * math.sqrt(1 + 4 + 0.25))


@pytest.mark.parametrize("offset", [0.004, 0.02])
def test_metrics_of_parallel_squares_golden_values(offset):
    a, b = square(0.0), square(offset)
    r = compare_meshes(b, a, threshold=0.01, num_samples=20_000)
    assert r.accuracy == pytest.approx(offset, rel=1e-4) and r.completeness == pytest.approx(offset, rel=1e-4)
    assert r.chamfer_l1 == pytest.approx(offset, rel=1e-4)
    assert r.fscore == (1.0 if offset < 0.01 else 0.0)
    assert r.normal_consistency == pytest.approx(1.0)


def test_metrics_against_a_brute_force_reference():
    """Exact point-to-triangle distances are below sampled nearest-neighbour ones and close to them."""
    from scipy.spatial import cKDTree

    import trimesh

    a = TriangleMesh(*(lambda s: (s.vertices, s.faces))(trimesh.creation.icosphere(3)))
    b = TriangleMesh(a.vertices * 1.01 + 0.005, a.faces)
    r = compare_meshes(b, a, num_samples=20_000)
    pb, _ = sample_surface(b, 20_000, seed=0)
    pa, _ = sample_surface(a, 400_000, seed=5)
    nn = cKDTree(pa).query(pb)[0]
    assert r.accuracy <= nn.mean() + 1e-6
    assert r.accuracy == pytest.approx(nn.mean(), abs=0.003)


def test_point_fraction_of_points_at_known_distances():
    import trimesh

    s = trimesh.creation.icosphere(5)
    m = TriangleMesh(s.vertices, s.faces)
    dirs = np.random.default_rng(1).normal(size=(1000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = np.concatenate([dirs[:700] * 1.005, dirs[700:] * 1.1])  # 70% within 0.01, 30% at 0.1
    r = point_fraction(pts, m, threshold=0.01)
    assert r["fraction_within"] == pytest.approx(0.7) and r["num_points"] == 1000
