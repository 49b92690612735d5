"""The mesh of the object alone: the support plane and what lies below it, fog that sight lines cross,
pieces far from the object, faces seen only from behind; objects without a support keep everything."""

import dataclasses
import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.scene import Similarity
from nerfpipe.mesh.clean import (
    faces_blocking_sight_lines, faces_on_or_below_plane, faces_outside_footprint, remove_small_components, support_plane, visible_faces,
)
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.metrics import sample_surface
from nerfpipe.mesh.pipeline import MeshConfig, build_meshes, plane_in_input_frame
from nerfpipe.mesh.reference import SightLines
from nerfpipe.mesh.views import look_at


def sphere(radius: float, center=(0.0, 0.0, 0.0), subdivisions: int = 4) -> TriangleMesh:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions, radius=radius)
    return TriangleMesh(s.vertices + np.asarray(center), s.faces)


def square(z: float, half: float = 1.5, n: int = 30) -> TriangleMesh:
    """The square ``|x|, |y| <= half`` at height ``z``, normal +z, 2 n² triangles."""
    x, y = np.meshgrid(np.linspace(-half, half, n + 1), np.linspace(-half, half, n + 1), indexing="ij")
    verts = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    i = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    return TriangleMesh(verts, np.concatenate([np.stack([i, i + n + 1, i + 1], 1), np.stack([i + 1, i + n + 1, i + n + 2], 1)]))


def merge(*meshes: TriangleMesh) -> TriangleMesh:
    offsets = np.cumsum([0] + [m.num_vertices for m in meshes[:-1]])
    return TriangleMesh(np.concatenate([m.vertices for m in meshes]), np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]))


def ring(n: int = 12, radius: float = 3.0, heights=(1.5,)) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.concatenate([np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n, h)], 1) for h in heights])


def cameras_at(centers: np.ndarray, target=(0.0, 0.0, 0.3), size: int = 64) -> Cameras:
    mats = np.stack([look_at(c, np.asarray(target, dtype=np.float64), np.array([0.0, 0.0, 1.0])) for c in centers])
    f = size / (2 * math.tan(math.radians(30)))
    return Cameras.create(mats, f, f, size / 2, size / 2, size, size, dtype=torch.float64)


def observations(points, normals, centers):
    """Sight lines from every camera to the points on their side of the surface."""
    cam, pt = np.nonzero(((centers[:, None] - points[None]) * normals[None]).sum(-1) > 0)
    return SightLines(points=points, centers=centers, point_idx=pt, cam_idx=cam)


def candidates(mesh: TriangleMesh, points: np.ndarray):
    samples, normals = sample_surface(mesh, 20_000)
    return np.concatenate([samples, points]), np.concatenate([normals, np.zeros_like(points)])


def test_the_plane_an_object_stands_on_is_found_and_removed():
    ball, table = sphere(0.5, (0.0, 0.0, 0.5)), square(0.0)  # the ball rests on z = 0
    scene, cams = merge(ball, table), ring()
    points = sample_surface(ball, 800, seed=1)[0]  # sparse points on the object only: a white table
    cand, normals = candidates(scene, points)
    plane = support_plane(cand, points, cams, 0.02, normals)
    assert plane is not None and plane[2] > 0.999 and abs(plane[3]) < 0.01  # +z, towards the cameras
    below = faces_on_or_below_plane(scene, plane, 0.02)
    assert below[ball.num_faces :].all()  # the whole table goes
    assert below[: ball.num_faces].mean() < 0.03  # the ball stays, but for the 2 % cap within the tolerance
    textured = np.concatenate([points, sample_surface(table, 1500, seed=2)[0]])  # table points too: same plane
    cand, normals = candidates(scene, textured)
    np.testing.assert_allclose(support_plane(cand, textured, cams, 0.02, normals), plane, atol=0.01)


def test_support_plane_side_tests_in_chunks_give_the_same_plane(monkeypatch):
    """The side tests hold [points, planes] arrays a chunk of planes at a time (100,000 points against 4,000
    hypotheses would be 3.2 GB each): chunks of any size choose the same plane, and the same one as the tests of
    every plane at once."""
    import nerfpipe.mesh.clean as clean

    ball, table = sphere(0.5, (0.0, 0.0, 0.5)), square(0.0)
    points = np.concatenate([sample_surface(ball, 800, seed=1)[0], sample_surface(table, 300, seed=2)[0]])
    cand, normals = candidates(merge(ball, table), points)
    monkeypatch.setattr(clean, "SIDE_TEST_ELEMENTS", 1 << 40)
    whole = support_plane(cand, points, ring(), 0.02, normals)
    assert whole is not None and whole[2] > 0.999
    for elements in (len(points) * 7, len(points) * 1000 + 5, 1):  # uneven chunks, and one plane at a time
        monkeypatch.setattr(clean, "SIDE_TEST_ELEMENTS", elements)
        np.testing.assert_array_equal(support_plane(cand, points, ring(), 0.02, normals), whole)


def test_a_flat_slice_of_fog_without_sparse_points_is_no_support():
    """A few-view mesh: the table under the object is a small noisy patch and a tilted slice of fog holds more
    surface samples, but no sparse point: the table, which holds the points of the object's base, is chosen."""
    rng = np.random.default_rng(0)
    cams = ring()
    ball = sample_surface(sphere(0.3, (0.0, 0.0, 0.3)), 400, seed=1)[0]
    table_pts = np.column_stack([rng.uniform(-0.6, 0.6, (400, 2)), np.zeros(400)])
    table = np.column_stack([rng.uniform(-0.6, 0.6, (400, 2)), rng.normal(scale=0.003, size=400)])
    tilt = math.radians(15.0)  # the fog slice z = -0.2 + tan(15 deg) x, under every point and camera
    xy = np.column_stack([rng.uniform(-1.5, 0.6, 1000), rng.uniform(-1.5, 1.5, 1000)])
    sheet = np.column_stack([xy, -0.2 + math.tan(tilt) * xy[:, 0]])
    normal = np.array([-math.sin(tilt), 0.0, math.cos(tilt)])
    points = np.concatenate([ball, table_pts])
    cand = np.concatenate([sheet, table, points])
    normals = np.concatenate([np.tile(normal, (1000, 1)), np.tile([0.0, 0.0, 1.0], (400, 1)), np.zeros_like(points)])
    fog = support_plane(cand, points, cams, 0.02, normals, min_points=0.0)
    assert fog is not None and abs(fog[:3] @ normal) > 0.999  # by the samples alone, the slice holds more
    plane = support_plane(cand, points, cams, 0.02, normals)
    assert plane is not None and plane[2] > 0.999 and abs(plane[3]) < 0.01


def test_no_support_plane_without_one():
    ball, cams = sphere(0.5, (0.0, 0.0, 0.5)), ring()
    points = sample_surface(ball, 800, seed=1)[0]
    cand, normals = candidates(ball, points)
    assert support_plane(cand, points, cams, 0.02, normals) is None  # a lone ball: a cap holds at most 2 tol / diameter
    scene = merge(ball, square(0.0))
    cand, normals = candidates(scene, points)
    all_around = ring(heights=(1.5, -1.5))  # seen from below too: the table is not a support
    assert support_plane(cand, points, all_around, 0.02, normals) is None
    rng = np.random.default_rng(0)  # fog: a slab of triangles at random orientations under the ball
    corners = rng.uniform([-1.5, -1.5, -0.3], [1.5, 1.5, 0.0], size=(20_000, 1, 3))
    fog = TriangleMesh((corners + rng.normal(scale=0.03, size=(20_000, 3, 3))).reshape(-1, 3), np.arange(60_000).reshape(-1, 3))
    cand, normals = candidates(merge(ball, fog), points)
    assert support_plane(cand, points, cams, 0.02, normals) is None  # slices of fog are not surfaces


def test_plane_in_input_frame():
    rot = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    world_from_input = Similarity(rot, torch.tensor([0.5, 0.0, -2.0], dtype=torch.float64), 2.0)
    plane = np.array([0.0, 0.6, 0.8, -0.3])
    x_input = np.random.default_rng(0).normal(size=(10, 3))
    x_world = world_from_input.apply_points(torch.from_numpy(x_input)).numpy()
    back = plane_in_input_frame(plane, world_from_input)
    np.testing.assert_allclose(np.linalg.norm(back[:3]), 1.0)
    np.testing.assert_allclose(x_input @ back[:3] + back[3], (x_world @ plane[:3] + plane[3]) / 2.0, atol=1e-12)


def test_fog_that_sight_lines_cross_is_peeled_and_the_surface_kept():
    ball, fog = sphere(0.5), sphere(1.0)  # a shell around the ball: every camera sees the ball through it
    scene = merge(ball, fog)
    pts, normals = sample_surface(ball, 8000, seed=2)  # about 2 cm apart
    origins, targets = observations(pts, normals, ring()).segments()
    blocking = faces_blocking_sight_lines(scene, origins, targets, 0.03, keep_near=pts)
    assert not blocking[: ball.num_faces].any()  # the ball is where the lines end: never blocking
    assert blocking[ball.num_faces :].mean() > 0.3  # the shell is crossed on every side the cameras look through
    inflated = TriangleMesh(ball.vertices * 1.02, ball.faces)  # the surface 1 cm in front of its points
    assert faces_blocking_sight_lines(inflated, origins, targets, 0.03).mean() > 0.5  # grazing lines cross it early (0.64)
    assert faces_blocking_sight_lines(inflated, origins, targets, 0.03, keep_near=pts).mean() < 0.005  # next to its points (0.0014)


def test_pieces_far_from_the_object_go_and_near_ones_stay():
    obj = sphere(0.5)
    near = sphere(0.2, (0.75, 0.0, 0.0), subdivisions=3)  # 5 cm from the object: a part of it
    far_sheet = square(0.0, half=1.0, n=20)
    far_sheet.vertices += np.array([5.0, 0.0, 0.0])  # larger than the object, 4.5 away, no sparse point on it
    scene = merge(obj, near, far_sheet)
    anchors = sample_surface(merge(obj, near), 500, seed=3)[0]
    out = remove_small_components(scene, 0.01, max_gap=0.2, anchors=anchors)
    assert out.num_faces == obj.num_faces + near.num_faces
    assert out.info["floater_faces_removed"] == far_sheet.num_faces
    by_area = remove_small_components(scene, 0.01, max_gap=0.2)  # without anchors the largest piece is the main one
    assert by_area.num_faces == far_sheet.num_faces


def test_a_sheet_beside_the_object_that_no_point_lies_on_goes():
    """Within the gap, a large piece without sparse points (fog) goes; a part of the object holding its share of
    the points stays, and so does a small piece without any (a patch of a texture-less side cut off by holes)."""
    obj = sphere(0.5)
    part = sphere(0.2, (0.75, 0.0, 0.0), subdivisions=3)
    sheet = square(-0.6, half=0.6, n=20)  # 0.1 under the object, half its area
    patch = square(0.0, half=0.05, n=2)
    patch.vertices += np.array([0.0, 0.6, 0.0])  # 0.1 beside it, under a percent of its area
    scene = merge(obj, part, sheet, patch)
    anchors = sample_surface(merge(obj, part), 500, seed=3)[0]
    kept = remove_small_components(scene, 0.0, max_gap=0.2, anchors=anchors)
    assert kept.num_faces == scene.num_faces  # without the rule every piece within the gap stays
    out = remove_small_components(scene, 0.0, max_gap=0.2, anchors=anchors, unsupported=(0.02, 0.05, 0.01))
    assert out.num_faces == scene.num_faces - sheet.num_faces
    assert out.info["floater_faces_removed"] == sheet.num_faces


def test_a_far_piece_that_holds_its_share_of_the_points_stays():
    """Beyond the gap a piece goes as a floater unless it holds ``far_min_anchors`` of the sparse points: a part of the
    object the mesh does not join to the rest (Sacre Coeur's dome above its facade, the drum a hole), not fog."""
    obj = sphere(0.5)
    dome = sphere(0.3, (0.0, 0.0, 1.5))  # 0.7 above the object: beyond a gap of 0.2
    fog = sphere(0.3, (2.0, 0.0, 0.0))  # as far and as large, one sparse point on it
    scene = merge(obj, dome, fog)
    anchors = np.concatenate([sample_surface(obj, 400, seed=3)[0], sample_surface(dome, 100, seed=4)[0], sample_surface(fog, 1, seed=5)[0]])
    gap_only = remove_small_components(scene, 0.01, max_gap=0.2, anchors=anchors, unsupported=(0.02, 0.05, 0.01))
    assert gap_only.num_faces == obj.num_faces  # the gap alone: the dome goes with the fog
    out = remove_small_components(scene, 0.01, max_gap=0.2, anchors=anchors, unsupported=(0.02, 0.05, 0.01), far_min_anchors=0.02)
    assert out.num_faces == obj.num_faces + dome.num_faces  # 20 % of the points: kept; the fog's 0.2 %: not
    assert out.info["floater_faces_removed"] == fog.num_faces


def test_sheets_beside_an_object_on_its_support_go_and_the_object_stays():
    """A sheet of fog joined to the object (a skirt just above the table, a wall at the region's side): their feet on the
    support plane lie outside the footprint of the object's points; the object, its texture-less overhang within the
    margin included, stays. Points on the table (within the tolerance) do not widen the footprint."""
    obj = sphere(0.5, (0.0, 0.0, 0.5))
    skirt = square(0.08, half=1.2, n=24)  # 0.08 above the table: beyond the support tolerance
    wall = TriangleMesh(np.array([[1.0, -0.5, 0.0], [1.0, 0.5, 0.0], [1.0, 0.5, 1.0], [1.0, -0.5, 1.0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    scene = merge(obj, skirt, wall)
    pts = sample_surface(obj, 400, seed=6)[0]
    pts = pts[pts[:, 0] < 0.4]  # the +x side of the object is texture-less: no points there
    table_pts = np.random.default_rng(0).uniform([-1.2, -1.2, 0.0], [1.2, 1.2, 0.01], (100, 3))
    plane = np.array([0.0, 0.0, 1.0, 0.0])
    out = faces_outside_footprint(scene, plane, np.concatenate([pts, table_pts]), tolerance=0.05, margin=0.15)
    n_obj, n_skirt = obj.num_faces, skirt.num_faces
    assert not out[:n_obj].any()  # all of the object, its side without points too
    feet = skirt.vertices[skirt.faces].mean(1)[:, :2]
    far = np.linalg.norm(feet, axis=1) > 0.5 + 0.15 + 0.05
    assert out[n_obj : n_obj + n_skirt][far].all() and out[n_obj + n_skirt :].all()
    assert not faces_outside_footprint(scene, plane, table_pts, tolerance=0.05, margin=0.15).any()  # no object points: nothing


def test_faces_seen_only_from_behind_are_unseen():
    shell = sphere(1.0)
    open_front = shell.submesh(shell.vertices[shell.faces].mean(1)[:, 0] < 0.7)  # a hole facing +x
    cams = cameras_at(np.array([[4.0, y, z] for y in (-0.3, 0.3) for z in (-0.3, 0.3)]), target=(0.0, 0.0, 0.0))
    back_wall = open_front.vertices[open_front.faces].mean(1)[:, 0] < -0.5  # seen through the hole, from inside
    assert visible_faces(open_front, cams)[back_wall].mean() > 0.5
    assert not visible_faces(open_front, cams, front_only=True)[back_wall].any()


def ball_on_table(points: torch.Tensor) -> torch.Tensor:
    """Density: a ball of radius 0.35 resting on a table (the half-space z < 0)."""
    inside = ((points - torch.tensor([0.0, 0.0, 0.35], dtype=points.dtype)).norm(dim=-1) < 0.35) | (points[..., 2] < 0)
    return inside.to(points.dtype) * 100.0


def test_pipeline_meshes_the_ball_not_the_table():
    aabb = torch.tensor([[-1.0, -1.0, -0.3], [1.0, 1.0, 1.0]])
    centers = ring(heights=(1.2, 2.0))
    ball = sphere(0.35, (0.0, 0.0, 0.35))
    pts, normals = sample_surface(ball, 2000, seed=4)
    pts, normals = pts[pts[:, 2] > 0.05], normals[pts[:, 2] > 0.05]
    cfg = MeshConfig(method="mc", resolution=64, level=50.0, colors=False)
    out = build_meshes(cfg, aabb, density_fn=ball_on_table, cameras=cameras_at(centers), sight_lines=observations(pts, normals, centers))
    assert out.figures["support_plane"] is not None and out.figures["support_faces_removed"] > 0
    voxel = out.figures["voxel_size"]
    assert out.full.vertices[:, 2].min() > 0.0  # nothing of the table is left
    dist = np.abs(np.linalg.norm(out.full.vertices - [0.0, 0.0, 0.35], axis=1) - 0.35)
    assert dist.max() < voxel  # only the ball
    kept = sample_surface(ball, 5000, seed=5)[0]
    kept = kept[kept[:, 2] > 0.1]  # above the support band
    assert np.mean(cKDTree(out.full.vertices).query(kept)[0] < 2 * voxel) > 0.99  # and all of it
    free = build_meshes(cfg, aabb, density_fn=lambda p: ball_on_table(p) * (p[..., 2] >= 0),
                        cameras=cameras_at(ring(heights=(1.2, -1.2))), sight_lines=observations(pts, normals, centers))
    assert free.figures["support_plane"] is None and "support_faces_removed" not in free.figures


def test_a_support_plane_known_from_the_sparse_points_is_the_one_removed():
    """Where the model knows the plane from the sparse points (``support``), the mesh stage removes that plane, not
    one it finds in the mesh (a TSDF table's orientation wanders from run to run); with ``support_from_points`` off,
    or without it, the mesh's own."""
    aabb = torch.tensor([[-1.0, -1.0, -0.3], [1.0, 1.0, 1.0]])
    centers = ring(heights=(1.2, 2.0))
    ball = sphere(0.35, (0.0, 0.0, 0.35))
    pts, normals = sample_surface(ball, 2000, seed=4)  # the ball's base touches the table: points on it
    cfg = MeshConfig(method="mc", resolution=64, level=50.0, colors=False, close_holes=0)  # the removed band stays open
    args = dict(density_fn=ball_on_table, cameras=cameras_at(centers), sight_lines=observations(pts, normals, centers))
    tilt = math.radians(2.0)
    known = np.array([math.sin(tilt), 0.0, math.cos(tilt), -0.01]) * 2.0  # not unit length: normalised
    out = build_meshes(cfg, aabb, support=known, **args)
    np.testing.assert_allclose(out.figures["support_plane"], known / np.linalg.norm(known[:3]))
    assert out.figures["support_plane_from"] == "sparse points"
    tol = out.figures["support_tolerance_world"]
    height = out.full.vertices @ (known[:3] / 2.0) + known[3] / 2.0
    assert (height[out.full.faces] >= tol).any(axis=1).all()  # every face left reaches above the known band
    own = build_meshes(dataclasses.replace(cfg, support_from_points=False), aabb, support=known, **args)
    assert own.figures["support_plane_from"] == "mesh" and abs(own.figures["support_plane"][2]) > 0.9999  # the table z = 0
    assert build_meshes(cfg, aabb, **args).figures["support_plane"] == own.figures["support_plane"]
    floor = build_meshes(cfg, aabb, support=np.array([0.0, 0.0, 1.0, 0.25]), **args)  # z = -0.25: no point of the ball on it
    assert floor.figures["support_plane_from"] == "mesh" and floor.figures["support_plane"] == own.figures["support_plane"]


def test_colmap_mouse_white_table_has_no_plane_a_textured_one_would(scene_path):
    """Real cameras and sparse points: the white table under the mouse carries (almost) no sparse point,
    so the points alone give no support plane; the same scene with points on a table under the mouse does."""
    from nerfpipe.data_adapters import load

    from nerfpipe.mesh.metrics import robust_diagonal
    from nerfpipe.mesh.trained import crop_to_points

    scene = load(scene_path("colmap_mouse"))
    xyz, centers = scene.points.xyz.double().numpy(), scene.cameras.centers.double().reshape(-1, 3).numpy()
    lo, hi = crop_to_points(scene.aabb, scene.cameras, scene.points.xyz, 0.05).double().numpy()
    obj = xyz[np.all((xyz >= lo) & (xyz <= hi), axis=1)]
    tol = 0.01 * robust_diagonal(obj)
    assert support_plane(obj, obj, centers, tol, min_inliers=0.05) is None
    rng = np.random.default_rng(0)
    floor = np.quantile(obj[:, 2], 0.005) - tol  # world +z is the cameras' mean up
    table = np.column_stack([rng.uniform(lo[0], hi[0], 1500), rng.uniform(lo[1], hi[1], 1500), floor + rng.normal(scale=tol / 4, size=1500)])
    both = np.concatenate([obj, table])
    plane = support_plane(both, both, centers, tol, min_inliers=0.05)
    assert plane is not None and plane[2] > 0.999 and abs(plane[3] + floor) < tol / 2
    assert np.all(centers @ plane[:3] + plane[3] > 0)  # every camera above it


def test_a_wall_behind_the_object_is_no_support_plane():
    """Cameras on one side of a wall (a facade, the back of a dome in a photo collection): the wall bounds the
    points and has every camera on one side, but its normal is 90 degrees from the cameras' up: refused; the same
    scene turned so that the wall is a floor is accepted."""
    ball, table = sphere(0.5, (0.0, 0.0, 0.5)), square(0.0)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # +z (the table's normal) -> -y
    wall = TriangleMesh(merge(ball, table).vertices @ turn.T, merge(ball, table).faces)
    cams = ring() @ turn.T
    points = sample_surface(ball, 800, seed=1)[0] @ turn.T
    cand, normals = candidates(wall, points)
    found = support_plane(cand, points, cams, 0.02, normals)
    assert found is not None and found[1] < -0.999  # without up: the wall qualifies
    assert support_plane(cand, points, cams, 0.02, normals, up=np.array([0.0, 0.0, 1.0])) is None
    assert support_plane(cand, points, cams, 0.02, normals, up=np.array([0.0, -1.0, 0.2])) is not None
