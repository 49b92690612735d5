"""Both extractors on the synthetic composite scene (known geometry): F-score at 1% >= 0.95.

Marching cubes runs on an oracle density built from the ground-truth mesh's signed distance
(a stand-in for a trained field); TSDF fuses depth maps ray-cast from the mesh.
"""

import dataclasses

import numpy as np
import pytest
import torch

from nerfpipe.data import synthetic
from nerfpipe.data.rays import camera_rays
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.extract import Grid, auto_level, extract_mesh
from nerfpipe.mesh.metrics import compare_meshes
from nerfpipe.mesh.tsdf import tsdf_fuse
from nerfpipe.util.errors import NerfpipeError

BOX = torch.tensor([[-1.3] * 3, [1.3] * 3])


@pytest.fixture(scope="module")
def scene():
    gt = synthetic.composite_scene()
    return gt, synthetic.raycaster(gt), TriangleMesh(gt.vertices, gt.faces)


def signed_distance(raycaster, p: torch.Tensor) -> torch.Tensor:
    import open3d as o3d

    return torch.from_numpy(raycaster.compute_signed_distance(o3d.core.Tensor(p.numpy().astype(np.float32))).numpy())


def test_marching_cubes_on_an_oracle_density(scene):
    gt, raycaster, gt_mesh = scene
    grid = Grid.over_box(BOX, 96)
    level = auto_level(grid.spacing)
    density = lambda p: 2 * level * torch.sigmoid(-signed_distance(raycaster, p) / (0.5 * grid.spacing))  # noqa: E731
    coarse = Grid.over_box(BOX, 24)
    coarse_sdf = signed_distance(raycaster, coarse.points(0, coarse.shape[0]).reshape(-1, 3)).reshape(coarse.shape)

    def occupancy(p):  # nearest coarse sample is inside or near the surface (sdf is 1-Lipschitz)
        ijk = ((p.double() - torch.from_numpy(coarse.origin)) / coarse.spacing).round().long().clamp(0, coarse.shape[0] - 1)
        return coarse_sdf[ijk[:, 0], ijk[:, 1], ijk[:, 2]] < 1.5 * coarse.spacing

    r = extract_mesh(density, BOX, resolution=96, occupancy_fn=occupancy)
    assert r.level == pytest.approx(level) and r.evaluated_fraction < 0.5
    m = compare_meshes(r.mesh, gt_mesh, num_samples=50_000)
    assert m.fscore >= 0.95 and m.chamfer_l1 < 0.5 * grid.spacing
    assert r.mesh.to_trimesh().is_watertight  # (the parts, 0.026 apart, merge at this resolution)


def _frames(scene, cams):
    gt, raycaster, _ = scene
    cache = {}

    def frame(i):
        if i not in cache:
            v = synthetic.render_view(raycaster, gt, cams, i)
            cache[i] = (v.depth * camera_rays(cams, i).z_scale.numpy(), np.round(v.rgb * 255).astype(np.uint8))
        return cache[i]

    return frame


def test_tsdf_of_ray_cast_depth_maps(scene):
    cfg = synthetic.SynthConfig(views=16, width=80, height=80, min_elevation_deg=-60.0)
    cams = synthetic.orbit_cameras(cfg)
    frame = _frames(scene, cams)
    mesh = tsdf_fuse(cams, frame, BOX, voxel_size=0.02)
    m = compare_meshes(mesh, scene[2], num_samples=50_000)
    assert m.fscore >= 0.95
    assert mesh.vertex_colors is not None and mesh.vertex_colors.std() > 10
    wide = tsdf_fuse(cams, frame, BOX, voxel_size=0.02, trunc_voxels=8.0)  # MeshConfig.truncation: consistent depths, the same surface
    assert wide.num_faces != mesh.num_faces and compare_meshes(wide, scene[2], num_samples=50_000).fscore >= 0.95
    # the pixel convention: K passes through unchanged; half a pixel off is measurably worse
    shifted = dataclasses.replace(cams, cx=cams.cx + 0.5, cy=cams.cy + 0.5)
    worse = compare_meshes(tsdf_fuse(shifted, frame, BOX, voxel_size=0.02), scene[2], num_samples=50_000)
    assert m.accuracy < 0.8 * worse.accuracy


def test_tsdf_caps_its_faces_by_fusing_the_same_frames_again_with_coarser_voxels(scene):
    """``max_faces`` (a time budget's cap on what follows fusion): a surface of more faces is fused again, each frame
    rendered once, with voxels as much larger as bring the faces near the cap, no larger than ``max_voxel_size``; the
    surface stays on the scene."""
    cfg = synthetic.SynthConfig(views=12, width=64, height=64, min_elevation_deg=-60.0)
    cams = synthetic.orbit_cameras(cfg)
    frame, calls = _frames(scene, cams), []
    counted = lambda i: (calls.append(i), frame(i))[1]  # noqa: E731
    full = tsdf_fuse(cams, frame, BOX, voxel_size=0.015)
    capped = tsdf_fuse(cams, counted, BOX, voxel_size=0.015, max_faces=full.num_faces // 3)
    assert sorted(calls) == list(range(len(cams)))
    assert capped.info["voxel_size"] == pytest.approx(0.015 * (1.05 * full.num_faces / (full.num_faces // 3)) ** 0.5)
    assert 0.2 * full.num_faces < capped.num_faces <= 1.1 * (full.num_faces // 3)  # about the cap: faces ~ 1 / voxel²
    assert compare_meshes(capped, scene[2], num_samples=50_000).fscore >= 0.9
    limited = tsdf_fuse(cams, frame, BOX, voxel_size=0.015, max_faces=10, max_voxel_size=0.02)
    assert limited.info["voxel_size"] == 0.02 and limited.num_faces > full.num_faces // 3
    assert tsdf_fuse(cams, frame, BOX, voxel_size=0.015, max_faces=full.num_faces).num_faces == full.num_faces


def test_tsdf_keeps_its_first_surface_where_the_coarser_fusion_finds_none(scene, monkeypatch):
    """A surface too thin for the coarser voxels (the second fusion raises): the first fusion's mesh is returned."""
    from nerfpipe.mesh import tsdf

    cams = synthetic.orbit_cameras(synthetic.SynthConfig(views=6, width=48, height=48, min_elevation_deg=-60.0))
    frame, fuse = _frames(scene, cams), tsdf._fuse

    def finer_only(cameras, frames, aabb, voxel_size, *args):
        if voxel_size > 0.03:
            raise NerfpipeError("TSDF fusion produced no surface inside the scene box")
        return fuse(cameras, frames, aabb, voxel_size, *args)

    monkeypatch.setattr(tsdf, "_fuse", finer_only)
    mesh = tsdf_fuse(cams, frame, BOX, voxel_size=0.03, max_faces=10)
    assert mesh.info["voxel_size"] == 0.03 and mesh.num_faces > 10


def test_tsdf_rejects_distorted_cameras_and_empty_depth(scene):
    cams = synthetic.orbit_cameras(synthetic.SynthConfig(views=4, width=32, height=32))
    distorted = dataclasses.replace(cams, distortion=torch.ones_like(cams.distortion))
    with pytest.raises(NerfpipeError, match="pinhole"):
        tsdf_fuse(distorted, lambda i: (np.ones((32, 32)), None), BOX, 0.05)
    with pytest.raises(NerfpipeError, match="no surface"):
        tsdf_fuse(cams, lambda i: (np.zeros((32, 32)), None), BOX, 0.05)
