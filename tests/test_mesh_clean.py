"""Cleaning and simplification: floaters, unseen faces, holes, quadric collapse, Hausdorff."""

import math

import numpy as np
import pytest
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.mesh.clean import close_holes, hausdorff_distance, remove_small_components, simplify, smooth, visible_faces
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.views import look_at
from nerfpipe.util.errors import NerfpipeError


def sphere(radius=1.0, center=(0.0, 0.0, 0.0), subdivisions=4) -> TriangleMesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    colors = np.tile(np.array([[200, 30, 30]], np.uint8), (len(s.vertices), 1))
    return TriangleMesh(s.vertices + np.asarray(center), s.faces, colors)


def merge(*meshes: TriangleMesh) -> TriangleMesh:
    offsets = np.cumsum([0] + [m.num_vertices for m in meshes[:-1]])
    return TriangleMesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]),
        np.concatenate([m.vertex_colors for m in meshes]),
    )


def ring_cameras(n=8, distance=4.0, size=64) -> Cameras:
    mats = []
    for k in range(n):
        a, el = 2 * math.pi * k / n, (-0.5 if k % 2 else 0.6)
        eye = distance * np.array([math.cos(a) * math.cos(el), math.sin(a) * math.cos(el), math.sin(el)])
        mats.append(look_at(eye, np.zeros(3), np.array([0.0, 0, 1])))
    f = size / (2 * math.tan(math.radians(25)))
    return Cameras.create(np.stack(mats), f, f, size / 2, size / 2, size, size, dtype=torch.float64)


def test_simplify_respects_the_target_and_bounds_the_hausdorff_distance():
    full = sphere(subdivisions=5)  # 20480 faces
    small = simplify(full, 2000)
    assert small.num_faces <= 2000 and small.num_faces > 1500
    assert small.vertex_colors is not None and (small.vertex_colors == [200, 30, 30]).all()
    d = hausdorff_distance(full, small)
    assert 0 < d["mean"] < d["max"] < 0.01  # unit sphere: well under 1% of the radius
    assert small.to_trimesh().is_watertight


def test_simplify_refuses_a_target_not_below_the_face_count():
    m = sphere(subdivisions=2)
    with pytest.raises(NerfpipeError, match="not below the mesh's 320 faces"):
        simplify(m, 320)
    with pytest.raises(NerfpipeError, match="at least 4"):
        simplify(m, 2)


def test_hausdorff_of_a_scaled_copy_is_the_offset():
    a = sphere()
    b = TriangleMesh(a.vertices * 1.05, a.faces)
    d = hausdorff_distance(a, b)
    assert d["max"] == pytest.approx(0.05, rel=0.05) and d["mean"] == pytest.approx(0.05, rel=0.1)


def test_small_floaters_are_removed_and_the_object_kept():
    obj, floater = sphere(1.0), sphere(0.03, center=(2.0, 0.0, 0.0), subdivisions=1)
    out = remove_small_components(merge(obj, floater), min_diameter_fraction=0.05)
    assert out.num_faces == obj.num_faces
    assert out.info["floater_faces_removed"] == floater.num_faces
    np.testing.assert_allclose(out.vertices.max(0), obj.vertices.max(0))


def test_faces_no_camera_sees_are_found():
    outer, inner = sphere(1.0), sphere(0.4, subdivisions=2)
    seen = visible_faces(merge(outer, inner), ring_cameras())
    assert seen[: outer.num_faces].mean() > 0.97
    assert not seen[outer.num_faces :].any()


def test_visibility_against_direct_rays_to_face_centres():
    """Slow reference: one ray from each camera to each face centre; seen if nothing is hit first.

    The z-buffer test may only add faces (it is lenient at silhouettes); it must never miss one.
    """
    import open3d as o3d

    m, cams = sphere(1.0, subdivisions=3), ring_cameras(n=3, size=96)
    fast = visible_faces(m, cams, tolerance=1e-3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(m.to_open3d_tensor())
    centres = m.vertices[m.faces].mean(1)
    slow = np.zeros(m.num_faces, bool)
    for i in range(len(cams)):
        eye = cams.centers[i].numpy()
        dist = np.linalg.norm(centres - eye, axis=1)
        rays = np.concatenate([np.tile(eye, (len(centres), 1)), (centres - eye) / dist[:, None]], 1)
        t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        slow |= t >= dist - 1e-3  # the sphere is inside every view (checked by the fast path's image test)
    assert 0.8 * m.num_faces < slow.sum() < m.num_faces
    assert not (slow & ~fast).any()
    assert (fast & ~slow).sum() < 0.1 * m.num_faces


def rippled(mesh: TriangleMesh, amplitude: float, seed: int = 0) -> TriangleMesh:
    """Each vertex moved along its normal by a smooth random field a few edges wide (a sum of random plane waves)."""
    rng = np.random.default_rng(seed)
    v = mesh.vertices
    waves = rng.normal(size=(12, 3)) * 12.0  # wavelengths about half the unit sphere's radius
    phases = rng.uniform(0, 2 * np.pi, 12)
    bump = np.sin(v @ waves.T + phases).sum(1) / np.sqrt(12)
    return TriangleMesh(v + amplitude * bump[:, None] * mesh.vertex_normals(), mesh.faces, mesh.vertex_colors)


def test_smooth_flattens_ripples_and_keeps_order_colours_and_size():
    clean = sphere(subdivisions=5)
    noisy = rippled(clean, 0.02)
    out = smooth(noisy, 3)
    assert out.num_vertices == noisy.num_vertices and (out.faces == noisy.faces).all()
    assert (out.vertex_colors == noisy.vertex_colors).all()
    radial = lambda m: np.linalg.norm(m.vertices, axis=1)
    assert np.std(radial(out)) < 0.85 * np.std(radial(noisy))  # the ripples lower
    assert abs(np.mean(radial(out)) - 1.0) < 0.005  # neither shrunk nor inflated
    centres = lambda m: m.vertices[m.faces].mean(1)
    agree = lambda m: np.mean(np.sum(m.face_normals() * centres(m) / np.linalg.norm(centres(m), axis=1, keepdims=True), 1))
    assert 1 - agree(out) < 0.4 * (1 - agree(noisy))  # and the surface's normals far truer (what shading shows)
    assert smooth(noisy, 0) is noisy


def test_smooth_keeps_a_boxs_edges_and_corners():
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0)).subdivide_to_size(0.03)
    mesh = TriangleMesh(np.asarray(box.vertices), np.asarray(box.faces))
    rng = np.random.default_rng(0)
    noisy = TriangleMesh(mesh.vertices + rng.normal(scale=0.002, size=mesh.vertices.shape), mesh.faces)
    out = smooth(noisy, 3)
    corner_ids = np.nonzero((np.abs(mesh.vertices) > 0.499).all(1))[0]
    assert len(corner_ids) == 8
    assert np.abs(out.vertices[corner_ids] - mesh.vertices[corner_ids]).max() < 0.02  # corners stay (Laplacian rounds them)
    off_side = lambda m: np.abs(np.abs(m.vertices).max(1) - 0.5).mean()  # every vertex's largest coordinate is 0.5 on the box
    assert off_side(out) < off_side(noisy)  # the sides flatter


def test_close_holes_makes_a_punctured_sphere_watertight():
    m = sphere(subdivisions=3)
    holed = m.submesh(~(m.faces == 0).any(axis=1))  # remove the fan around vertex 0: a pentagonal hole
    assert not holed.to_trimesh().is_watertight
    closed = close_holes(holed, max_hole_edges=30)
    assert closed.to_trimesh().is_watertight and closed.num_faces == holed.num_faces + 3


def test_depth_map_fast_pinhole_path_matches_nerfpipe_rays():
    """Open3D's pinhole ray generator (fast path) against nerfpipe's camera_rays (reference)."""
    import dataclasses

    import open3d as o3d

    from nerfpipe.mesh.clean import _depth_map

    m, cams = sphere(1.0, subdivisions=4), ring_cameras(n=2, size=64)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(m.to_open3d_tensor())
    fast = _depth_map(scene, cams, 1)
    ref = _depth_map(scene, dataclasses.replace(cams, distortion=torch.ones_like(cams.distortion)), 1)  # OPENCV, zero params
    assert torch.equal(torch.isfinite(fast), torch.isfinite(ref)) and torch.isfinite(fast).float().mean() > 0.2
    hit = torch.isfinite(fast)
    torch.testing.assert_close(fast[hit], ref[hit], atol=1e-4, rtol=0)


def test_edge_pieces_part_faces_that_touch_at_a_vertex_only():
    from nerfpipe.mesh.clean import component_labels, edge_pieces

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [-1, 0, 0], [0, -1, 0.0]])
    mesh = TriangleMesh(v, np.array([[0, 1, 2], [1, 3, 2], [0, 4, 5]]))  # two faces share an edge, the third vertex 0
    count, label = edge_pieces(mesh)
    assert count == 2 and label[0] == label[1] != label[2]
    assert len(np.unique(component_labels(mesh)[1][mesh.faces[:, 0]])) == 1  # by shared vertices: one piece


def test_a_small_flap_hanging_on_a_vertex_goes_with_the_floaters():
    ball = sphere(subdivisions=3)
    tip = int(np.argmax(ball.vertices[:, 2]))  # the flap hangs on the ball's top vertex: one piece by vertices
    top = ball.vertices[tip]
    flap_v = np.concatenate([ball.vertices, top + np.array([[0.01, 0.0, 0.005], [0.0, 0.01, 0.005]])])
    faces = np.concatenate([ball.faces, [[tip, len(ball.vertices), len(ball.vertices) + 1]]])
    mesh = TriangleMesh(flap_v, faces, np.concatenate([ball.vertex_colors, ball.vertex_colors[:2]]))
    out = remove_small_components(mesh, min_diameter_fraction=0.01)
    assert out.num_faces == ball.num_faces and out.to_trimesh().is_watertight
    assert remove_small_components(mesh, min_diameter_fraction=0.0).num_faces == mesh.num_faces  # off: kept
