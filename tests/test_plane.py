"""The support plane's texture (``nerfpipe.fields.plane``) and where the fast model uses it."""

import math

import numpy as np
import pytest
import torch

from nerfpipe.fields.plane import PlaneTexture, PlaneTextureConfig, contract_2d, plane_hits
from nerfpipe.models.base import SceneInfo
from nerfpipe.models.fast import SPARSITY_MIN_ARC, FastConfig

FLOOR = torch.tensor([0.0, 0.0, 1.0, 0.5])  # z = -0.5, normal up
BOX = torch.tensor([[-1.0] * 3, [1.0] * 3])


def _rays(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g) * 2.0
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return origins, directions


def test_plane_hits_meet_the_plane_from_the_cameras_side():
    """Against the obvious reference, ray by ray: a hit lies on the plane, in front of an origin above it, on a ray going down."""
    origins, directions = _rays(2000)
    t, hit = plane_hits(origins, directions, FLOOR)
    for o, d, ti, h in zip(origins.tolist(), directions.tolist(), t.tolist(), hit.tolist()):
        above, down = o[2] > -0.5, d[2] < 0
        assert h == (above and down)
        if h:
            assert ti > 0 and o[2] + ti * d[2] == pytest.approx(-0.5, abs=1e-4)
    assert 0.2 < hit.float().mean() < 0.4  # about a quarter: above and going down


def test_contract_2d_is_the_identity_inside_the_disc_and_squeezes_the_rest_into_twice_its_radius():
    u = torch.tensor([[0.3, -0.4], [0.0, 0.0], [1.0, 0.0], [3.0, 4.0], [1e6, 0.0]])
    c = contract_2d(u)
    assert torch.equal(c[:3], u[:3])
    assert c[3].norm() == pytest.approx(2.0 - 1.0 / 5.0) and torch.allclose(c[3] / c[3].norm(), u[3] / 5.0)
    assert c[4].norm() == pytest.approx(2.0, abs=1e-5)
    r = torch.linspace(0.5, 50.0, 200)[:, None] * torch.tensor([[0.6, 0.8]])
    norms = contract_2d(r).norm(dim=-1)
    assert (norms.diff() > 0).all() and norms.max() < 2.0  # monotone, bounded


def test_the_texture_keeps_the_background_where_rays_miss_and_learns_where_they_meet():
    torch.manual_seed(0)
    tex = PlaneTexture(PlaneTextureConfig(levels=(4, 8)), FLOOR, torch.zeros(3), radius=1.0)
    origins, directions = _rays(512)
    bg = torch.rand(512, 3)
    out = tex(origins, directions, bg)
    _, hit = plane_hits(origins, directions, FLOOR)
    assert torch.equal(out[~hit], bg[~hit])
    alpha = tex.cfg.initial_opacity  # mostly transparent at first
    assert torch.allclose(torch.sigmoid(tex.mlp[2].bias[3]), torch.tensor(alpha))
    assert torch.allclose(out[hit], bg[hit], atol=alpha + 1e-6)
    assert tex.coordinates(torch.tensor([[0.0, 0.0, -0.5]])).abs().max() < 1e-6  # the centre's foot is the texture's middle
    target = torch.zeros(512, 3)  # a black table in front of a bright background: the sheet must become opaque and dark
    opt = torch.optim.Adam(tex.parameters(), lr=0.05)
    first = None
    for _ in range(150):
        loss = ((tex(origins, directions, bg) - target)[hit] ** 2).mean()
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in tex.parameters())
        opt.step()
    assert float(loss.detach()) < 0.1 * first


def _camera_above(eye, target, size: int = 64, fov_deg: float = 60.0):
    from nerfpipe.data.cameras import Cameras
    from nerfpipe.data.orbit import look_at

    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    pose = look_at(torch.tensor(eye), torch.tensor(target), torch.tensor([0.0, 1.0, 0.0]))
    return Cameras.create(pose[None], f, f, size / 2, size / 2, size, size)


def test_points_at_inverts_the_contracted_coordinates():
    tex = PlaneTexture(PlaneTextureConfig(levels=(4,)), FLOOR, torch.tensor([0.3, -0.2, 0.7]), radius=0.8)
    c = (torch.rand(500, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1) * 0.99
    c = c[(2 * c).norm(dim=-1) < 1.99]  # inside the rim (infinitely far)
    points = tex.points_at(c)
    assert torch.allclose(points[:, 2], torch.tensor(-0.5), atol=1e-5)  # on the plane
    assert torch.allclose(tex.coordinates(points), c, atol=1e-4)


def test_the_texture_is_only_where_training_cameras_see_the_plane_steeply_enough():
    """A camera looking straight down at the texture's middle: its footprint is covered, the rest of the plane is
    not (the texture transparent there whatever it learned); ``min_views`` 2 needs a second camera; a camera seeing
    the plane at a grazing angle does not count; ``min_views`` 0 covers everything."""
    tex = PlaneTexture(PlaneTextureConfig(levels=(4, 8), initial_opacity=0.9, min_views=1, min_incidence=0.2), FLOOR, torch.zeros(3), radius=1.0)
    down = _camera_above([0.0, 0.0, 1.5], [0.0, 0.0, -0.5])  # 2 above the floor, 60 degrees: a disc of about 1.15
    inside, outside = torch.tensor([[0.0, 0.0, -0.5], [0.5, 0.5, -0.5]]), torch.tensor([[3.0, 0.0, -0.5], [-1.6, -1.6, -0.5], [0.0, 40.0, -0.5]])
    everywhere = tex.rgba(torch.cat([inside, outside]))[:, 3]  # before any cover: the texture everywhere
    assert (everywhere > 0.8).all()
    tex.cover(down)
    assert torch.equal(tex.rgba(inside)[:, 3], everywhere[:2]) and torch.equal(tex.rgba(outside)[:, 3], torch.zeros(3))
    share = float(tex.coverage.mean())  # about the footprint's share of the contracted square [-2, 2]^2
    assert 0.5 * (2 * 1.15) ** 2 / 16 < share < 1.5 * (2 * 1.15) ** 2 / 16
    tex.cfg.min_views = 2
    tex.cover(down)
    assert tex.coverage.max() == pytest.approx(0.5)  # one camera is half of two
    below = _camera_above([0.0, 0.0, -1.5], [0.0, 0.0, -3.0])  # under the floor, looking away: sees nothing of its top
    grazing = _camera_above([3.0, 0.0, -0.45], [0.0, 0.0, -0.5])  # 0.05 above it, 3 away: at most 0.05 / 1.9 steep
    both = _camera_above([0.0, 0.2, 1.5], [0.0, 0.0, -0.5])
    from nerfpipe.data.cameras import Cameras

    tex.cover(Cameras.cat([down, below, grazing]))
    assert tex.coverage.max() == pytest.approx(0.5)
    tex.cover(Cameras.cat([down, both]))
    assert torch.equal(tex.rgba(inside)[:, 3], everywhere[:2]) and float((tex.coverage == 1).float().mean()) < share  # where both see it
    tex.cfg.min_views = 0
    tex.cover(down)
    assert torch.equal(tex.coverage, torch.ones_like(tex.coverage))


def test_the_fast_model_covers_its_texture_from_the_training_cameras_and_old_checkpoints_keep_it_everywhere():
    cam = _camera_above([0.0, 0.0, 2.0], [0.0, 0.0, -1.0])
    model = FastConfig(preset="small").setup(_info(cameras=cam))
    assert 0.0 < float(model.plane.coverage.mean()) < 1.0
    state = model.state_dict()
    assert torch.equal(state["plane.coverage"], model.plane.coverage)
    again = FastConfig(preset="small").setup(_info())  # rebuilt without cameras: the checkpoint's coverage
    assert torch.equal(again.plane.coverage, torch.ones_like(again.plane.coverage))
    again.load_state_dict(state)
    assert torch.equal(again.plane.coverage, model.plane.coverage)
    old = FastConfig(preset="small").setup(_info(cameras=cam))  # a checkpoint from before the coverage: everywhere
    old.load_state_dict({k: v for k, v in state.items() if k != "plane.coverage"})
    assert torch.equal(old.plane.coverage, torch.ones_like(old.plane.coverage))


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from nerfpipe.data.synthetic import SynthConfig, generate

    cfg = SynthConfig(scene="room", views=8, width=40, height=30, num_points=400, min_elevation_deg=10.0, max_elevation_deg=60.0)
    return generate(tmp_path_factory.mktemp("room") / "room", cfg).path


@pytest.mark.parametrize("max_points", [None, 150])
def test_the_room_scenes_support_plane_is_its_floor(room, monkeypatch, max_points):
    """In the loaded (normalised) frame: the room's floor z = ROOM_FLOOR, mapped there, is the plane found in its points
    (also from a sample of them, as for captures of more than SUPPORT_MAX_POINTS)."""
    from nerfpipe.data.synthetic import ROOM_FLOOR
    from nerfpipe.data_adapters import load
    from nerfpipe.training import trainer
    from nerfpipe.training.trainer import scene_info, support_plane_of

    if max_points is not None:
        monkeypatch.setattr(trainer, "SUPPORT_MAX_POINTS", max_points)
    scene = load(room)
    assert max_points is None or len(scene.points.xyz) > 2 * max_points
    plane = support_plane_of(scene)
    assert plane is not None and scene_info(scene).support_plane == plane
    floor = scene.world_from_input.apply_points(torch.tensor([[0.0, 0.0, ROOM_FLOOR], [1.0, 0.0, ROOM_FLOOR], [0.0, 1.0, ROOM_FLOOR]], dtype=torch.float64))
    normal = np.cross((floor[1] - floor[0]).numpy(), (floor[2] - floor[0]).numpy())
    normal /= np.linalg.norm(normal)
    assert abs(float(np.dot(normal, plane[:3]))) > math.cos(math.radians(1.0))
    assert np.abs(floor.numpy() @ np.array(plane[:3]) + plane[3]).max() < 1e-3 * float((scene.aabb[1] - scene.aabb[0]).norm())


def test_colmap_mouses_support_plane_bounds_its_points_from_below(scene_path):
    """A white table with 1.5 % of the points on it: the plane under the mouse, its normal near the cameras' up."""
    from nerfpipe.data.normalize import upright_direction
    from nerfpipe.data_adapters import load
    from nerfpipe.mesh.metrics import robust_diagonal
    from nerfpipe.training.trainer import SUPPORT_MAX_TILT, SUPPORT_TOLERANCE, support_plane_of

    scene = load(scene_path("colmap_mouse"))
    plane = np.array(support_plane_of(scene))
    points = scene.points.xyz.double().numpy()
    lo, hi = scene.aabb.double().numpy()
    points = points[np.all((points >= lo) & (points <= hi), axis=1)]  # the object region's: the plane under the object
    height = points @ plane[:3] + plane[3]
    tol = SUPPORT_TOLERANCE * robust_diagonal(points)
    assert np.mean(height > -tol) >= 0.98 and np.mean(np.abs(height) < tol) >= 0.01
    up = upright_direction(scene.split_cameras("train")).double().numpy()
    assert np.degrees(np.arccos(plane[:3] @ up / np.linalg.norm(up))) < SUPPORT_MAX_TILT
    centres = scene.split_cameras("train").centers.double().reshape(-1, 3).numpy()
    assert np.mean(centres @ plane[:3] + plane[3] > 0) >= 0.95
    from nerfpipe.training.trainer import above_support

    above = above_support(scene)  # the mesh figures' points on the mouse: not on the table, not under it
    every = scene.points.xyz.double().numpy()
    assert above is not None and np.array_equal(above, every @ plane[:3] + plane[3] > tol)
    assert 100 < (~above).sum() < 0.2 * len(points)  # colmap_mouse: the table's points in and around the box


def test_no_support_plane_without_points_or_surroundings(room):
    import dataclasses

    from nerfpipe.data_adapters import load
    from nerfpipe.training.trainer import support_plane_of

    scene = load(room)
    assert support_plane_of(dataclasses.replace(scene, points=None)) is None
    assert support_plane_of(dataclasses.replace(scene, has_alpha=True)) is None  # an object on white: nothing around it


def _info(**kw) -> SceneInfo:
    base = dict(aabb=BOX, near=0.5, far=10.0, num_images=20, pixels_per_image=100, unbounded=True, arc=2 * math.pi,
                support_plane=(0.0, 0.0, 1.0, 1.0))
    return SceneInfo(**{**base, **kw})


def test_the_fast_model_textures_the_support_plane_of_objects_photographed_from_around_them():
    model = FastConfig(preset="small").setup(_info())
    assert model.plane is not None and model.stats()["support_texture"] == 1.0
    grouped = {id(p) for g in model.param_groups() for p in g["params"]}
    assert all(id(p) in grouped for p in model.plane.parameters())  # every parameter trained, once
    assert sum(id(p) in grouped for p in model.parameters()) == len(list(model.parameters()))
    assert FastConfig(preset="small").setup(_info(arc=SPARSITY_MIN_ARC)).plane is not None  # one side of an object
    assert FastConfig(preset="small").setup(_info(arc=math.radians(63))).plane is None  # a facade (the castle: -0.1 dB)
    assert FastConfig(preset="small").setup(_info(support_plane=None)).plane is None
    assert FastConfig(preset="small", support_texture=False).setup(_info()).plane is None
    assert FastConfig(preset="small", background_field=False).setup(_info()).plane is None  # the demo's object on white
    assert FastConfig(preset="small", support_texture=True).setup(_info(arc=0.5)).plane is not None


def test_the_texture_renders_in_front_of_the_surroundings_and_round_trips_through_a_checkpoint():
    from nerfpipe.data.rays import RayBundle

    torch.manual_seed(0)
    model = FastConfig(preset="small").setup(_info()).eval()
    n = 64
    origins = torch.tensor([[0.0, -3.0, 2.0]]).expand(n, 3)
    directions = torch.nn.functional.normalize(torch.stack([torch.linspace(-0.5, 0.5, n), torch.ones(n), torch.full((n,), -1.5)], -1), dim=-1)
    rays = RayBundle(origins=origins, directions=directions, cam_idx=torch.zeros(n, dtype=torch.long), z_scale=torch.ones(n))
    with torch.no_grad():
        model.plane.mlp[2].bias[3] = 20.0  # opaque
        model.plane.mlp[2].bias[:3] = -20.0  # black
        rgb = model.get_outputs(rays, torch.ones(n, 3)).rgb
    _, hit = plane_hits(origins, directions, model.plane.plane)
    assert hit.all() and rgb.max() < 0.05  # whatever lay behind it, the black table
    state = model.state_dict()
    assert any(k.startswith("plane.") for k in state)
    again = FastConfig(preset="small").setup(_info())
    again.load_state_dict(state)
    assert torch.equal(again.plane.mlp[2].bias, model.plane.mlp[2].bias)
    old = FastConfig(preset="small").setup(_info())  # a checkpoint from before the texture: rendered without it
    old.load_state_dict({k: v for k, v in state.items() if not k.startswith("plane.")}, strict=False)
    assert old.plane is None


def test_the_texture_lies_at_its_distance_behind_what_the_field_behind_the_box_holds_in_front_of_it():
    """A wall of the surroundings in front of the table's far plane hides it (a ray past a table's edge, towards the
    room's wall); where the ray meets the plane under the box, the texture shows. Before session 36 the texture was
    composited over everything behind the box."""
    from nerfpipe.data.rays import RayBundle
    from nerfpipe.estimators.occupancy import ray_aabb_intersect

    model = FastConfig(preset="small").setup(_info()).eval()
    model.front = False  # the field's part in front of the box, opaque here too, would hide all (test_unbounded's)
    n = 256
    origins = torch.tensor([[0.0, -4.0, 1.5]]).expand(n, 3)
    down = torch.linspace(0.2, 1.5, n)  # grazing rays meet the floor far away, steep ones under the box
    directions = torch.nn.functional.normalize(torch.stack([torch.zeros(n), torch.ones(n), -down], -1), dim=-1)
    rays = RayBundle(origins=origins, directions=directions, cam_idx=torch.zeros(n, dtype=torch.long), z_scale=torch.ones(n))
    with torch.no_grad():
        model.plane.mlp[2].bias[3], model.plane.mlp[2].bias[:3] = 20.0, -20.0  # an opaque black table
        for table in model.behind.density_grid.tables:
            table.fill_(50.0)  # everything behind the box opaque ...
        model.behind.mlp[2].weight.zero_()
        model.behind.mlp[2].bias.fill_(20.0)  # ... and white
        for table in model.field.density_grid.tables:
            table.fill_(-50.0)  # the box empty
        out = model.get_outputs(rays, torch.full((n, 3), 0.5))
    t_plane, hit = plane_hits(origins, directions, model.plane.plane)
    t_in, t_exit = ray_aabb_intersect(origins, directions, BOX)
    clear = out.acc < 0.01  # rays the box lets through
    behind_wall = hit & (t_plane > t_exit + 0.5) & clear
    under_box = hit & (t_in <= t_exit) & (t_plane <= t_exit + 1e-4) & clear  # through the box to its floor
    assert behind_wall.sum() > 20 and under_box.sum() > 5
    assert out.rgb[behind_wall].min() > 0.95  # the surroundings' wall in front of the far table
    assert out.rgb[under_box].max() < 0.05  # the table where the ray meets it first
    in_front = hit & (t_in > t_exit)  # rays that meet the table before the box: the opaque surroundings come first
    assert in_front.sum() > 20 and out.rgb[in_front].min() > 0.95


def test_the_mesh_stage_takes_the_support_plane_of_objects_photographed_from_around_them():
    """``known_support``: the sparse points' plane (``SceneInfo.support_plane``) for the mesh stage where the cameras
    surround the object, as for the texture; none for a facade or a model that knows no scene."""
    from nerfpipe.mesh.trained import known_support

    assert known_support(FastConfig(preset="small").setup(_info())) == (0.0, 0.0, 1.0, 1.0)
    assert known_support(FastConfig(preset="small", support_texture=False).setup(_info())) == (0.0, 0.0, 1.0, 1.0)
    assert known_support(FastConfig(preset="small").setup(_info(arc=math.radians(63)))) is None
    assert known_support(FastConfig(preset="small").setup(_info(support_plane=None))) is None
    assert known_support(torch.nn.Linear(1, 1)) is None
