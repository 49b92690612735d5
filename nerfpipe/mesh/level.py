"""The iso-level whose marching-cubes surface best agrees with rendered depth: :func:`choose_level`.

A density field has no natural iso-value. The renderer, though, says where the surface is: a
training view's ray ends on it. The points are taken at the rays' median depth in the sampled
volume (where the ray becomes half opaque, :func:`median_depth_points`), not the expected depth
``depth / acc``, which lies inside soft, foggy surfaces. So the level is chosen by what it is for:

    level* = argmin over candidate levels L of  ½ (mean_i min(d(p_i, S_L), c) + mean_{x ∈ S_L} min(d(x, P), c))

a clamped Chamfer distance between the rendered surface points ``P = {p_i}`` and the marching-cubes
surface ``S_L`` of the sampled density at ``L`` (the second mean is area-weighted over triangles).
A level too low wraps the points in a fattened solid; a level too high shrinks the surface to the
density peaks and leaves holes (first term) or fragments where no ray ends (second term). The clamp
``c`` (a few voxels) keeps background points, unseen parts and holes from dominating. Trained grid
fields carry the surface as a thin shell whose peak density varies over the object, which a quantile
of densities or the opacity level ``ln 2 / h`` misplace; the score measures the thing wanted.

Limits: in a soft (foggy, under-trained) field even the median-depth surface lies a voxel or so
inside the fog's front; a quantile level can then be as good.

Cost: the density volume is sampled once (:func:`nerfpipe.mesh.extract.sample_volume`); every
candidate is meshed on a copy ``downsample`` times coarser; then the full grid is meshed once at
the chosen level. Candidates are log-spaced between quantiles of the density at the points, plus
the opacity level, then refined between the best one's neighbours.

Glossary:
    points     rendered surface points, world frame ``[N, 3]``
    coarse     the volume with every ``downsample``-th sample per axis
    score      clamped Chamfer distance between the points and a candidate's surface, world units
"""

from dataclasses import dataclass, field

import numpy as np
import torch

from nerfpipe.functional.volrend import render_weights
from nerfpipe.mesh.extract import Volume, _marching_cubes, auto_level
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.util.typing import Float, Tensor

MAX_POINTS = 20_000
"""Surface points used for scoring (an even subsample of more)."""


@dataclass
class LevelChoice:
    """The chosen level and why (recorded in mesh.json)."""

    level: float
    """The level with the best (lowest) score."""
    candidates: "list[float]" = field(default_factory=list)
    """Every level tried, ascending."""
    scores: "list[float]" = field(default_factory=list)
    """Score of each candidate (clamped Chamfer distance, world units; ``clamp`` when no surface)."""
    clamp: float = 0.0
    """Distance at which a point's contribution is clamped."""
    voxel_size: float = 0.0
    """Spacing of the coarse grid the candidates were meshed on."""
    num_points: int = 0
    """Surface points scored."""

    def to_dict(self) -> dict:
        return {"level_rule": "agreement", "level": self.level, "level_score": min(self.scores),
                "level_candidates": [{"level": lv, "score": sc} for lv, sc in zip(self.candidates, self.scores)],
                "level_clamp": self.clamp, "level_voxel_size": self.voxel_size, "level_points": self.num_points}  # fmt: skip


def densities_at(volume: Volume, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points"]:
    """Trilinear interpolation of the sampled densities at world points (0 outside the box)."""
    g = volume.grid
    shape = torch.tensor(g.shape, dtype=torch.float64)
    origin = torch.from_numpy(g.origin).float()
    scale = 2.0 / (g.spacing * (shape.float() - 1))  # align_corners=True: -1 and 1 are the first and last samples
    coords = ((points.float() - origin) * scale - 1.0)[:, [2, 1, 0]][None, :, None, None]  # grid_sample wants (z, y, x)
    out = torch.nn.functional.grid_sample(volume.values[None, None], coords, mode="bilinear", padding_mode="zeros", align_corners=True)
    return out.reshape(-1)


def median_depth_points(
    volume: Volume, origins: Float[Tensor, "num_points 3"], points: Float[Tensor, "num_points 3"], beyond: float = 1.3, chunk: int = 2048,
    opacity: float = 0.5,
) -> Float[Tensor, "num_kept 3"]:
    """Where the rays ``origins -> points`` become half opaque in the sampled volume (median depth).

    Marches each ray in half-voxel steps up to ``beyond`` times the distance to its point, with
    the volume's trilinear density; rays that never reach opacity 0.5 are dropped. Expected depth
    (``depth / acc``, the given points) lies inside a soft surface; the median depth lies at its front.
    """
    step = 0.5 * volume.grid.spacing
    out = []
    for o, p in zip(origins.float().split(chunk), points.float().split(chunk)):
        length = (p - o).norm(dim=-1, keepdim=True)
        d = (p - o) / length.clamp(min=1e-12)
        end = beyond * length
        start = _box_entry(volume, o, d).clamp(max=end)  # no density before the ray enters the volume
        k = torch.arange(int(float((end - start).max()) / step) + 2, dtype=o.dtype)
        t = start + k[None, :] * step  # distance along each ray [R, S]
        sigma = densities_at(volume, (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)).reshape(t.shape)
        weights, trans = render_weights(sigma, (t <= end) * step)
        accumulated = 1 - (trans - weights)  # opacity after each sample: 1 - T_i (1 - alpha_i)
        hit = accumulated >= opacity
        first = hit.float().argmax(dim=1, keepdim=True)
        out.append((o + t.gather(1, first) * d)[hit[:, -1]])
    return torch.cat(out) if out else points[:0]


def _box_entry(volume: Volume, origins: Float[Tensor, "R 3"], directions: Float[Tensor, "R 3"]) -> Float[Tensor, "R 1"]:
    """Distance along each ray to where it enters the volume's box (0 from inside; beyond it when it misses)."""
    g = volume.grid
    lo = torch.from_numpy(g.origin).float()
    hi = lo + g.spacing * (torch.tensor(g.shape, dtype=torch.float32) - 1)
    safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t_lo, t_hi = (lo - origins) / safe, (hi - origins) / safe
    return torch.minimum(t_lo, t_hi).amax(dim=-1, keepdim=True).clamp(min=0.0)


def agreement_score(volume: Volume, level: float, points: Float[np.ndarray, "num_points 3"], clamp: float, tree=None) -> float:
    """Clamped Chamfer distance between ``points`` and the surface at ``level``: the mean of

    * the mean over points of ``min(distance to the surface, clamp)`` (exact point-triangle distance;
      large where the surface has holes or runs off the points), and
    * the area-weighted mean over triangles of ``min(distance from the centroid to the nearest point, clamp)``
      (large where the surface has pieces no rendered ray ends at: fog, fragments).

    ``tree``: a ``scipy.spatial.cKDTree`` of ``points`` (built when None). ``clamp`` when there is no surface.
    """
    values = volume.values
    if not volume.min < level < volume.max:
        return clamp
    verts, faces, _ = _marching_cubes(values.numpy(), level, volume.grid)
    if len(faces) == 0:
        return clamp
    return 0.5 * (_points_to_surface(verts, faces, points, clamp) + _surface_to_points(verts, faces, points, clamp, tree))


def _points_to_surface(verts: np.ndarray, faces: np.ndarray, points: np.ndarray, clamp: float) -> float:
    o3d = require("open3d", "mesh")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    d = scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()
    return float(np.minimum(d, clamp).mean())


def _surface_to_points(verts: np.ndarray, faces: np.ndarray, points: np.ndarray, clamp: float, tree=None) -> float:
    from scipy.spatial import cKDTree

    tree = cKDTree(points) if tree is None else tree
    tri = verts[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d, _ = tree.query(tri.mean(1), distance_upper_bound=clamp)
    return float(np.sum(area * np.minimum(d, clamp)) / max(float(area.sum()), 1e-30))


def _even_subsample(points: Tensor, count: int) -> Tensor:
    if len(points) <= count:
        return points
    return points[torch.linspace(0, len(points) - 1, count).round().long()]


def initial_candidates(volume: Volume, point_density: Tensor, count: int) -> "list[float]":
    """``count`` log-spaced levels over four decades up to twice the 99% quantile of the density at the points, plus ln 2 / h."""
    positive = point_density[point_density > 0]
    if len(positive) == 0:
        raise NerfpipeError("the density is zero at every rendered surface point: cannot choose a level from depth (is the model trained?)")
    hi = 2.0 * float(torch.quantile(positive.double(), 0.99))
    levels = set(np.geomspace(hi * 1e-4, hi, count).tolist())
    levels.add(auto_level(volume.grid.spacing))
    return sorted(lv for lv in levels if volume.min < lv < volume.max)


def _refined(candidates: "list[float]", scores: "list[float]", count: int) -> "list[float]":
    """``count`` log-spaced levels on each side of the best candidate, up to its neighbours."""
    best = int(np.argmin(scores))
    out = []
    for nb in (best - 1, best + 1):
        if 0 <= nb < len(candidates):
            out += np.geomspace(candidates[best], candidates[nb], count + 2)[1:-1].tolist()
    return out


def choose_level(
    volume: Volume,
    points: Float[Tensor, "num_points 3"],
    origins: "Float[Tensor, 'num_points 3'] | None" = None,
    downsample: int = 2,
    clamp_voxels: float = 3.0,
    count: int = 14,
    refine: int = 3,
) -> LevelChoice:
    """The level whose surface best agrees with the rendered surface points (see the module doc).

    Args:
        volume: densities sampled once on the full grid.
        points: rendered surface points (world frame), at expected depth.
        origins: the ray origin of each point; when given, the points are moved to the rays'
            median depth in the volume (:func:`median_depth_points`), the front of soft surfaces.
        downsample: candidates are meshed on every ``downsample``-th sample per axis.
        clamp_voxels: clamp distance in voxels of that coarse grid.
        count: initial log-spaced candidates.
        refine: extra candidates on each side of the best initial one.

    Raises:
        NerfpipeError: no points, an empty or non-finite field, or no candidate inside the density range.
    """
    if len(points) == 0:
        raise NerfpipeError("no opaque rendered pixel: cannot choose the level from rendered depth")
    if not bool(torch.isfinite(volume.values).all()):
        raise NerfpipeError("the density field has NaN or infinite values; cannot extract a mesh")
    if float(volume.values.max()) <= 0.0:
        raise NerfpipeError("the density field is empty (zero everywhere in the box): nothing to mesh — is the model trained?")
    points = _even_subsample(points.float().cpu(), MAX_POINTS)
    if origins is not None:
        points = median_depth_points(volume, _even_subsample(origins.float().cpu(), MAX_POINTS), points)
        if len(points) == 0:
            raise NerfpipeError("no rendered ray becomes half opaque in the sampled volume: cannot choose the level from depth")
    coarse = volume.downsampled(downsample)
    clamp = clamp_voxels * coarse.grid.spacing
    candidates = initial_candidates(coarse, densities_at(volume, points), count)
    if not candidates:
        raise NerfpipeError("no candidate level lies inside the density range of the field")
    from scipy.spatial import cKDTree

    pts = points.double().numpy()
    tree = cKDTree(pts)
    scores = [agreement_score(coarse, lv, pts, clamp, tree) for lv in candidates]
    extra = _refined(candidates, scores, refine)
    scores += [agreement_score(coarse, lv, pts, clamp, tree) for lv in extra]
    order = np.argsort(candidates + extra)
    levels, scores = [(candidates + extra)[i] for i in order], [scores[i] for i in order]
    best = int(np.argmin(scores))
    return LevelChoice(levels[best], levels, scores, clamp, coarse.grid.spacing, len(points))


def _agreement_score_reference(volume: Volume, level: float, points: np.ndarray, clamp: float) -> float:
    """Slow obvious reference of :func:`agreement_score`: every point-triangle and centroid-point distance, by brute force."""
    verts, faces, _ = _marching_cubes(volume.values.numpy(), level, volume.grid)
    tri = verts[faces]
    to_surface = np.mean([min(_point_triangles_distance(p, tri), clamp) for p in points])
    area = np.array([0.5 * np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) for t in tri])
    nearest = np.array([np.sqrt(((points - t.mean(0)) ** 2).sum(1)).min() for t in tri])
    return float(0.5 * (to_surface + np.sum(area * np.minimum(nearest, clamp)) / area.sum()))


def _point_triangles_distance(p: np.ndarray, tri: np.ndarray) -> float:
    """Distance from one point to the nearest of triangles ``[T, 3, 3]``: the foot of the perpendicular
    when it falls inside a triangle, else the nearest point of its three edges."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    foot = p - np.sum((p - a) * n, axis=1, keepdims=True) * n
    inside = np.ones(len(tri), bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.sum(np.cross(v - u, foot - u) * n, axis=1) >= 0
    best = np.where(inside, np.linalg.norm(p - foot, axis=1), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        t = np.clip(np.sum((p - u) * (v - u), axis=1) / np.sum((v - u) ** 2, axis=1), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - (u + t[:, None] * (v - u)), axis=1))
    return float(best.min())
