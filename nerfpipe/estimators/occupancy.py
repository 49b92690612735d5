"""An occupancy grid over the scene box that skips empty space (instant-ngp / nerfacc style).

The grid keeps an exponential moving average of the density at each cell, refreshed from a
``density_fn`` during training, and a binary mask ``density * step > threshold``. Rays are
marched with a fixed step inside the box; samples in empty cells are dropped and the rest are
packed (see :mod:`nerfpipe.functional.packed`), so the cost follows the occupied space.

Glossary:
    aabb        ``[2, 3]`` scene box ``[min, max]``
    cell        one of ``res^3`` boxes the aabb is cut into; cell ``(i, j, k)`` is row ``(i*res + j)*res + k``
    step_size   distance between consecutive samples along a ray (world units)
    packed      samples of all rays back to back, ``ray_indices`` giving each sample's ray
"""

from dataclasses import dataclass
from collections.abc import Callable

import torch
from torch import nn

from nerfpipe.typing import Bool, Float, Int, Tensor


@dataclass
class OccupancyGridConfig:
    """How the occupancy grid is built and refreshed."""

    resolution: int = 128
    """Cells per axis."""
    update_every: int = 16
    """Refresh the grid every this many training steps."""
    warmup_steps: int = 16
    """Steps before the first refresh (every cell counts as occupied until then)."""
    ema_decay: float = 0.95
    """Decay of the running density per refresh."""
    threshold: float = 0.01
    """A cell is occupied when ``density * step_size`` exceeds this (or the mean, if lower)."""

    def setup(self, aabb: Float[Tensor, "2 3"]) -> "OccupancyGrid":
        return OccupancyGrid(self, aabb)


@dataclass
class PackedSamples:
    """Ray intervals kept by marching, packed (sorted by ray)."""

    ray_indices: Int[Tensor, "num_samples"]
    t_starts: Float[Tensor, "num_samples"]
    t_ends: Float[Tensor, "num_samples"]
    num_rays: int

    def __len__(self) -> int:
        return self.ray_indices.shape[0]

    def select(self, keep: Bool[Tensor, "num_samples"]) -> "PackedSamples":
        return PackedSamples(self.ray_indices[keep], self.t_starts[keep], self.t_ends[keep], self.num_rays)

    def points(self, origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"]) -> Float[Tensor, "num_samples 3"]:
        t = 0.5 * (self.t_starts + self.t_ends)
        return origins[self.ray_indices] + t[:, None] * directions[self.ray_indices]


def ray_aabb_intersect(
    origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"], aabb: Float[Tensor, "2 3"]
) -> "tuple[Float[Tensor, 'num_rays'], Float[Tensor, 'num_rays']]":
    """Entry and exit distances of rays through a box (slab method); ``t_near > t_far`` on a miss."""
    inv = 1.0 / torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(dim=-1)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    return t_near, t_far


class OccupancyGrid(nn.Module):
    """Binary occupancy over ``aabb`` with a running density per cell (buffers, saved with the model)."""

    def __init__(self, cfg: OccupancyGridConfig, aabb: Float[Tensor, "2 3"]) -> None:
        super().__init__()
        self.cfg = cfg
        r = cfg.resolution
        self.register_buffer("aabb", aabb.detach().clone().float())
        self.register_buffer("density", torch.zeros(r**3))
        self.register_buffer("binary", torch.ones(r**3, dtype=torch.bool))

    @property
    def occupied_fraction(self) -> float:
        return float(self.binary.float().mean())

    def cell_index(self, points: Float[Tensor, "num_points 3"]) -> "tuple[Int[Tensor, 'num_points'], Bool[Tensor, 'num_points']]":
        """Cell row of each point and whether the point is inside the box."""
        r = self.cfg.resolution
        x01 = (points - self.aabb[0]) / (self.aabb[1] - self.aabb[0])
        inside = ((x01 >= 0) & (x01 <= 1)).all(dim=-1)
        ijk = (x01 * r).long().clamp(0, r - 1)
        return (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2], inside

    def occupied(self, points: Float[Tensor, "num_points 3"]) -> Bool[Tensor, "num_points"]:
        """Whether each point lies in an occupied cell (points outside the box are empty)."""
        idx, inside = self.cell_index(points)
        return self.binary[idx] & inside

    def cell_centers(self, jitter: bool) -> Float[Tensor, "num_cells 3"]:
        r = self.cfg.resolution
        ar = torch.arange(r, device=self.aabb.device, dtype=torch.float32)
        ijk = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), dim=-1).reshape(-1, 3)
        ijk = ijk + (torch.rand_like(ijk) if jitter else 0.5)
        return self.aabb[0] + ijk / r * (self.aabb[1] - self.aabb[0])

    @torch.no_grad()
    def update(self, density_fn: Callable[[Tensor], Tensor], step_size: float, chunk: int = 1 << 19) -> None:
        """Refresh the running density at every cell (one jittered point each) and the mask."""
        pts = self.cell_centers(jitter=True)
        new = torch.cat([density_fn(p).reshape(-1).float() for p in pts.split(chunk)])
        self.density.copy_(torch.maximum(self.density * self.cfg.ema_decay, new))
        occ = self.density * step_size
        thre = min(self.cfg.threshold, float(occ.clamp(min=0).mean()))
        self.binary.copy_(occ > thre)

    def occupied_aabb(self) -> Float[Tensor, "2 3"]:
        """The smallest box around the occupied cells (the whole box when none is)."""
        r = self.cfg.resolution
        occ = self.binary.view(r, r, r)
        if not occ.any():
            return self.aabb.clone()
        lo, hi = [], []
        for axis in range(3):
            other = tuple(a for a in range(3) if a != axis)
            nz = occ.any(dim=other[1]).any(dim=other[0]).nonzero()[:, 0]
            lo.append(nz.min())
            hi.append(nz.max() + 1)
        cell = (self.aabb[1] - self.aabb[0]) / r
        return torch.stack([self.aabb[0] + torch.stack(lo) * cell, self.aabb[0] + torch.stack(hi) * cell])

    @torch.no_grad()
    def march(
        self,
        origins: Float[Tensor, "num_rays 3"],
        directions: Float[Tensor, "num_rays 3"],
        near: float,
        far: float,
        step_size: float,
        jitter: bool = False,
        aabb: "Float[Tensor, '2 3'] | None" = None,
        chunk_samples: int = 1 << 22,
    ) -> PackedSamples:
        """Intervals of length ``step_size`` along each ray through occupied cells, packed.

        Args:
            origins, directions: rays (unit directions).
            near, far: limits along every ray.
            step_size: interval length.
            jitter: shift each ray's intervals by a random fraction of a step (training).
            aabb: march only inside this box (default: the grid's box), e.g. :meth:`occupied_aabb`.
        """
        box = self.aabb if aabb is None else aabb
        t0, t1 = ray_aabb_intersect(origins, directions, box)
        t0, t1 = t0.clamp(min=near), t1.clamp(max=far)
        n_steps = ((t1 - t0) / step_size).ceil().clamp(min=0).long()
        max_steps = int(n_steps.max()) if n_steps.numel() else 0
        offset = torch.rand_like(t0) if jitter else torch.zeros_like(t0)
        parts, rows = [], max(1, chunk_samples // max(max_steps, 1))
        for s in range(0, origins.shape[0], rows):
            parts.append(self._march_rows(origins, directions, t0, t1, offset, step_size, max_steps, s, s + rows))
        return PackedSamples(*(torch.cat(p) for p in zip(*parts)), num_rays=origins.shape[0])

    def _march_rows(self, origins, directions, t0, t1, offset, step_size, max_steps, start, stop):
        sl = slice(start, stop)
        k = torch.arange(max_steps + 1, device=origins.device, dtype=origins.dtype)
        t_starts = t0[sl, None] + (k[None, :] + offset[sl, None] - 1.0).clamp(min=0) * step_size
        t_ends = (t0[sl, None] + (k[None, :] + offset[sl, None]) * step_size).clamp(max=t1[sl, None])
        mids = 0.5 * (t_starts + t_ends)
        valid = t_ends > t_starts
        pts = origins[sl, None, :] + mids[..., None] * directions[sl, None, :]
        valid &= self.occupied(pts.reshape(-1, 3)).view(valid.shape)
        ray, step = valid.nonzero(as_tuple=True)
        return ray + start, t_starts[ray, step], t_ends[ray, step]
