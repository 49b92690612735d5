"""The automatic level from rendered depth (agreement rule): known surfaces, fast paths vs references, bad input."""

import numpy as np
import pytest
import torch

from nerfpipe.mesh.extract import auto_level, mesh_volume, sample_volume
from nerfpipe.mesh.level import _agreement_score_reference, agreement_score, choose_level, densities_at
from nerfpipe.mesh.pipeline import MeshConfig, build_meshes
from nerfpipe.util.errors import NerfpipeError

BOX = torch.tensor([[-1.0] * 3, [1.0] * 3])
R = 0.6
RES = 65  # odd: every 2nd sample is the grid of resolution 33 exactly


def sphere_points(n: int = 2000, radius: float = R, seed: int = 0) -> torch.Tensor:
    dirs = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed))
    return torch.nn.functional.normalize(dirs, dim=-1) * radius


def soft_sphere(p: torch.Tensor) -> torch.Tensor:
    """A solid blob, density 100 · sigmoid((R - r) / 0.02): 50 on the sphere."""
    return 100.0 * torch.sigmoid((R - p.norm(dim=-1)) / 0.02)


def shell(p: torch.Tensor, width: float = 0.02) -> torch.Tensor:
    """A thin shell (Gaussian across r = R, under a voxel wide) whose peak varies 40x from bottom to top,
    as a trained grid field carries a surface; no single density quantile fits everywhere."""
    r = p.norm(dim=-1)
    peak = 50.0 * 40.0 ** (0.5 + 0.5 * p[:, 2] / r.clamp(min=1e-6))
    return peak * torch.exp(-(((r - R) / width) ** 2))


def rendered_points(field, dirs: torch.Tensor, n: int = 1024) -> torch.Tensor:
    """Where radial rays from r = 1 towards the centre end: ``depth / acc`` of a quadrature of the volume integral."""
    t = torch.linspace(0, 1, n + 1)
    mid, dt = 0.5 * (t[1:] + t[:-1]), float(t[1] - t[0])
    sigma = field((dirs[:, None, :] * (1 - mid)[None, :, None]).reshape(-1, 3)).reshape(len(dirs), n)
    alpha = 1 - torch.exp(-sigma * dt)
    weights = alpha * torch.cumprod(torch.cat([torch.ones(len(dirs), 1), 1 - alpha[:, :-1]], 1), 1)
    depth = (weights * mid).sum(1) / weights.sum(1)
    return dirs * (1 - depth)[:, None]


def test_blob_surface_lies_on_the_points_within_a_voxel():
    volume = sample_volume(soft_sphere, BOX, RES)
    choice = choose_level(volume, sphere_points())
    radii = np.linalg.norm(mesh_volume(volume, choice.level).mesh.vertices, axis=1)
    assert np.abs(radii - R).max() < 0.25 * volume.grid.spacing
    assert choice.level == pytest.approx(50.0, rel=0.1)  # the density on the blob's surface
    assert choice.candidates == sorted(choice.candidates) and len(choice.scores) == len(choice.candidates)
    assert choice.scores[choice.candidates.index(choice.level)] == min(choice.scores)


def test_shell_level_is_near_the_best_of_a_dense_full_resolution_scan():
    """The fast search (coarse grid, few candidates) against the slow obvious one (every level, full grid)."""
    from nerfpipe.mesh.metrics import point_fraction

    volume = sample_volume(shell, BOX, RES)
    h = volume.grid.spacing
    points = rendered_points(shell, sphere_points(1000) / R)
    pts, clamp = points.double().numpy(), 3 * h
    choice = choose_level(volume, points)
    dense = min(agreement_score(volume, lv, pts, clamp) for lv in np.geomspace(1.0, 2000.0, 40))
    assert agreement_score(volume, choice.level, pts, clamp) < dense + 0.25 * h
    mesh = mesh_volume(volume, choice.level).mesh
    assert point_fraction(pts, mesh, h)["fraction_within"] == 1.0  # no hole where the shell is faint
    radii = np.linalg.norm(mesh.vertices, axis=1)
    # the outer side, near the shell's centre: no single level traces a shell whose peak varies 40x closer
    # than width * sqrt(ln 40) ~ 1.2 h on its bright side
    assert np.abs(radii[radii > R] - R).mean() < 1.5 * h
    coarse = volume.downsampled(2)
    assert auto_level(coarse.grid.spacing) in choice.candidates
    median = float(torch.quantile(shell(points), 0.5))
    assert min(choice.scores) < agreement_score(coarse, median, pts, choice.clamp)  # the old rule at its median


def test_downsampled_volume_is_the_coarser_grid():
    fine = sample_volume(shell, BOX, RES).downsampled(2)
    coarse = sample_volume(shell, BOX, (RES + 1) // 2)
    assert fine.grid.shape == coarse.grid.shape and fine.grid.spacing == pytest.approx(coarse.grid.spacing)
    np.testing.assert_allclose(fine.values.numpy(), coarse.values.numpy(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("level", [5.0, 50.0, 90.0])
def test_agreement_score_matches_the_slow_reference(level):
    volume = sample_volume(soft_sphere, BOX, 33)
    points = torch.cat([sphere_points(120), sphere_points(40, 0.3, 1), sphere_points(40, 0.9, 2)]).double().numpy()
    clamp = 3 * volume.grid.spacing
    fast = agreement_score(volume, level, points, clamp)
    assert fast == pytest.approx(_agreement_score_reference(volume, level, points, clamp), rel=1e-4, abs=1e-6)
    assert 0 < fast < clamp
    assert agreement_score(volume, 1e6, points, clamp) == clamp  # no surface at that level: every point clamped


def test_densities_at_interpolates_the_volume():
    linear = lambda p: 3.0 + p @ torch.tensor([1.0, -2.0, 0.5])  # noqa: E731  (trilinear is exact)
    volume = sample_volume(linear, BOX, 17)
    pts = torch.rand(200, 3, generator=torch.Generator().manual_seed(3)) * 1.8 - 0.9
    torch.testing.assert_close(densities_at(volume, pts), linear(pts), atol=1e-5, rtol=1e-5)
    assert float(densities_at(volume, torch.tensor([[5.0, 0.0, 0.0]]))[0]) == 0.0  # outside the box


@pytest.mark.parametrize(
    "field, points, message",
    [
        (soft_sphere, torch.zeros(0, 3), "no opaque"),
        (lambda p: torch.zeros(len(p)), sphere_points(50), "empty"),
        (lambda p: torch.full((len(p),), float("nan")), sphere_points(50), "NaN"),
        (lambda p: 100.0 * (p[:, 0] > 0.5).float(), sphere_points(50, 0.2), "zero at every"),
    ],
)
def test_bad_input_fails_with_a_clear_message(field, points, message):
    with pytest.raises(NerfpipeError, match=message):
        choose_level(sample_volume(field, BOX, 17), points)


def test_pipeline_records_the_candidates_and_needs_points():
    cfg = MeshConfig(method="mc", resolution=RES, remove_unseen=False, level_from="agreement")
    out = build_meshes(cfg, BOX, density_fn=soft_sphere, surface_points=sphere_points(500))
    f = out.figures
    assert f["level_rule"] == "agreement" and f["level"] == pytest.approx(50.0, rel=0.1)
    assert min(c["score"] for c in f["level_candidates"]) == f["level_score"]
    assert any(c["level"] == f["level"] for c in f["level_candidates"])
    with pytest.raises(NerfpipeError, match="needs rendered surface points"):
        build_meshes(cfg, BOX, density_fn=soft_sphere)
    assert build_meshes(MeshConfig(method="mc", resolution=33, level_from="opacity", remove_unseen=False), BOX, density_fn=soft_sphere).figures["level_rule"] == "opacity"


def test_median_depth_points_are_where_rays_become_half_opaque():
    """A slab of constant density s beyond x = 0.2: rays along +x are half opaque at x = 0.2 + ln 2 / s."""
    import math

    from nerfpipe.mesh.level import median_depth_points

    s = 10.0
    volume = sample_volume(lambda p: s * (p[:, 0] > 0.2).float(), BOX, 65)
    yz = torch.rand(50, 2, generator=torch.Generator().manual_seed(4)) - 0.5
    origins = torch.cat([torch.full((50, 1), -0.9), yz], 1)
    ends = torch.cat([torch.full((50, 1), 0.6), yz], 1)  # expected depth of an infinite slab: 0.2 + 1 / s = 0.3
    pts = median_depth_points(volume, origins, ends)
    assert len(pts) == 50
    torch.testing.assert_close(pts[:, 1:], yz)
    assert (pts[:, 0] - (0.2 + math.log(2) / s)).abs().max() < volume.grid.spacing
    faint = median_depth_points(volume, origins, torch.cat([torch.full((50, 1), 0.21), yz], 1), beyond=1.0)
    assert len(faint) == 0  # never half opaque before the end: dropped


def test_default_level_is_five_percent_of_a_voxel_opaque():
    import math

    out = build_meshes(MeshConfig(method="mc", resolution=33, remove_unseen=False), BOX, density_fn=soft_sphere)
    f = out.figures
    assert f["level_rule"] == "opacity" and f["level_opacity"] == 0.05
    assert f["level"] == pytest.approx(-math.log(0.95) / f["voxel_size"])
    assert 1.0 - math.exp(-f["level"] * f["voxel_size"]) == pytest.approx(0.05)
