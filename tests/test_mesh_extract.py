"""Marching-cubes extraction: analytic spheres and blobs, occupancy skipping, levels, bad input."""

import math

import numpy as np
import pytest
import torch

from nerfpipe.mesh.extract import Grid, auto_level, extract_mesh
from nerfpipe.util.errors import NerfpipeError

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
R = 0.6


def soft_sphere(p: torch.Tensor, radius: float = R, width: float = 0.02, peak: float = 100.0) -> torch.Tensor:
    """Density ``peak * sigmoid((r - |p|) / width)``: exactly ``peak / 2`` on the sphere."""
    return peak * torch.sigmoid((radius - p.norm(dim=-1)) / width)


def test_sphere_is_watertight_with_the_right_volume():
    r = extract_mesh(soft_sphere, BOX, resolution=96, level=50.0)
    tm = r.mesh.to_trimesh()
    assert tm.is_watertight and tm.is_winding_consistent and tm.body_count == 1
    assert tm.volume == pytest.approx(4 / 3 * math.pi * R**3, rel=0.01)  # positive: faces wound outwards
    radii = np.linalg.norm(r.mesh.vertices, axis=1)
    assert np.abs(radii - R).max() < 0.25 * r.voxel_size
    cos = np.sum(r.vertex_normals * r.mesh.vertices, axis=1) / radii  # normals point outwards
    assert cos.min() > 0.95


def test_auto_level_is_half_opacity_per_voxel():
    h = 0.013
    level = auto_level(h)
    assert 1 - math.exp(-level * h) == pytest.approx(0.5)
    assert 1 - math.exp(-auto_level(h, 0.9) * h) == pytest.approx(0.9)
    with pytest.raises(NerfpipeError, match="opacity"):
        auto_level(h, 1.0)


def test_auto_level_on_a_gaussian_blob_gives_the_expected_radius():
    peak, s = 400.0, 0.3
    blob = lambda p: peak * torch.exp(-(p**2).sum(-1) / (2 * s**2))  # noqa: E731
    r = extract_mesh(blob, BOX, resolution=80)
    assert r.level == pytest.approx(math.log(2) / r.voxel_size)
    expected = s * math.sqrt(2 * math.log(peak / r.level))  # where peak * exp(-r²/2s²) = level
    radii = np.linalg.norm(r.mesh.vertices, axis=1)
    assert radii.mean() == pytest.approx(expected, abs=0.1 * r.voxel_size)


def test_grid_sampling_matches_a_dense_reference_and_is_chunk_invariant():
    calls = []

    def counted(p):
        calls.append(len(p))
        return soft_sphere(p)

    a = extract_mesh(counted, BOX, resolution=40, level=50.0, chunk=977)
    assert max(calls) <= 977 and sum(calls) == 40**3
    b = extract_mesh(soft_sphere, BOX, resolution=40, level=50.0)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    # reference: the whole grid at once, sampled with linspace
    lin = torch.linspace(-1, 1, 40)
    dense = soft_sphere(torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1)).numpy()
    from skimage.measure import marching_cubes

    v, _, _, _ = marching_cubes(dense, 50.0, spacing=(2 / 39,) * 3)
    np.testing.assert_allclose(np.sort(a.mesh.vertices[:, 0]), np.sort(v[:, 0] - 1.0), atol=1e-5)


def test_occupancy_skips_empty_space_without_changing_the_mesh():
    evaluated = []

    def counted(p):
        evaluated.append(len(p))
        return soft_sphere(p)

    occupancy = lambda p: p.norm(dim=-1) < R + 0.1  # noqa: E731
    full = extract_mesh(soft_sphere, BOX, resolution=48, level=50.0)
    skip = extract_mesh(counted, BOX, resolution=48, level=50.0, occupancy_fn=occupancy)
    assert skip.evaluated_fraction < 0.35 and sum(evaluated) < 0.35 * 48**3
    np.testing.assert_array_equal(full.mesh.vertices, skip.mesh.vertices)
    np.testing.assert_array_equal(full.mesh.faces, skip.mesh.faces)


def test_non_cubic_box_keeps_isotropic_spacing():
    g = Grid.over_box(torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 0.5]]), 65)
    assert g.spacing == pytest.approx(2 / 64) and g.shape == (65, 33, 17)


@pytest.mark.parametrize(
    "density, level, message",
    [
        (lambda p: torch.zeros(len(p)), None, "empty"),
        (soft_sphere, 1e4, "outside the density range"),
        (soft_sphere, -1.0, "outside the density range"),
        (lambda p: torch.full((len(p),), float("nan")), 1.0, "NaN"),
        (lambda p: torch.ones(len(p) + 1), 1.0, "returned"),
    ],
)
def test_bad_fields_fail_with_a_clear_message(density, level, message):
    with pytest.raises(NerfpipeError, match=message):
        extract_mesh(density, BOX, resolution=16, level=level)


def test_bad_box_and_resolution():
    with pytest.raises(NerfpipeError, match="no volume"):
        extract_mesh(soft_sphere, torch.tensor([[0.0, 0, 0], [1.0, 0, 1]]), resolution=16)
    with pytest.raises(NerfpipeError, match="resolution"):
        extract_mesh(soft_sphere, BOX, resolution=4)


def test_level_from_surface_points_puts_the_surface_on_them():
    from nerfpipe.mesh.extract import level_from_surface_points

    dirs = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    jitter = 0.004 * torch.randn(500, generator=torch.Generator().manual_seed(1))
    level = level_from_surface_points(soft_sphere, dirs * (R + jitter)[:, None], quantile=0.5)
    assert level == pytest.approx(50.0, rel=0.1)  # soft_sphere is peak / 2 = 50 on the sphere
    r = extract_mesh(soft_sphere, BOX, resolution=64, level=level)
    assert np.linalg.norm(r.mesh.vertices, axis=1).mean() == pytest.approx(R, abs=0.003)
    with pytest.raises(NerfpipeError, match="no opaque"):
        level_from_surface_points(soft_sphere, torch.zeros(0, 3))


@pytest.mark.parametrize("quantile", [0.05, 0.1, 0.5])
def test_level_quantile_encloses_that_share_of_the_surface_points(quantile):
    from nerfpipe.mesh.extract import level_from_surface_points

    gen = torch.Generator().manual_seed(2)
    pts = torch.nn.functional.normalize(torch.randn(2000, 3, generator=gen), dim=-1) * (R + 0.02 * torch.randn(2000, 1, generator=gen))
    level = level_from_surface_points(soft_sphere, pts, quantile=quantile)
    inside = (soft_sphere(pts) >= level).float().mean()
    assert float(inside) == pytest.approx(1 - quantile, abs=0.01)


def test_canonical_order_makes_shuffled_meshes_equal_and_keeps_the_surface():
    import trimesh

    from nerfpipe.mesh.container import TriangleMesh

    s = trimesh.creation.icosphere(3)
    mesh = TriangleMesh(s.vertices, s.faces, np.arange(len(s.vertices) * 3).reshape(-1, 3) % 256)
    rng = np.random.default_rng(0)
    perm = rng.permutation(mesh.num_vertices)  # another order of the same surface, as another thread schedule gives
    inverse = np.argsort(perm)
    faces = np.roll(inverse[mesh.faces], 1, axis=1)[rng.permutation(mesh.num_faces)]
    shuffled = TriangleMesh(mesh.vertices[perm], faces, mesh.vertex_colors[perm])
    a, b = mesh.canonical(), shuffled.canonical()
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces) and np.array_equal(a.vertex_colors, b.vertex_colors)
    tri = lambda m: sorted(tuple(sorted(map(tuple, t))) for t in m.vertices[m.faces])  # noqa: E731
    assert tri(a) == tri(mesh)  # the same triangles
    np.testing.assert_allclose(np.sort(a.face_normals(), axis=0), np.sort(mesh.face_normals(), axis=0), atol=1e-12)  # orientation kept
