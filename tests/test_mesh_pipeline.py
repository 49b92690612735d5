"""The mesh post-stage over callables: outputs, frames, figures, and bad input leaving no files."""

import json
import math

import numpy as np
import pytest
import torch

from nerfpipe.data.scene import Similarity
from nerfpipe.mesh.pipeline import FILES, MeshConfig, build_meshes, write_meshes
from nerfpipe.util.errors import NerfpipeError

BOX = torch.tensor([[-1.0] * 3, [1.0] * 3])


def blob(p):
    """A sphere (r 0.5) plus a tiny floater at (0.8, 0.8, 0.8)."""
    main = torch.sigmoid((0.5 - p.norm(dim=-1)) / 0.02)
    floater = torch.sigmoid((0.04 - (p - 0.8).norm(dim=-1)) / 0.01)
    return 200.0 * torch.maximum(main, floater)


def rgb(p, d):
    return torch.stack([torch.ones_like(p[:, 0]), 0.5 + 0.5 * torch.tanh(p[:, 2]), torch.zeros_like(p[:, 0])], -1)


def world_from_input() -> Similarity:
    c, s = math.cos(0.3), math.sin(0.3)
    return Similarity(torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]], dtype=torch.float64), torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64), 0.5)


def test_marching_cubes_post_stage_writes_input_frame_meshes(tmp_path):
    import trimesh

    cfg = MeshConfig(method="mc", resolution=64, faces=2000, remove_unseen=False, min_component=0.1, level_from="opacity", level_opacity=0.5)
    out = build_meshes(cfg, BOX, density_fn=blob, rgb_fn=rgb)
    assert out.figures["floater_faces_removed"] > 0 and out.full.to_trimesh().body_count == 1
    assert out.simplified.num_faces <= 2000 and 0 < out.figures["hausdorff_max"] < 0.05
    paths = write_meshes(out, tmp_path, world_from_input(), views=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.json", "mesh.ply", "mesh_simplified.ply"]
    tm = trimesh.load(paths["mesh.ply"], process=False)
    centre_input = world_from_input().inverse().apply_points(torch.zeros(1, 3, dtype=torch.float64))[0].numpy()
    radii = np.linalg.norm(tm.vertices - centre_input, axis=1)
    level = out.figures["level"]
    r_world = 0.5 + 0.02 * math.log(200.0 / level - 1)  # where 200 sigmoid((0.5 - r) / 0.02) = level
    assert radii.mean() == pytest.approx(r_world / 0.5, rel=0.01)  # world_from_input scale 0.5
    assert (tm.visual.vertex_colors[:, 0] == 255).all() and tm.visual.vertex_colors[:, 1].std() > 10
    figures = json.loads(paths["mesh.json"].read_text())
    assert figures["faces_simplified"] <= 2000 and figures["frame"] == "input"


def test_small_mesh_with_default_target_is_copied(tmp_path):
    out = build_meshes(MeshConfig(method="mc", resolution=32, remove_unseen=False, level_from="opacity"), BOX, density_fn=blob)
    assert out.simplified.num_faces == out.full.num_faces and out.figures["hausdorff_max"] == 0.0


@pytest.mark.parametrize(
    "cfg, density, message",
    [
        (MeshConfig(method="mc", resolution=32, level_from="opacity"), lambda p: torch.zeros(len(p)), "empty"),
        (MeshConfig(method="mc", resolution=32, level=1e6), blob, "outside the density range"),
        (MeshConfig(method="mc", resolution=32, faces=10**7, level_from="opacity"), blob, "not below the mesh's"),
    ],
)
def test_bad_input_fails_before_anything_is_written(tmp_path, cfg, density, message):
    with pytest.raises(NerfpipeError, match=message):
        out = build_meshes(cfg, BOX, density_fn=density)
        write_meshes(out, tmp_path / "mesh", world_from_input())
    assert not (tmp_path / "mesh").exists()


def test_files_list_is_what_gets_written(tmp_path):
    out = build_meshes(MeshConfig(method="mc", resolution=32, remove_unseen=False, level_from="opacity"), BOX, density_fn=blob)
    write_meshes(out, tmp_path, Similarity())
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(FILES)


def test_public_names_resolve_and_heavy_libraries_stay_lazy():
    import subprocess
    import sys

    import nerfpipe.mesh as mesh

    assert all(hasattr(mesh, name) for name in mesh.__all__)
    code = "import sys, nerfpipe.mesh; print(sorted(m for m in ('open3d', 'pymeshlab', 'skimage', 'trimesh') if m in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "[]"


def cut_ball(p):
    """A ball (r 0.5) centred 0.2 inside the box's +x side: the side cuts a round hole into its surface."""
    return 200.0 * torch.sigmoid((0.5 - (p - torch.tensor([0.8, 0.0, 0.0])).norm(dim=-1)) / 0.02)


@pytest.mark.parametrize("holes", [0, 300])
def test_holes_up_to_the_limit_are_closed_after_cleaning(holes):
    cfg = MeshConfig(method="mc", resolution=32, remove_unseen=False, level_from="opacity", level_opacity=0.5, close_holes=holes)
    out = build_meshes(cfg, BOX, density_fn=cut_ball)
    assert out.figures["box_side_faces_removed"] > 0  # the cut side went: a hole of about 50 edges
    assert out.full.to_trimesh().is_watertight == (holes > 0)
    assert out.figures.get("hole_faces_added", 0) > 0 if holes else "hole_faces_added" not in out.figures


def test_a_mesh_whose_holes_cannot_be_closed_keeps_them_with_a_warning(monkeypatch):
    import nerfpipe.mesh.pipeline as pipeline

    def refuse(mesh, max_hole_edges):
        raise NerfpipeError("closing holes failed: non-manifold")

    monkeypatch.setattr(pipeline, "close_holes", refuse)
    cfg = MeshConfig(method="mc", resolution=32, remove_unseen=False, level_from="opacity", level_opacity=0.5)
    with pytest.warns(UserWarning, match="keeps its holes"):
        out = build_meshes(cfg, BOX, density_fn=cut_ball)
    assert out.figures["hole_faces_added"] == 0 and not out.full.to_trimesh().is_watertight
