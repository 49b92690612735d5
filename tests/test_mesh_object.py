"""Meshing the object, not the fog: crop to the sparse points, drop fog walls on the box sides,
points figures with an explicit "on the object" rule, mesh area near the points; budgeted resolution."""

import math

import numpy as np
import pytest
import torch

from nerfpipe.mesh.clean import faces_near_box_sides
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.pipeline import BUDGET_RESOLUTIONS, MeshConfig, build_meshes, mesh_seconds, resolution_for_budget
from nerfpipe.mesh.reference import area_near_points, points_figures
from nerfpipe.mesh.trained import crop_to_points

BOX = torch.tensor([[-1.0] * 3, [1.0] * 3])


def sphere_mesh(radius: float = 0.5) -> TriangleMesh:
    import trimesh

    s = trimesh.creation.icosphere(4, radius=radius)
    return TriangleMesh(s.vertices, s.faces)


def wall(x: float, half: float = 0.5, n: int = 10) -> TriangleMesh:
    """A square in the plane ``X = x`` (``2 half`` wide), 2 n² triangles."""
    y, z = np.meshgrid(np.linspace(-half, half, n + 1), np.linspace(-half, half, n + 1), indexing="ij")
    verts = np.stack([np.full(y.size, x), y.ravel(), z.ravel()], 1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    i = i.ravel()
    faces = np.concatenate([np.stack([i, i + n + 1, i + 1], 1), np.stack([i + 1, i + n + 1, i + n + 2], 1)])
    return TriangleMesh(verts, faces)


def merged(a: TriangleMesh, b: TriangleMesh) -> TriangleMesh:
    return TriangleMesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.faces, b.faces + a.num_vertices]))


def test_faces_near_box_sides_are_the_fog_wall():
    mesh = merged(sphere_mesh(), wall(0.99))
    near = faces_near_box_sides(mesh, BOX.numpy(), 0.02)
    assert near[sphere_mesh().num_faces :].all() and not near[: sphere_mesh().num_faces].any()
    assert not faces_near_box_sides(mesh, BOX.numpy(), 0.005).any()


def test_fog_wall_is_dropped_by_the_pipeline():
    def field(p):  # a blob and a slab of "background paint" on the box's +x side
        blob = torch.sigmoid((0.5 - p.norm(dim=-1)) / 0.02)
        paint = torch.sigmoid((p[:, 0] - 0.95) / 0.01)
        return 100.0 * torch.maximum(blob, paint)

    keep = build_meshes(MeshConfig(method="mc", resolution=48, level=50.0, remove_unseen=False, box_sides=0.0, min_component=0.0), BOX, density_fn=field)
    cut = build_meshes(MeshConfig(method="mc", resolution=48, level=50.0, remove_unseen=False, min_component=0.0), BOX, density_fn=field)
    assert keep.full.vertices[:, 0].max() > 0.9
    radii = np.linalg.norm(cut.full.vertices, axis=1)
    assert np.abs(radii - 0.5).max() < 0.01 and cut.figures["box_side_faces_removed"] > 0
    assert cut.figures["box_world"] == BOX.tolist()


def test_crop_to_points_takes_their_robust_extent_inside_the_box():
    from test_mesh_clean import ring_cameras

    cams = ring_cameras()  # 8 cameras 4 units from the origin, looking at it
    gen = torch.Generator().manual_seed(0)
    xyz = torch.rand(1000, 3, generator=gen) * 0.4 - 0.2  # the object, in [-0.2, 0.2]^3
    xyz = torch.cat([xyz, torch.tensor([[50.0, 0, 0], [0, -30.0, 0], [0.0, 0.0, 0.9]])])  # three outliers
    box = crop_to_points(BOX, cams, xyz, margin=0.1)
    expected = torch.tensor([[-0.2] * 3, [0.2] * 3]) * 1.2  # extent grown by 10% of 0.4 on each side
    assert torch.allclose(box, expected, atol=0.03)
    far = crop_to_points(BOX, cams, xyz + 10.0, margin=0.1)  # no overlap: the box is kept
    assert torch.equal(far, BOX)


def test_points_figures_state_which_points_count():
    mesh = sphere_mesh()
    gen = np.random.default_rng(0)
    on = gen.normal(size=(300, 3))
    on = 0.5 * on / np.linalg.norm(on, axis=1, keepdims=True)
    off = gen.uniform(2.0, 3.0, size=(100, 3))  # background, far away
    points = np.concatenate([on, off])
    inside = np.all(np.abs(points) <= 1.0, axis=1)
    f = points_figures(mesh, points, threshold=0.02, on_object=inside)
    assert f["points_used"] == 300 and f["points_excluded"] == 100 and f["points_object_rule"] == "inside the meshed box"
    assert f["points_within_threshold"] == 1.0 and f["points_all_within_threshold"] == pytest.approx(0.75)
    g = points_figures(mesh, points, threshold=0.02)  # no box: the mesh's bounds grown by the threshold
    assert g["points_used"] == 300 and "bounds" in g["points_object_rule"]


def test_mesh_area_near_points_detects_fog():
    sphere = sphere_mesh()
    gen = np.random.default_rng(1)
    pts = gen.normal(size=(20000, 3))
    pts = 0.5 * pts / np.linalg.norm(pts, axis=1, keepdims=True)  # dense on the sphere only
    assert area_near_points(sphere, pts, 0.03) > 0.99
    fog = merged(sphere, wall(0.9, half=1.0))  # a 2x2 wall far from every point
    share = 4 * math.pi * 0.25 / (4 * math.pi * 0.25 + 4.0)  # the sphere's share of the area
    assert area_near_points(fog, pts, 0.03) == pytest.approx(share, abs=0.02)


def test_resolution_for_budget_steps_down_with_the_time_left():
    assert resolution_for_budget(256, None) == 256
    assert resolution_for_budget(256, 1e6) == 256
    assert resolution_for_budget(256, 2 * mesh_seconds(192) + 1) == 192
    assert resolution_for_budget(256, 2 * mesh_seconds(128) + 1) == 128
    assert resolution_for_budget(256, 0.0) == min(BUDGET_RESOLUTIONS)  # nothing fits: the cheapest
    assert resolution_for_budget(160, 1e6) == 160 and resolution_for_budget(160, 0.0) == 128
    assert resolution_for_budget(96, 0.0) == 96  # never above the requested resolution
    assert mesh_seconds(256) > mesh_seconds(192) > mesh_seconds(128)


def test_mesh_stage_lowers_the_resolution_under_a_short_budget():
    from nerfpipe.plugins.mesh import budgeted

    cfg = MeshConfig(method="mc", resolution=256)
    assert budgeted(cfg, None).resolution == 256
    assert budgeted(cfg, 2 * mesh_seconds(192) + 1).resolution == 192
    assert budgeted(MeshConfig(method="tsdf", resolution=256), 0.0).resolution == 256  # tsdf: untouched
