"""``nerfpipe mesh`` on a stand-in run (an analytic sphere model) and ``nerfpipe eval-mesh``."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfpipe.cli import main
from nerfpipe.data.cameras import Cameras
from nerfpipe.data.scene import ImageSet, SceneData, Similarity
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.export import write_ply
from nerfpipe.mesh.views import look_at
from nerfpipe.models.base import Model, RenderOutputs
from nerfpipe.util.errors import NerfpipeError

RADIUS = 0.5
WORLD_FROM_INPUT = Similarity(torch.eye(3, dtype=torch.float64), torch.tensor([0.2, 0.0, -0.1], dtype=torch.float64), 2.0)


class SphereModel(Model):
    """A radiance field that is a solid sphere: soft density, analytic ray-traced renders."""

    def density_fn(self, points):
        return 400.0 * torch.sigmoid((RADIUS - points.norm(dim=-1)) / 0.01)

    def rgb_fn(self, points, directions):
        return torch.tensor([0.2, 0.4, 0.9]).expand(len(points), 3)

    def get_outputs(self, rays, background):
        b = (rays.origins * rays.directions).sum(-1)
        disc = b**2 - ((rays.origins**2).sum(-1) - RADIUS**2)
        hit = disc > 0
        t = torch.where(hit, -b - disc.clamp(min=0).sqrt(), torch.zeros_like(b))
        acc = hit.float()
        rgb = torch.where(hit[..., None], torch.tensor([0.2, 0.4, 0.9]), background)
        return RenderOutputs(rgb=rgb, depth=t * acc, acc=acc)


def sphere_scene(n=12, size=48) -> SceneData:
    mats = []
    for k in range(n):
        a, el = 2 * math.pi * k / n, (0.5 if k % 2 else -0.3)
        mats.append(look_at(3.0 * np.array([math.cos(a) * math.cos(el), math.sin(a) * math.cos(el), math.sin(el)]), np.zeros(3), np.array([0, 0, 1.0])))
    f = size / (2 * math.tan(math.radians(20)))
    cams = Cameras.create(np.stack(mats), f, f, size / 2, size / 2, size, size)
    return SceneData(cams, ImageSet(array=np.zeros((n, size, size, 3), np.uint8)), {"train": np.arange(n)}, 1.0, 5.0,
                     torch.tensor([[-1.0] * 3, [1.0] * 3]), WORLD_FROM_INPUT, Path("sphere"), "test")


@pytest.fixture
def fake_run(tmp_path, monkeypatch):
    import nerfpipe.training.runs

    monkeypatch.setattr(nerfpipe.training.runs, "load_run", lambda run_dir, device="cpu": (sphere_scene(), SphereModel(), {}))
    return tmp_path


@pytest.mark.parametrize("method", ["mc", "tsdf"])
def test_mesh_command_writes_the_outputs_in_the_input_frame(fake_run, method, capsys):
    import trimesh

    assert main(["mesh", str(fake_run), "--method", method, "--resolution", "64", "--faces", "1500", "--views.tsdf-size", "48", *(["--level", "200"] if method == "mc" else [])]) == 0
    figures = json.loads(capsys.readouterr().out)
    out = fake_run / "mesh"
    assert sorted(p.name for p in out.iterdir()) == ["mesh.json", "mesh.ply", "mesh_simplified.ply", "mesh_views.png"]
    full = trimesh.load(out / "mesh.ply", process=False)
    small = trimesh.load(out / "mesh_simplified.ply", process=False)
    centre = WORLD_FROM_INPUT.inverse().apply_points(torch.zeros(1, 3, dtype=torch.float64))[0].numpy()
    radii = np.linalg.norm(full.vertices - centre, axis=1)
    assert radii.mean() == pytest.approx(RADIUS / 2.0, rel=0.03)  # input units: world / scale 2
    assert len(small.faces) <= 1500 and figures["hausdorff_max"] > 0
    assert abs(full.visual.vertex_colors[:, 2].astype(float).mean() - 0.9 * 255) < 15
    assert figures["smooth_steps"] == (1 if method == "tsdf" else 0)  # the TSDF surface's ripple; mc's level set is smooth
    assert method == "mc" or figures["truncation_voxels"] == 4.0


def test_mesh_command_bad_input_leaves_nothing(fake_run, capsys):
    assert main(["mesh", str(fake_run), "--resolution", "32", "--level", "1e6", "--method", "mc"]) == 2
    assert "outside the density range" in capsys.readouterr().err
    assert main(["mesh", str(fake_run), "--resolution", "32", "--faces", "100000000"]) == 2
    assert main(["mesh", str(fake_run), "--resolution", "32", "--level-from", "quantile", "--level", "1e6", "--method", "mc"]) == 2
    assert "not below" in capsys.readouterr().err
    assert main(["mesh", str(fake_run), "--resolution", "32", "--smooth", "-1"]) == 2
    assert "smooth" in capsys.readouterr().err
    assert main(["mesh", str(fake_run), "--resolution", "32", "--truncation", "0"]) == 2
    assert "truncation" in capsys.readouterr().err
    assert not (fake_run / "mesh").exists()


def test_eval_mesh_cli(tmp_path, capsys):
    import trimesh

    s = trimesh.creation.icosphere(4)
    write_ply(TriangleMesh(s.vertices, s.faces), tmp_path / "a.ply")
    write_ply(TriangleMesh(s.vertices * 1.005, s.faces), tmp_path / "b.ply")
    assert main(["eval-mesh", str(tmp_path / "b.ply"), str(tmp_path / "a.ply"), "--json", "--samples", "20000"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["fscore"] == 1.0 and r["chamfer_l1"] == pytest.approx(0.005, rel=0.05)
    assert main(["eval-mesh", str(tmp_path / "b.ply"), str(tmp_path / "missing.ply")]) == 2


def test_eval_mesh_against_colmap_points(tmp_path, capsys):
    """A synthetic COLMAP scene: its gt mesh holds every sparse point; a shifted mesh fewer."""
    from nerfpipe.data.synthetic import SynthConfig, generate

    scene = tmp_path / "scene"
    generate(scene, SynthConfig(views=6, width=32, height=32, num_points=300, min_track_length=2))
    assert main(["eval-mesh", str(scene / "gt_mesh.ply"), str(scene), "--json", "--samples", "5000"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["points_within_threshold"] == 1.0 and r["gt_mesh_fscore"] == 1.0
    gt = trimesh_load(scene / "gt_mesh.ply")
    write_ply(TriangleMesh(gt.vertices + [0.0, 0.0, 0.05], gt.faces), tmp_path / "shifted.ply")
    assert main(["eval-mesh", str(tmp_path / "shifted.ply"), str(scene), "--json", "--samples", "5000"]) == 0
    assert json.loads(capsys.readouterr().out)["points_within_threshold"] < 0.9


def trimesh_load(path):
    import trimesh

    return trimesh.load(path, process=False)


@pytest.mark.parametrize("rule", ["agreement", "quantile"])
def test_level_from_rendered_depth(fake_run, capsys, rule):
    assert main(["mesh", str(fake_run), "--resolution", "48", "--faces", "1000", "--level-from", rule, "--method", "mc"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["level_rule"] == rule
    if rule == "quantile":  # the density at expected depth: 200 on the sphere model's surface
        assert figures["level"] == pytest.approx(200.0, rel=0.15)
    else:  # rays become half opaque where 400 * 0.01 * softplus((r - R) / 0.01) = ln 2: r = R + 0.017
        assert 30.0 < figures["level"] < 120.0 and len(figures["level_candidates"]) > 10
    full = trimesh_load(fake_run / "mesh" / "mesh.ply")
    centre = WORLD_FROM_INPUT.inverse().apply_points(torch.zeros(1, 3, dtype=torch.float64))[0].numpy()
    radii = 2.0 * np.linalg.norm(full.vertices - centre, axis=1)  # world units (scale 2)
    front = RADIUS + (0.017 if rule == "agreement" else 0.0)  # where the surface was put
    assert abs(radii.mean() - front) < 0.5 * figures["voxel_size"]


def test_tsdf_views_follow_the_time_budget():
    """With a budget, the first view is timed and only the views that fit are kept (never fewer than
    min_views, smaller when even those do not fit; evenly spread from the first); without one, all requested;
    frames are the same either way."""
    from nerfpipe.mesh.trained import MIN_TSDF_SHRINK, tsdf_frames

    scene, model = sphere_scene(), SphereModel()
    train = scene.split_cameras("train")
    cams, frame = tsdf_frames(model, train, 12, 32, 4096, "cpu")
    assert len(cams) == 12
    enough, enough_frame = tsdf_frames(model, train, 12, 32, 4096, "cpu", seconds=1e6)
    assert len(enough) == 12 and torch.equal(enough.width, cams.width)
    depth, rgb = enough_frame(0)
    assert np.array_equal(depth, frame(0)[0]) and (depth > 0).any()
    # no time at all: min_views views, evenly spread from the first, at the smallest size (the budget, not the views, holds)
    tight, tight_frame = tsdf_frames(model, train, 12, 32, 4096, "cpu", seconds=1e-9, min_views=3)
    assert len(tight) == 3 and torch.equal(tight.world_from_cam[0], cams.world_from_cam[0])
    assert int(tight.width[0]) == round(32 * MIN_TSDF_SHRINK) and (tight_frame(0)[0] > 0).any()
    # the renders' seconds are summed for mesh.json: the timed first view's and each later one's
    before = tight_frame.seconds()
    assert before > 0 and tight_frame(1) is not None and tight_frame.seconds() > before


def test_tsdf_render_budget_keeps_a_reserve_that_grows_with_the_time_left():
    """What the renders may take of the time left: ``budget_share`` of it after a reserve of ``fixed_seconds``, or of
    ``fixed_share`` of it where that is more; nothing when the reserve takes it all; no limit without a budget."""
    from nerfpipe.mesh.trained import RenderedViews

    views = RenderedViews(budget_share=0.6, fixed_seconds=10.0, fixed_share=0.3)
    assert views.render_budget(None) is None
    assert views.render_budget(21.5) == pytest.approx(0.6 * 11.5)  # session 68's starved fox: 8 views of 105 px before
    assert views.render_budget(80.0) == pytest.approx(0.6 * 56.0)
    assert views.render_budget(5.0) == 0.0
    # what fusion may give: as many faces as the reserve has time for at seconds_per_face each
    per_face = dataclasses.replace(views, seconds_per_face=40e-6)
    assert per_face.max_faces(None) is None
    assert per_face.max_faces(18.6) == round(10.0 / 40e-6)  # the demo under --time-budget 60: 250,000 (530,000 before)
    assert per_face.max_faces(80.0) == round(24.0 / 40e-6)
    for name, value in (("fixed_share", 1.0), ("budget_share", 0.0), ("fixed_seconds", -1.0), ("seconds_per_face", 0.0)):
        with pytest.raises(NerfpipeError, match=name.replace("_", "-")):
            RenderedViews(**{name: value})


def test_tsdf_renders_smaller_views_rather_than_too_few(monkeypatch):
    """A frame takes 1 s on the test clock; 3 s fit 3 views: 2 x min_views = 6 views are rendered at
    sqrt(3/6) of the size instead."""
    import itertools
    import time

    from nerfpipe.mesh.trained import tsdf_frames

    clock = itertools.count()
    monkeypatch.setattr(time, "perf_counter", lambda: float(next(clock)))
    cams, frame = tsdf_frames(SphereModel(), sphere_scene().split_cameras("train"), 12, 32, 4096, "cpu", seconds=3.0, min_views=3)
    assert len(cams) == 6 and int(cams.width[0]) == round(32 * 0.5**0.5)
    assert frame(0)[0].shape == (int(cams.height[0]), int(cams.width[0]))
    # 1 s fits one view: min_views = 3 are rendered at sqrt(1/3) of the size (before: 3 at full size, 3 s)
    cams, frame = tsdf_frames(SphereModel(), sphere_scene().split_cameras("train"), 12, 32, 4096, "cpu", seconds=1.0, min_views=3)
    assert len(cams) == 3 and int(cams.width[0]) == round(32 * (1 / 3) ** 0.5)


class FoggySphereModel(SphereModel):
    """The sphere behind fog: the expected depth is pulled to the front, the stop depth stays on the sphere."""

    def get_outputs(self, rays, background):
        out = super().get_outputs(rays, background)
        stop = torch.where(out.acc > 0, out.depth, torch.full_like(out.depth, float("nan")))
        return RenderOutputs(rgb=out.rgb, depth=0.8 * out.depth, acc=out.acc, stop_depth=stop)


def test_tsdf_fuses_where_rays_stop_not_the_fog_pulled_mean():
    from nerfpipe.mesh.pipeline import MeshConfig
    from nerfpipe.mesh.trained import RenderedViews, mesh_model

    cfg = MeshConfig(resolution=48, remove_unseen=False, colors=False, min_component=0.0, max_gap=0.0)
    out = mesh_model(cfg, FoggySphereModel(), sphere_scene(), RenderedViews(tsdf_views=12, tsdf_size=48))
    radius = np.linalg.norm(out.full.vertices, axis=1)
    assert out.figures["method"] == "tsdf" and abs(np.median(radius) - RADIUS) < 0.02  # the mean depth would put it at ~0.3 or less
    assert out.figures["tsdf_views"] == 12 and out.figures["seconds_tsdf_renders"] > 0


def test_eval_mesh_counts_the_objects_points_above_its_support(scene_path, tmp_path, capsys):
    """colmap_mouse (photographed from around, on a table): eval-mesh counts the points inside the mesh's bounds that lie
    above the plane the sparse points give (``above_support``), as the mesh stage does; the table's are not the object's."""
    import trimesh

    from nerfpipe.data_adapters import load
    from nerfpipe.training.trainer import above_support

    data = scene_path("colmap_mouse")
    scene = load(data)
    xyz = scene.world_from_input.inverse().apply_points(scene.points.xyz.double()).numpy()
    spread = np.linalg.norm(xyz - np.median(xyz, 0), axis=1)
    hull = trimesh.convex.convex_hull(xyz[spread < np.quantile(spread, 0.9)])
    write_ply(TriangleMesh(hull.vertices, hull.faces), tmp_path / "hull.ply")
    assert main(["eval-mesh", str(tmp_path / "hull.ply"), str(data), "--json", "--samples", "5000"]) == 0
    r = json.loads(capsys.readouterr().out)
    above = above_support(scene)
    tau = r["points_threshold"]
    near = np.all((xyz >= hull.bounds[0] - tau) & (xyz <= hull.bounds[1] + tau), axis=1)
    assert "above the support plane" in r["points_object_rule"]
    assert r["points_used"] == int((near & above).sum()) and 0 < r["points_used"] < int(near.sum())
