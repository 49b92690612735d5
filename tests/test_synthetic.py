"""Synthetic scenes: determinism, ray-casting geometry against analytic spheres, layouts on disk."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfpipe.util.errors import NerfpipeError
from nerfpipe.data.synthetic import (
    MESH_FILE,
    SCENE_FILE,
    SPHERE_RADIUS,
    SynthConfig,
    composite_scene,
    generate,
    load_gt_mesh,
    orbit_cameras,
    raycaster,
    render_view,
    sample_points,
    sphere_scene,
    view_name,
)

SMALL = dict(views=6, width=33, height=33)  # odd size: the centre pixel ray is the optical axis


def _analytic_sphere_t(origins, directions, radius):
    """Distance along unit rays to the first hit of a sphere at the origin (nan on a miss)."""
    b = -(origins * directions).sum(-1)
    disc = b**2 - ((origins**2).sum(-1) - radius**2)
    return np.where(disc >= 0, b - np.sqrt(np.clip(disc, 0, None)), np.nan)


@pytest.fixture(scope="module")
def sphere_views():
    cfg = SynthConfig(scene="sphere", **SMALL)
    mesh, cams = sphere_scene(), orbit_cameras(cfg)
    scene = raycaster(mesh)
    return cfg, mesh, cams, scene, [render_view(scene, mesh, cams, i) for i in range(len(cams))]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The composite scene in both layouts, same cameras."""
    root = tmp_path_factory.mktemp("synth")
    cfg = dict(views=10, width=40, height=32, num_points=600)
    return {layout: generate(root / layout, SynthConfig(layout=layout, **cfg)) for layout in ("colmap", "blender")}


def test_generation_is_deterministic(tmp_path):
    a = generate(tmp_path / "a", SynthConfig(**SMALL))
    b = generate(tmp_path / "b", SynthConfig(**SMALL))
    c = generate(tmp_path / "c", SynthConfig(seed=1, **SMALL))
    name = f"images/{view_name(3)}.png"
    assert (a.path / name).read_bytes() == (b.path / name).read_bytes()
    assert (a.path / name).read_bytes() != (c.path / name).read_bytes()
    assert (a.path / "sparse/0/points3D.bin").read_bytes() == (b.path / "sparse/0/points3D.bin").read_bytes()


def test_centre_depth_is_distance_to_sphere(sphere_views):
    cfg, _, cams, _, views = sphere_views
    for view in views:
        centre = view.depth[cfg.height // 2, cfg.width // 2]
        assert abs(centre - (cfg.distance - SPHERE_RADIUS)) < 1e-3


def test_depth_matches_analytic_ray_sphere_hits(sphere_views):
    from nerfpipe.data.rays import camera_rays

    cfg, _, cams, _, views = sphere_views
    for i, view in enumerate(views):
        rays = camera_rays(cams, i)
        o, d = rays.origins.numpy(), rays.directions.numpy()
        t = _analytic_sphere_t(o, d, SPHERE_RADIUS)
        normal = (o + np.nan_to_num(t)[..., None] * d) / SPHERE_RADIUS
        frontal = np.isfinite(t) & (-(normal * d).sum(-1) > 0.3)  # hits away from the silhouette
        assert np.all(view.alpha[frontal])
        np.testing.assert_allclose(view.depth[frontal], t[frontal], atol=2e-3)


def test_alpha_is_the_projected_disk(sphere_views):
    cfg, _, cams, _, views = sphere_views
    focal = float(cams.fx[0])
    r_px = focal * SPHERE_RADIUS / math.sqrt(cfg.distance**2 - SPHERE_RADIUS**2)
    v, u = np.mgrid[: cfg.height, : cfg.width] + 0.5
    dist = np.hypot(u - cfg.width / 2, v - cfg.height / 2)
    for view in views:
        assert abs(view.alpha.sum() - math.pi * r_px**2) < 2 * math.pi * r_px * 0.5
        assert np.all(view.alpha[dist < r_px - 1]) and not np.any(view.alpha[dist > r_px + 1])
        assert np.all(np.isinf(view.depth[~view.alpha]))
        # pixel centres at +0.5: the hit pixels are symmetric about the principal point
        centroid = [u[view.alpha].mean(), v[view.alpha].mean()]
        np.testing.assert_allclose(centroid, [cfg.width / 2, cfg.height / 2], atol=0.05)


def test_sparse_point_visibility_matches_convexity(sphere_views):
    """On a sphere a point is visible iff it faces the camera (and projects inside the image)."""
    cfg, mesh, cams, scene, _ = sphere_views
    pts = sample_points(scene, mesh, cams, SynthConfig(scene="sphere", num_points=300, min_track_length=1, **SMALL))
    to_cam = cams.centers.numpy()[None] - pts.xyz[:, None]
    normal = pts.xyz / np.linalg.norm(pts.xyz, axis=-1, keepdims=True)
    cos = (to_cam * normal[:, None]).sum(-1) / np.linalg.norm(to_cam, axis=-1)
    clear = np.abs(cos) > 0.05  # grazing points depend on the faceting
    assert np.array_equal(pts.visible[clear], (cos > 0)[clear])


def test_colmap_model_round_trips_through_pycolmap(written):
    import pycolmap

    result = written["colmap"]
    rec = pycolmap.Reconstruction(str(result.path / "sparse" / "0"))
    assert rec.num_reg_images() == len(result.cameras) and rec.num_points3D() == result.num_points > 0
    cams = result.cameras
    for image in rec.images.values():
        i = int(Path(image.name).stem.split("_")[1])
        np.testing.assert_allclose(image.cam_from_world().matrix(), cams.cam_from_world[i, :3].numpy(), atol=1e-12)
        np.testing.assert_allclose(image.camera.params, [cams.fx[i], cams.fy[i], cams.cx[i], cams.cy[i]])
        assert (image.camera.width, image.camera.height) == (int(cams.width[i]), int(cams.height[i]))
    assert rec.compute_mean_reprojection_error() < 1e-6
    assert min(p.track.length() for p in rec.points3D.values()) >= SynthConfig().min_track_length


def test_colmap_tracks_are_the_generator_visibility(written):
    """The adapter reads back exactly the (point, view) pairs the generator found unoccluded, at their pixels."""
    from nerfpipe import data_adapters

    result = written["colmap"]
    cfg = SynthConfig(layout="colmap", views=10, width=40, height=32, num_points=600)  # the fixture's
    truth = sample_points(raycaster(result.mesh), result.mesh, result.cameras, cfg)
    scene = data_adapters.load(result.path)
    pts = scene.points
    view = torch.tensor([int(Path(p).stem.split("_")[1]) for p in scene.images.paths])
    seen = np.zeros_like(truth.visible)
    seen[pts.track_point.numpy(), view[pts.track_camera].numpy()] = True
    assert len(pts.track_point) == int(truth.visible.sum()) and np.array_equal(seen, truth.visible)
    np.testing.assert_allclose(pts.track_xy.numpy(), truth.uv[pts.track_point.numpy(), view[pts.track_camera].numpy()], atol=1e-9)


def test_files_and_mesh_in_input_frame(written):
    import trimesh

    for layout, result in written.items():
        record = json.loads((result.path / SCENE_FILE).read_text())
        assert record["config"]["layout"] == layout
        mesh = load_gt_mesh(result.path)
        assert isinstance(mesh, trimesh.Trimesh) and (result.path / MESH_FILE).is_file()
        np.testing.assert_allclose(mesh.vertices, result.mesh.vertices, atol=1e-6)
        assert np.all(np.abs(mesh.bounds) < 1.0)
    blender = written["blender"].path
    frames = {s: json.loads((blender / f"transforms_{s}.json").read_text())["frames"] for s in ("train", "val", "test")}
    assert sum(len(f) for f in frames.values()) == len(written["blender"].cameras)
    import imageio.v3 as iio

    rgba = iio.imread(blender / (frames["train"][0]["file_path"] + ".png"))
    assert rgba.shape == (32, 40, 4) and set(np.unique(rgba[..., 3])) == {0, 255}


def test_composite_parts_are_disjoint():
    import trimesh

    parts = composite_scene()
    mesh = trimesh.Trimesh(parts.vertices, parts.faces)  # merges duplicate vertices
    bodies = mesh.split(only_watertight=False)
    assert len(bodies) == 3 and all(b.is_watertight for b in bodies)
    for a in bodies:
        for b in bodies:
            if a is not b:
                assert not np.any(b.contains(a.vertices))
    assert sorted(b.euler_number for b in bodies) == [0, 2, 2]  # torus genus 1, two spheres


@pytest.mark.parametrize("layout", ["colmap", "blender"])
def test_adapters_read_the_generator_cameras(written, layout):
    from nerfpipe import data_adapters

    result = written[layout]
    scene = data_adapters.load(result.path)
    order = [int(Path(p).stem.split("_")[1]) for p in scene.images.paths]
    expected = result.cameras[torch.tensor(order)]
    back = scene.world_from_input.inverse().apply_world_from_cam(scene.cameras.world_from_cam.double())
    torch.testing.assert_close(back, expected.world_from_cam, atol=1e-5, rtol=0)
    for k in ("fx", "fy", "cx", "cy"):
        torch.testing.assert_close(getattr(scene.cameras, k).double(), getattr(expected, k), atol=1e-4, rtol=0)
    assert scene.has_alpha == (layout == "blender")


def test_refuses_to_overwrite_foreign_folders(tmp_path):
    (tmp_path / "keep.txt").write_text("user data")
    with pytest.raises(NerfpipeError, match="not empty"):
        generate(tmp_path, SynthConfig(**SMALL))
    with pytest.raises(NerfpipeError, match="without scene.json"):
        generate(tmp_path, SynthConfig(**SMALL), overwrite=True)
    assert (tmp_path / "keep.txt").exists()


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """The room scene, small: the composite object on the floor of a closed, patterned room."""
    cfg = SynthConfig(scene="room", views=8, width=40, height=30, num_points=400, min_elevation_deg=10.0, max_elevation_deg=60.0)
    return cfg, generate(tmp_path_factory.mktemp("room") / "room", cfg)


def test_room_every_ray_hits_its_walls_floor_or_object(room):
    """A closed room: no pixel without a surface; each hit of the surroundings lies on the floor, a wall or the ceiling."""
    from nerfpipe.data.rays import camera_rays
    from nerfpipe.data.synthetic import ROOM_FLOOR, ROOM_HALF_WIDTH, ROOM_HEIGHT, cast

    cfg, result = room
    mesh = result.mesh
    scene = raycaster(mesh)
    hits_object = []
    for i in range(len(result.cameras)):
        rays = camera_rays(result.cameras, i)
        o, d = rays.origins.reshape(-1, 3).numpy(), rays.directions.reshape(-1, 3).numpy()
        t, face, _ = cast(scene, o, d)
        assert (face >= 0).all()
        p = o + t[:, None] * d
        far = face >= mesh.object_faces
        on_plane = (np.abs(p[far, 2] - ROOM_FLOOR) < 1e-4) | (np.abs(p[far, 2] - ROOM_FLOOR - ROOM_HEIGHT) < 1e-4) \
            | (np.abs(np.abs(p[far, :2]) - ROOM_HALF_WIDTH) < 1e-4).any(-1)
        assert on_plane.all()
        hits_object.append((~far).mean())
    assert 0.1 < min(hits_object) and max(hits_object) < 0.9  # each view shows the object and its surroundings


def test_room_gt_mesh_is_the_object_alone(room):
    """gt_mesh.ply (and the mesh figures against it) hold the composite object, not the room around it."""
    from nerfpipe.data.synthetic import ROOM_FLOOR

    _, result = room
    gt, obj = load_gt_mesh(result.path), composite_scene(0)
    underside = (np.abs(obj.vertices[obj.faces][..., 2] - ROOM_FLOOR) < 1e-9).all(-1)  # on the floor: never seen
    assert 0 < underside.sum() and len(gt.faces) == len(obj.faces) - underside.sum()
    assert np.allclose(gt.bounds, obj.bounds(), atol=1e-6) and np.allclose(gt.faces, obj.faces[~underside])
    parts = result.mesh.object_part(), result.mesh.surroundings_part()
    assert len(parts[0].faces) + len(parts[1].faces) == len(result.mesh.faces)
    assert np.allclose(parts[1].vertices[parts[1].faces], result.mesh.vertices[result.mesh.faces[len(gt.faces):]])
    record = json.loads((result.path / SCENE_FILE).read_text())
    assert record["num_faces"] == len(gt.faces) and np.allclose(record["bbox"], obj.bounds())


def test_room_sparse_points_on_object_and_surroundings(room):
    """As SfM would find them: points on the object and on the floor and walls, each seen by at least three views."""
    import pycolmap

    from nerfpipe.data.synthetic import ROOM_FLOOR

    _, result = room
    rec = pycolmap.Reconstruction(str(result.path / "sparse" / "0"))
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    inside = (np.abs(xyz) <= 0.95 * 1.3).all(-1)  # the composite object's extent
    assert inside.sum() > 100 and (~inside).sum() > 20  # 8 views: few surroundings points lie in three of them
    assert (np.abs(xyz[~inside, 2] - ROOM_FLOOR) < 1e-4).sum() > 10  # the floor's
    assert min(len(p.track.elements) for p in rec.points3D.values()) >= 3


def test_room_refuses_cameras_outside_it():
    with pytest.raises(NerfpipeError, match="inside its room"):
        SynthConfig(scene="room")  # the default band reaches 25 degrees below the horizon: under the floor
    SynthConfig(scene="room", min_elevation_deg=10.0, max_elevation_deg=60.0)
