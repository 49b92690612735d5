"""Marching-cubes extraction of a density field: :func:`extract_mesh`.

The field is sampled on a regular grid over the scene box, slab by slab (a chunk of points
at a time), skipping space an occupancy test marks empty; scikit-image's marching cubes then
extracts the iso-surface ``density == level``.

Choosing the level. A density has no natural iso-value, but the renderer gives one a
meaning: a ray crossing a slab of thickness ``h`` with density σ is blocked with probability
``1 - exp(-σ h)``. :func:`auto_level` is the density at which one voxel of the extraction grid
blocks a given fraction of a ray (half by default, ``σ = ln 2 / h``; the mesh pipeline uses 5%,
the front of the soft shells trained fields learn). :func:`level_from_surface_points` takes a low
quantile of the density where rendered rays end, and :func:`nerfpipe.mesh.level.choose_level` the
level whose surface best agrees with rendered depth, meshing one sampled :class:`Volume`
(:func:`sample_volume`) at several levels.
"""

import math
from dataclasses import dataclass
from collections.abc import Callable

import numpy as np
import torch

from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.util.typing import Float, Tensor

DensityFn = Callable[[Tensor], Tensor]
"""``density_fn(points [N, 3]) -> density [N]`` (or ``[N, 1]``), world coordinates."""
OccupancyFn = Callable[[Tensor], Tensor]
"""``occupancy_fn(points [N, 3]) -> bool [N]``: false where space is known to be empty."""


def auto_level(voxel_size: float, opacity: float = 0.5) -> float:
    """The density at which a ray crossing one voxel accumulates ``opacity``.

    Solves ``1 - exp(-σ h) = opacity``: ``σ = -ln(1 - opacity) / h`` (``ln 2 / h`` for 0.5).

    Example:
        >>> round(auto_level(0.01), 3)
        69.315
    """
    if not 0.0 < opacity < 1.0:
        raise NerfpipeError(f"level opacity must be in (0, 1), got {opacity}")
    return -math.log1p(-opacity) / voxel_size


@torch.no_grad()
def level_from_surface_points(
    density_fn: DensityFn, points: Float[Tensor, "num_points 3"], chunk: int = 1 << 18, quantile: float = 0.5
) -> float:
    """The largest level whose solid ``{density >= level}`` holds ``1 - quantile`` of the rendered surface points.

    ``points`` are where rays terminate (``origin + direction * depth / acc`` of rendered
    training views, opaque pixels only). Along a ray the density rises through the surface, so
    the iso-surface at the density found at these points agrees with the rendered depth. With
    ``quantile = 0.5`` (the median) the surface passes through the typical point; a trained grid
    field often carries the surface as a thin shell whose peak density varies a lot, and there a
    low quantile (e.g. 0.1: 90% of the observed surface enclosed) avoids holes where the shell
    is faint.
    """
    if len(points) == 0:
        raise NerfpipeError("no opaque rendered pixel to take the surface level from")
    dens = torch.cat([density_fn(p).reshape(-1).float().cpu() for p in points.split(chunk)])
    level = float(torch.quantile(dens, quantile)) if len(dens) <= 16_000_000 else float(dens.kthvalue(max(1, int(quantile * len(dens)))).values)
    if not level > 0:
        raise NerfpipeError("the density at the rendered surface is zero: cannot choose a level from depth")
    return level


@dataclass
class Grid:
    """A regular grid of sample points with isotropic spacing over a box."""

    origin: Float[np.ndarray, "3"]
    """Position of sample ``(0, 0, 0)``."""
    spacing: float
    """Distance between neighbouring samples (the voxel size h)."""
    shape: "tuple[int, int, int]"
    """Samples per axis (x, y, z)."""

    @classmethod
    def over_box(cls, aabb: Float[Tensor, "2 3"], resolution: int) -> "Grid":
        """``resolution`` samples along the longest side; other sides get the same spacing."""
        if resolution < 8:
            raise NerfpipeError(f"resolution must be at least 8, got {resolution}")
        lo, hi = (aabb.double().cpu().numpy()[i] for i in (0, 1))
        extent = hi - lo
        if not np.all(extent > 0):
            raise NerfpipeError(f"the box has no volume: min {lo.tolist()} max {hi.tolist()}")
        h = float(extent.max()) / (resolution - 1)
        shape = tuple(int(math.ceil(e / h - 1e-6)) + 1 for e in extent)
        return cls(lo, h, shape)

    def axis(self, a: int, start: int = 0, stop: "int | None" = None) -> Float[Tensor, "n"]:
        """Sample coordinates along axis ``a`` (float32)."""
        idx = torch.arange(start, self.shape[a] if stop is None else stop, dtype=torch.float64)
        return (self.origin[a] + self.spacing * idx).float()

    def points(self, x_start: int, x_stop: int, out: "Tensor | None" = None) -> Float[Tensor, "nx ny nz 3"]:
        """Sample positions of the slab ``x_start <= i < x_stop`` (float32, written by broadcasting into ``out``)."""
        _, ny, nz = self.shape
        pts = torch.empty(x_stop - x_start, ny, nz, 3) if out is None else out[: x_stop - x_start]
        pts[..., 0] = self.axis(0, x_start, x_stop)[:, None, None]
        pts[..., 1] = self.axis(1)[None, :, None]
        pts[..., 2] = self.axis(2)[None, None, :]
        return pts


@dataclass
class ExtractResult:
    """What :func:`extract_mesh` returns."""

    mesh: TriangleMesh
    """The iso-surface, in the frame of ``aabb`` (the world frame)."""
    vertex_normals: Float[np.ndarray, "num_verts 3"]
    """Outward unit normals from the density gradient (they point to lower density)."""
    level: float
    """The iso-value used."""
    voxel_size: float
    """Grid spacing h."""
    evaluated_fraction: float
    """Fraction of grid samples where ``density_fn`` was called (the rest was skipped as empty)."""


def _occupied_mask(grid: Grid, occupancy_fn: "OccupancyFn | None", chunk: int, device) -> "Tensor | None":
    """Samples to evaluate: occupied ones, dilated by one sample so no surface cell is cut."""
    if occupancy_fn is None:
        return None
    occ = _sample_grid(grid, lambda p: occupancy_fn(p).float(), None, chunk, device)
    occ = torch.nn.functional.max_pool3d(occ[None, None], kernel_size=3, stride=1, padding=1)[0, 0]
    return occ > 0


@torch.no_grad()
def _sample_grid(grid: Grid, fn: DensityFn, mask: "Tensor | None", chunk: int, device) -> Float[Tensor, "nx ny nz"]:
    """Evaluate ``fn`` on all (or the masked) grid samples, ``chunk`` points at a time; zero elsewhere."""
    nx, ny, nz = grid.shape
    out = torch.zeros(grid.shape, dtype=torch.float32)
    slab = max(1, chunk // (ny * nz))
    buffer = torch.empty(min(slab, nx), ny, nz, 3)
    for x0 in range(0, nx, slab):
        x1 = min(nx, x0 + slab)
        pts = grid.points(x0, x1, buffer)
        sel = None if mask is None else mask[x0:x1]
        flat = pts.reshape(-1, 3) if sel is None else pts[sel]
        vals = torch.cat([fn(p.to(device)).reshape(-1).float().cpu() for p in flat.split(chunk)]) if len(flat) else flat[:, 0]
        if vals.numel() != len(flat):
            raise NerfpipeError(f"density_fn returned {vals.numel()} values for {len(flat)} points")
        if sel is None:
            out[x0:x1] = vals.reshape(x1 - x0, ny, nz)
        else:
            out[x0:x1][sel] = vals
    return out


def check_level(volume: Float[Tensor, "nx ny nz"], level: float) -> None:
    """Fail with a clear message when the level yields no surface."""
    if not bool(torch.isfinite(volume).all()):
        raise NerfpipeError("the density field has NaN or infinite values; cannot extract a mesh")
    lo, hi = float(volume.min()), float(volume.max())
    if hi <= 0.0:
        raise NerfpipeError("the density field is empty (zero everywhere in the box): nothing to mesh — is the model trained?")
    if not lo < level < hi:
        raise NerfpipeError(f"level {level:.4g} is outside the density range [{lo:.4g}, {hi:.4g}] of the field: no surface at that level; choose a level inside the range")


@dataclass
class Volume:
    """Densities sampled on a grid: sample once, then mesh at as many levels as needed."""

    grid: Grid
    """Where the samples are."""
    values: Float[Tensor, "nx ny nz"]
    """Density at each sample (0 where the occupancy test skipped it)."""
    evaluated_fraction: float = 1.0
    """Fraction of samples where the field was called."""

    @property
    def min(self) -> float:
        return float(self.values.min())

    @property
    def max(self) -> float:
        return float(self.values.max())

    def downsampled(self, factor: int) -> "Volume":
        """Every ``factor``-th sample per axis: the same field on a grid ``factor`` times coarser."""
        if factor < 1:
            raise NerfpipeError(f"downsampling factor must be at least 1, got {factor}")
        values = self.values[::factor, ::factor, ::factor].contiguous()
        return Volume(Grid(self.grid.origin, self.grid.spacing * factor, tuple(values.shape)), values, self.evaluated_fraction)


def sample_volume(
    density_fn: DensityFn,
    aabb: Float[Tensor, "2 3"],
    resolution: int = 256,
    occupancy_fn: "OccupancyFn | None" = None,
    chunk: int = 1 << 18,
    device: "str | torch.device" = "cpu",
) -> Volume:
    """Sample ``density_fn`` on the grid of :meth:`Grid.over_box` (see :func:`extract_mesh` for the args)."""
    grid = Grid.over_box(aabb, resolution)
    mask = _occupied_mask(grid, occupancy_fn, chunk, device)
    values = _sample_grid(grid, density_fn, mask, chunk, device)
    return Volume(grid, values, 1.0 if mask is None else float(mask.float().mean()))


def mesh_volume(volume: Volume, level: float) -> ExtractResult:
    """Marching cubes of a sampled volume at ``level``."""
    check_level(volume.values, level)
    grid = volume.grid
    verts, faces, normals = _marching_cubes(volume.values.numpy(), level, grid)
    mesh = TriangleMesh(verts, faces, info={"method": "mc", "level": level, "voxel_size": grid.spacing, "grid_shape": list(grid.shape)})
    return ExtractResult(mesh, normals, level, grid.spacing, volume.evaluated_fraction)


def extract_mesh(
    density_fn: DensityFn,
    aabb: Float[Tensor, "2 3"],
    resolution: int = 256,
    level: "float | None" = None,
    occupancy_fn: "OccupancyFn | None" = None,
    chunk: int = 1 << 18,
    level_opacity: float = 0.5,
    device: "str | torch.device" = "cpu",
) -> ExtractResult:
    """Extract the surface ``density == level`` of a field with marching cubes.

    The same as :func:`sample_volume` then :func:`mesh_volume`; use those two to try several
    levels on one sampled volume (:func:`nerfpipe.mesh.level.choose_level`).

    Args:
        density_fn: density at world points, ``[N, 3] -> [N]``.
        aabb: box ``[min, max]`` to mesh, in world units.
        resolution: samples along the longest side of the box.
        level: iso-value; ``None`` picks :func:`auto_level` of the grid spacing.
        occupancy_fn: optional test ``[N, 3] -> bool [N]``; samples it marks empty (and not
            next to an occupied one) are not evaluated and count as density 0.
        chunk: points per ``density_fn`` call.
        level_opacity: opacity of one voxel that defines the automatic level.
        device: where the points are sent for evaluation.

    Raises:
        NerfpipeError: empty field, level outside the density range, bad box or resolution.

    Example:
        >>> sphere = lambda p: 100.0 * (p.norm(dim=-1) < 0.5).float()
        >>> r = extract_mesh(sphere, torch.tensor([[-1.0] * 3, [1.0] * 3]), resolution=32, level=50.0)
        >>> r.mesh.num_faces > 0
        True
    """
    grid = Grid.over_box(aabb, resolution)
    level = auto_level(grid.spacing, level_opacity) if level is None else float(level)
    return mesh_volume(sample_volume(density_fn, aabb, resolution, occupancy_fn, chunk, device), level)


def _marching_cubes(volume: np.ndarray, level: float, grid: Grid):
    """scikit-image marching cubes; faces wound counter-clockwise seen from low density (outside)."""
    measure = require("skimage.measure", "mesh")
    h = grid.spacing
    verts, faces, normals, _ = measure.marching_cubes(volume, level=level, spacing=(h, h, h), allow_degenerate=False)
    # skimage winds faces towards increasing values; density grows inwards, so flip to face outwards.
    return verts.astype(np.float64) + grid.origin, faces[:, ::-1].astype(np.int64), normals.astype(np.float64)
