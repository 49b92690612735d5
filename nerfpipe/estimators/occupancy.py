"""An occupancy grid over the scene box that skips empty space (instant-ngp / nerfacc style).

The grid keeps an exponential moving average of the density at each cell, refreshed from a
``density_fn`` during training (every cell at first, then a random quarter of them and the occupied
ones), and a binary mask ``density * step > threshold``. Rays are marched with a fixed step inside
the box; samples in empty cells are dropped and the rest are packed (see
:mod:`nerfpipe.functional.packed`), so the cost follows the occupied space. Before that, each ray is
sampled once per coarse cell of a 4x coarser, dilated copy of the mask, and only the span between its
first and last occupied coarse cell is marched finely (the kept samples are the same).
:meth:`OccupancyGrid.march_until_opaque` also evaluates a density on the way, in rounds of a few
samples per ray, and stops each ray once it is opaque (early ray termination).

Glossary:
    aabb        ``[2, 3]`` scene box ``[min, max]``
    cell        one of ``res^3`` boxes the aabb is cut into; cell ``(i, j, k)`` is row ``(i*res + j)*res + k``
    coarse cell ``skip_factor^3`` cells; counts as occupied when one of its cells or of its 26 neighbours' cells is
    span        per ray, the interval numbers ``first..last`` that can meet an occupied cell
    step_size   distance between consecutive samples along a ray (world units)
    packed      samples of all rays back to back, ``ray_indices`` giving each sample's ray
    round       one pass of marching + density over the rays still alive (a few samples each)
    optical depth  sum of ``sigma * delta`` in front of a sample; transmittance is ``exp(-depth)``
"""

import math
from dataclasses import dataclass
from collections.abc import Callable

import torch
from torch import nn
from torch.nn import functional as F

from nerfpipe.functional.packed import more_opaque_than, pack_static
from nerfpipe.functional.volrend import optical_thickness, weights_from_thickness
from nerfpipe.util.typing import Bool, Float, Int, Tensor


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
    update_fraction: float = 0.25
    """Each refresh after the first evaluates this fraction of the cells, drawn at random, plus as
    many occupied cells at most (nerfacc's schedule); the others keep their running density. 1: all."""
    skip_factor: int = 4
    """Two-level empty-space skipping: each ray is first marched through a grid this many times
    coarser (occupancy dilated by one coarse cell) and only the span between its first and last
    occupied coarse cell is marched finely. The kept samples are the same (0 or 1: off)."""

    def setup(self, aabb: Float[Tensor, "2 3"]) -> "OccupancyGrid":
        return OccupancyGrid(self, aabb)


@dataclass
class PackedSamples:
    """Ray intervals kept by marching, packed (sorted by ray)."""

    ray_indices: Int[Tensor, "num_samples"]
    t_starts: Float[Tensor, "num_samples"]
    t_ends: Float[Tensor, "num_samples"]
    num_rays: int
    count: "Int[Tensor, ''] | None" = None
    """How many samples the marching kept, on the device (marching in fixed shapes; None otherwise). Where they were
    packed into slots known beforehand the slots past it are zero-length padding at the end, on the last ray (they
    add nothing to any ray), or, beyond the slots, the last samples were dropped."""
    intervals: "Int[Tensor, ''] | None" = None
    """How many occupied intervals the marching evaluated the density at, on the device (fixed shapes; None otherwise)."""

    def __len__(self) -> int:
        return self.ray_indices.shape[0]

    def select(self, keep: Bool[Tensor, "num_samples"]) -> "PackedSamples":
        return self.take(keep.nonzero()[:, 0])

    def take(self, idx: Int[Tensor, "num_kept"]) -> "PackedSamples":
        """The samples at positions ``idx`` (one mask turned into positions once: a mask indexing each tensor
        would be one host sync per tensor on CUDA)."""
        return PackedSamples(self.ray_indices[idx], self.t_starts[idx], self.t_ends[idx], self.num_rays)

    def points(self, origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"]) -> Float[Tensor, "num_samples 3"]:
        t = 0.5 * (self.t_starts + self.t_ends)
        return origins[self.ray_indices] + t[:, None] * directions[self.ray_indices]


@dataclass
class _Limits:
    """Where the rays of one :meth:`OccupancyGrid.march` call start and end, and their step."""

    origins: Tensor
    directions: Tensor
    t0: Tensor
    t1: Tensor
    offset: Tensor
    step_size: float
    box: Tensor
    """The box the rays are marched in."""
    first: Tensor
    """Per ray, the first interval number that can be occupied (0 without skipping)."""
    last: Tensor
    """Per ray, the last interval number that can be occupied (``first > last``: none)."""

    def t_start(self, rays: Tensor, k: Tensor) -> Tensor:
        """Start of interval ``k`` of each ray (as :meth:`OccupancyGrid._intervals` computes it)."""
        return self.t0[rays] + (k.to(self.t0.dtype) + self.offset[rays] - 1.0).clamp(min=0) * self.step_size


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
        self.register_buffer("_bordered", F.pad(torch.ones((r,) * 3, dtype=torch.bool), (1,) * 6).reshape(-1), persistent=False)
        """:attr:`binary` with a border of empty cells, ``(r + 2)^3``: a point's cell is read without testing whether
        it lies in the box (:meth:`occupied_along`). Copied in place when ``binary`` changes (:meth:`_bordered_mask`)."""
        self._bordered_key: "tuple | None" = None
        self._coarse_cache: "tuple | None" = None
        self._has_density: "bool | None" = None
        """Whether :attr:`density` holds a refresh (None: not known yet, read once)."""
        self._box_cache: "tuple[tuple, tuple[float, float]] | None" = None

    @property
    def occupied_fraction(self) -> float:
        return float(self.binary.float().mean())

    def cell_index(self, points: Float[Tensor, "num_points 3"]) -> "tuple[Int[Tensor, 'num_points'], Bool[Tensor, 'num_points']]":
        """Cell row of each point and whether the point is inside the box."""
        r = self.cfg.resolution
        ijk, inside = self._cell_ijk(points)
        return (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2], inside

    def _cell_ijk(self, points: Float[Tensor, "*bs 3"]) -> "tuple[Int[Tensor, '*bs 3'], Bool[Tensor, '*bs']]":
        """Cell of each point (points outside the box clamped to the nearest cell) and whether it is inside."""
        r = self.cfg.resolution
        scale, offset = self._bordered_units()
        u = torch.addcmul(offset - 1.0, points, scale)  # in cells of the box
        inside = ((u >= 0) & (u <= r)).all(dim=-1)
        return u.long().clamp(0, r - 1), inside

    def occupied(self, points: Float[Tensor, "num_points 3"]) -> Bool[Tensor, "num_points"]:
        """Whether each point lies in an occupied cell (points outside the box are empty)."""
        scale, offset = self._bordered_units()
        return self._bordered_lookup(torch.addcmul(offset, points, scale).unbind(-1))

    def occupied_along(
        self, origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"], t: Float[Tensor, "num_rays steps"]
    ) -> Bool[Tensor, "num_rays steps"]:
        """Whether the points ``origins + t * directions`` lie in occupied cells (points outside the box are empty),
        computed per axis in cells of the bordered mask (:attr:`_bordered`): one multiply-add per point and axis and
        one read, with no test whether a point is inside the box (outside it, it reads the empty border). 5x faster on
        the CPU than building the points and testing them (:meth:`cell_index`: 9.0 against 1.8 ms for 16,384 rays of
        32 intervals); a point on a cell's boundary may fall in either cell (float rounding)."""
        scale, offset = self._bordered_units()
        start, stride = torch.addcmul(offset, origins, scale), directions * scale
        return self._bordered_lookup(tuple(torch.addcmul(start[:, a, None], t, stride[:, a, None]) for a in range(3)))

    def _bordered_units(self) -> "tuple[Float[Tensor, '3'], Float[Tensor, '3']]":
        """``(scale, offset)``: a point ``p`` lies at ``p * scale + offset`` in cells of the bordered mask (cell
        ``(i, j, k)`` of the box is ``(i + 1, j + 1, k + 1)`` there)."""
        scale = self.cfg.resolution / (self.aabb[1] - self.aabb[0])
        return scale, 1.0 - self.aabb[0] * scale

    def _bordered_lookup(self, coords: "tuple[Tensor, Tensor, Tensor]") -> Bool[Tensor, "..."]:
        """The bordered mask at positions given per axis in its cells (tensors of one shape): a position outside the
        box reads the empty border, a NaN too."""
        n = self.cfg.resolution + 2
        exact = coords[0].dtype == torch.float64 or n**3 <= 1 << 24  # the rows as floats hold them exactly
        rows = None
        for u in coords:
            u = u.floor().nan_to_num_(0.0).clamp_(0, n - 1)
            u = u if exact else u.long()
            rows = u if rows is None else rows.mul_(n).add_(u)
        return self._bordered_mask()[rows.long()]

    def _bordered_mask(self) -> Bool[Tensor, "num_bordered"]:
        """:attr:`_bordered`, its inside copied from :attr:`binary` in place when that changed since (its version: the
        refresh copies it too, so that a CUDA graph replaying reads; other writers are caught here)."""
        key = (self.binary._version, self.binary.data_ptr())
        if key != self._bordered_key:
            r = self.cfg.resolution
            self._bordered.view(r + 2, r + 2, r + 2)[1:-1, 1:-1, 1:-1].copy_(self.binary.view(r, r, r))
            self._bordered_key = key
        return self._bordered

    def cell_centers(
        self, jitter: bool, cells: "Int[Tensor, 'num_cells'] | None" = None, generator: "torch.Generator | None" = None
    ) -> Float[Tensor, "num_cells 3"]:
        """Centres of all cells (or of ``cells``, by row), or one random point in each when ``jitter``."""
        r = self.cfg.resolution
        if cells is None:
            cells = torch.arange(r**3, device=self.aabb.device)
        ijk = torch.stack([cells // (r * r), (cells // r) % r, cells % r], dim=-1).float()
        ijk = ijk + (torch.rand(ijk.shape, dtype=ijk.dtype, device=ijk.device, generator=generator) if jitter else 0.5)
        return self.aabb[0] + ijk / r * (self.aabb[1] - self.aabb[0])

    @torch.no_grad()
    def update(
        self, density_fn: Callable[[Tensor], Tensor], step_size: float, full: bool = False, chunk: int = 1 << 19,
        generator: "torch.Generator | None" = None, rotation: int = 0,
    ) -> None:
        """Refresh the running density (one jittered point per cell) and the mask: at every cell when
        ``full``, at the first refresh (no density yet) or when ``update_fraction >= 1``, else at a
        random fraction of the cells and the occupied ones (random draws from ``generator``; the occupied ones in
        round robin, ``rotation`` counting the refreshes: :meth:`_cells_to_refresh`)."""
        if self._has_density is None:  # read once (a loaded grid), then known on the host
            self._has_density = bool(self.density.any())
        full = full or self.cfg.update_fraction >= 1 or not self._has_density
        cells = None if full else self._cells_to_refresh(generator, rotation)
        pts = self.cell_centers(jitter=True, cells=cells, generator=generator)
        new = torch.cat([density_fn(p).reshape(-1).float() for p in pts.split(chunk)])
        if cells is None:
            self.density.copy_(torch.maximum(self.density * self.cfg.ema_decay, new))
        else:  # a cell drawn twice decays once and keeps the larger of its new densities
            decayed = self.density.index_put((cells,), self.density[cells] * self.cfg.ema_decay)
            self.density.copy_(decayed.scatter_reduce(0, cells, new, "amax"))
        self._has_density = True
        occ = self.density * step_size
        thre = occ.clamp(min=0).mean().clamp(max=self.cfg.threshold)  # on the device: no read back
        self.binary.copy_(occ > thre)
        self._bordered_mask()

    def _cells_to_refresh(self, generator: "torch.Generator | None", rotation: int) -> Int[Tensor, "num_refreshed"]:
        """``update_fraction`` of the cells uniformly at random, and as many occupied cells at most: all of them
        when there are fewer, else the first ones in row order from row ``rotation * n`` on (round robin over
        the refreshes: every occupied cell is drawn at least once in ``1 / update_fraction`` of them). The rows are
        a fixed number (a cell may come twice; where there are fewer occupied cells, the uniform ones fill in): no
        shape depends on the data and nothing is read back."""
        total = self.binary.numel()
        n = max(1, int(total * self.cfg.update_fraction))
        uniform = torch.randint(total, (n,), device=self.binary.device, generator=generator)
        start = rotation * n % total
        rolled = torch.roll(self.binary, -start)
        occupied = (torch.nonzero_static(rolled, size=n, fill_value=0)[:, 0] + start) % total
        found = torch.arange(n, device=uniform.device) < rolled.sum()
        return torch.cat([uniform, torch.where(found, occupied, uniform)])

    def occupied_aabb(self) -> Float[Tensor, "2 3"]:
        """The smallest box around the occupied cells (the whole box when none is), computed on the device:
        per axis the first and last occupied slab (``argmax`` of the slabs' occupancy, from either end)."""
        return self._box_of(self.binary.view((self.cfg.resolution,) * 3))

    @torch.no_grad()
    def supported_aabb(self, min_share: float = 0.01) -> Float[Tensor, "2 3"]:
        """The smallest box around the occupied cells of the pieces that hold at least ``min_share`` of them:
        the occupied cells are grouped into 26-connected pieces (on a copy of the grid coarsened twofold, so
        that a piece may have gaps of a cell), and the small pieces, floaters that a few views' noise left
        anywhere in the box, do not stretch the box (one host read: for occasional calls, e.g. tightening).

        Example: lego_200 after 140 steps has 99.5 k occupied cells, 98 % in one piece and the rest in 815
        pieces of at most 129 cells spread to the box's faces: :meth:`occupied_aabb` is nearly the whole box.
        """
        from nerfpipe.functional.components import connected_components

        r = self.cfg.resolution
        occ = self.binary.view(r, r, r)
        counts = F.avg_pool3d(occ.float()[None, None], 2, ceil_mode=True, divisor_override=1)[0, 0]  # occupied cells per coarse cell
        labels = connected_components(counts > 0)
        per_label = torch.zeros(labels.numel() + 1, device=occ.device).index_add_(0, labels.reshape(-1), counts.reshape(-1))
        per_label[0] = 0.0
        kept = per_label >= min_share * per_label.sum()
        coarse = kept[labels]
        fine = coarse.repeat_interleave(2, 0).repeat_interleave(2, 1).repeat_interleave(2, 2)[:r, :r, :r]
        return self._box_of(occ & fine)

    def _box_of(self, occ: Bool[Tensor, "r r r"]) -> Float[Tensor, "2 3"]:
        r = self.cfg.resolution
        lo, hi = [], []
        for axis in range(3):
            other = tuple(a for a in range(3) if a != axis)
            slabs = occ.any(dim=other[1]).any(dim=other[0]).byte()
            lo.append(slabs.argmax())
            hi.append(r - slabs.flip(0).argmax())
        cell = (self.aabb[1] - self.aabb[0]) / r
        box = torch.stack([self.aabb[0] + torch.stack(lo) * cell, self.aabb[0] + torch.stack(hi) * cell])
        return torch.where(occ.any(), box, self.aabb)

    def _limits(self, origins, directions, near, far, step_size, jitter, aabb, generator=None, span: bool = True) -> "_Limits":
        # a march box is clipped to the grid's box (outside it no cell is occupied), so the grid's diagonal bounds
        # every ray's span: read once per grid box, not once per march box (which changes at every refresh)
        box = self.aabb if aabb is None else torch.stack([torch.maximum(aabb[0], self.aabb[0]), torch.minimum(aabb[1], self.aabb[1])])
        t0, t1 = ray_aabb_intersect(origins, directions, box)
        t0, t1 = t0.clamp(min=near), t1.clamp(max=far)
        n_steps = ((t1 - t0) / step_size).ceil().clamp(min=0).long()
        offset = torch.rand(t0.shape, dtype=t0.dtype, device=t0.device, generator=generator) if jitter else torch.zeros_like(t0)
        lim = _Limits(origins, directions, t0, t1, offset, step_size, box, torch.zeros_like(n_steps), n_steps)
        if span and self.cfg.skip_factor > 1 and n_steps.numel():
            lim.first, lim.last = self._occupied_span(lim)
        return lim

    def _coarse(self) -> "tuple[Bool[Tensor, 'num_coarse'], int]":
        """Occupancy of cells ``skip_factor`` times larger, dilated by one cell (cached until ``binary`` changes)."""
        key = (self.binary._version, self.binary.data_ptr())
        if self._coarse_cache is None or self._coarse_cache[0] != key:
            r, f = self.cfg.resolution, self.cfg.skip_factor
            occ = self.binary.view(1, 1, r, r, r).float()
            coarse = torch.nn.functional.max_pool3d(occ, f, f, ceil_mode=True)
            coarse = torch.nn.functional.max_pool3d(coarse, 3, 1, padding=1)
            self._coarse_cache = (key, coarse.reshape(-1) > 0, coarse.shape[-1])
        return self._coarse_cache[1], self._coarse_cache[2]

    def _grid_box(self) -> "tuple[float, float]":
        """The smallest side of a cell and the diagonal of the grid's box, read from the device once per box (it
        changes when the box is tightened): every marched box lies in it (:meth:`_limits`)."""
        key = (self.aabb.data_ptr(), self.aabb._version)
        if self._box_cache is None or self._box_cache[0] != key:
            grid = self.aabb.detach().cpu()
            self._box_cache = key, (float(((grid[1] - grid[0]) / self.cfg.resolution).min()), float((grid[1] - grid[0]).norm()))
        return self._box_cache[1]

    def _coarse_steps(self) -> "tuple[float, int]":
        """The coarse step ``h`` and the most coarse samples a unit ray can take through the grid's box (its
        diagonal over ``h``, with a margin for rounding)."""
        cell, diagonal = self._grid_box()
        h = cell * self.cfg.skip_factor
        return h, max(int(math.ceil(diagonal / h * 1.001)) + 2, 1)

    def max_intervals(self, step_size: float) -> int:
        """The most intervals of ``step_size`` a unit ray can have in the grid's box (known on the host)."""
        return int(math.ceil(self._grid_box()[1] / step_size * 1.001)) + 2

    def _occupied_span(self, lim: "_Limits", chunk: int = 1 << 21) -> "tuple[Tensor, Tensor]":
        """First and last interval of each ray that can meet an occupied cell.

        The ray is sampled every ``h`` (the smallest side of a coarse cell) at ``t0 + (j + 1/2) h``.
        Every point of ``[t0, t1]`` lies within ``h / 2`` of a sample, so within one coarse cell of it
        along each axis: a point in an occupied cell puts a sample in the dilated coarse occupancy.
        No occupied point therefore lies before ``t0 + j_first h`` or after ``t0 + (j_last + 1) h``,
        and the intervals wholly outside that span (one more on each side for rounding) are skipped.
        The number of coarse samples is bounded by the diagonal of the marched box (unit directions), not
        read from the rays: no data-dependent shape reaches the host.
        """
        coarse, rc = self._coarse()
        f = self.cfg.skip_factor
        h, n_max = self._coarse_steps()
        n = ((lim.t1 - lim.t0) / h).ceil().clamp(min=0, max=n_max).long()
        j = torch.arange(n_max, device=n.device)
        # the samples in coarse cells' units: a start and a step per ray, one multiply-add per sample (a float
        # rounding moves a sample by far less than the half coarse cell the argument above leaves to spare)
        scale = (self.cfg.resolution / f) / (self.aabb[1] - self.aabb[0])
        start = (lim.origins + lim.t0[:, None] * lim.directions - self.aabb[0]) * scale
        stride = lim.directions * (h * scale)
        half = (j + 0.5).to(lim.t0.dtype)[None, :, None]
        exact = start.dtype == torch.float64 or (start.dtype == torch.float32 and rc**3 <= 1 << 24)  # the cells' rows as floats hold them exactly
        j_first, j_last, hit_any = [], [], []
        for s in range(0, len(n), max(1, chunk // n_max)):
            rows = slice(s, s + max(1, chunk // n_max))
            q = torch.addcmul(start[rows, None, :], half, stride[rows, None, :]).floor_().nan_to_num_(0.0).clamp_(0, rc - 1)
            q = q if exact else q.long()
            cells = (q[..., 0] * rc + q[..., 1]).mul_(rc).add_(q[..., 2]).long()
            hit = coarse[cells] & (j < n[rows, None])  # points outside the box count in the nearest coarse cell
            first = torch.where(hit, j, n_max).amin(dim=1)  # the first and last hit (none: 0 and n_max - 1, unused)
            any_hit = first < n_max
            j_first.append(torch.where(any_hit, first, 0))
            j_last.append(torch.where(any_hit, torch.where(hit, j, -1).amax(dim=1), n_max - 1))
            hit_any.append(any_hit)
        jf, jl, any_hit = torch.cat(j_first), torch.cat(j_last), torch.cat(hit_any)
        per_step = h / lim.step_size
        first = ((jf * per_step - lim.offset).floor().long() - 1).clamp(min=0)
        last = torch.minimum(((jl + 1) * per_step - lim.offset + 1.0).ceil().long() + 1, lim.last)
        return torch.where(any_hit, first, lim.last + 1), last

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
        generator: "torch.Generator | None" = None,
    ) -> PackedSamples:
        """Intervals of length ``step_size`` along each ray through occupied cells, packed.

        Args:
            origins, directions: rays (unit directions).
            near, far: limits along every ray.
            step_size: interval length.
            jitter: shift each ray's intervals by a random fraction of a step (training).
            aabb: march only inside this box (default: the grid's box), e.g. :meth:`occupied_aabb`.
            generator: the stream of the jitter (default: torch's global one).
        """
        lim = self._limits(origins, directions, near, far, step_size, jitter, aabb, generator)
        span = int((lim.last - lim.first).max()) + 1 if origins.shape[0] else 0
        k = torch.arange(max(span, 0), device=origins.device)[None, :]
        parts, rows = [], max(1, chunk_samples // max(span, 1))
        for s in range(0, origins.shape[0], rows):
            rays = torch.arange(s, min(s + rows, origins.shape[0]), device=origins.device)
            ks = lim.first[rays, None] + k
            valid, t_starts, t_ends = self._intervals(lim, rays, ks.to(origins.dtype))
            valid &= ks <= lim.last[rays, None]
            ray, step = valid.nonzero(as_tuple=True)
            parts.append((rays[ray], t_starts[ray, step], t_ends[ray, step]))
        if not parts:
            return PackedSamples(origins.new_zeros(0, dtype=torch.long), origins.new_zeros(0), origins.new_zeros(0), 0)
        return PackedSamples(*(torch.cat(p) for p in zip(*parts)), num_rays=origins.shape[0])

    def _intervals(self, lim: _Limits, rays: Int[Tensor, "num_rays"], k: Float[Tensor, "rows steps"]):
        """Intervals number ``k`` of rays ``rays`` (``[R, S]`` each) and which are in occupied cells."""
        t0, offset = lim.t0[rays, None], lim.offset[rays, None]
        t_starts = t0 + (k + offset - 1.0).clamp(min=0) * lim.step_size
        t_ends = (t0 + (k + offset) * lim.step_size).clamp(max=lim.t1[rays, None])
        valid = t_ends > t_starts
        valid &= self.occupied_along(lim.origins[rays], lim.directions[rays], 0.5 * (t_starts + t_ends))
        return valid, t_starts, t_ends

    @torch.no_grad()
    def march_until_opaque(
        self,
        origins: Float[Tensor, "num_rays 3"],
        directions: Float[Tensor, "num_rays 3"],
        near: float,
        far: float,
        step_size: float,
        sigma_fn: "Callable[[PackedSamples], Tensor]",
        min_transmittance: float,
        min_alpha: "float | None" = None,
        jitter: bool = False,
        aabb: "Float[Tensor, '2 3'] | None" = None,
        rounds: "Rounds | None" = None,
        generator: "torch.Generator | None" = None,
        fixed_shapes: bool = False,
        capacity: "tuple[int, int] | None" = None,
    ) -> "tuple[PackedSamples, Float[Tensor, 'num_samples']]":
        """:meth:`march` then :func:`~nerfpipe.functional.packed.prune_mask`, with early ray termination.

        Rays are marched and their densities evaluated in rounds of a few samples per ray; a ray
        stops once its transmittance has fallen to ``min_transmittance``, so samples behind an
        opaque surface are never marched nor evaluated (instant-ngp's compacted rounds).

        Args:
            origins, directions, near, far, step_size, jitter, aabb, generator: as for :meth:`march`.
            sigma_fn: density of packed samples (``[num_samples]``), evaluated without gradients.
            min_transmittance: keep samples whose transmittance exceeds this.
            min_alpha: keep only samples more opaque than this (``None``: no alpha test).
            rounds: samples per ray and round (default :class:`Rounds`).
            fixed_shapes: instead of rounds, march every ray over the longest span the grid's box allows and
                evaluate the density at every interval at once, in shapes known on the host; the kept samples
                are then packed by one ``nonzero``, the only read back (for a GPU: see :meth:`_until_opaque_fixed`).
            capacity: with ``fixed_shapes``, ``(sample slots, interval slots)``: pack the occupied intervals whose density
                is evaluated and the samples kept into exactly that many (no read back at all: :func:`pack_static`);
                those beyond are dropped (an interval dropped counts as empty), the result's ``count`` and
                ``intervals`` say how many there were.

        Returns:
            The kept samples, as ``prune_mask`` selects them from :meth:`march` (equal up to the
            order of floating-point sums), and their densities.
        """
        # in fixed shapes every ray is marched over the longest span anyway: the coarse skipping would save nothing
        lim = self._limits(origins, directions, near, far, step_size, jitter, aabb, generator, span=not fixed_shapes)
        if fixed_shapes:
            return self._until_opaque_fixed(lim, sigma_fn, min_transmittance, min_alpha, capacity=capacity)
        state = _RayState.start(lim)
        rounds = rounds or Rounds()
        kept, n = [], 0
        while len(state.rays):
            k, s = rounds.samples(n), rounds.steps(n)
            rows = max(1, rounds.chunk_samples // s)
            parts = [self._round(lim, state.slice(i, i + rows), sigma_fn, k, s, min_transmittance, min_alpha)
                     for i in range(0, len(state.rays), rows)]
            kept += [p[0] for p in parts]  # (samples, densities, which to keep) of each chunk
            state = _RayState.cat([p[1] for p in parts])
            n += 1
        return _sorted_by_ray(kept, origins)

    def _until_opaque_fixed(self, lim: _Limits, sigma_fn, min_transmittance: float, min_alpha: "float | None", chunk: int = 1 << 22,
                            capacity: "tuple[int, int] | None" = None, compact: "bool | None" = None):
        """:meth:`march_until_opaque` in shapes known on the host: each ray's intervals ``first .. first + S - 1``
        (``S`` = :meth:`max_intervals`, the longest span a ray can have in the grid's box) are marched, their
        densities evaluated where they are occupied, the transmittance in front of each is an exclusive cumulative
        sum along the row, and one ``nonzero`` packs the samples kept. The rounds' read backs (a ``nonzero`` for the
        samples and one for the rays still alive in each round) are gone. ``compact`` (default: on the CPU, and with
        a ``capacity``): the occupied intervals are gathered first and the density evaluated at those only (on the
        CPU by a ``nonzero``: 106 ms per lego_200 step at 4,096 rays against 340 ms with a density at every interval,
        as fast as the rounds' 107, the same samples); otherwise at every interval, the empty ones masked (CUDA's
        eager step: it keeps the one read back)."""
        num_rays, span = lim.origins.shape[0], self.max_intervals(lim.step_size)
        device = lim.origins.device
        compact = (device.type == "cpu" or capacity is not None) if compact is None else compact
        if capacity is not None:  # one chunk: the slots count every ray's intervals
            chunk = num_rays * span
        k, rows = torch.arange(span, device=device), max(1, chunk // span)
        valid, t_starts, t_ends, sigma = [], [], [], []
        for s in range(0, num_rays, rows):
            rays = torch.arange(s, min(s + rows, num_rays), device=device)
            ks = lim.first[rays, None] + k
            v, t0, t1 = self._intervals(lim, rays, ks.to(lim.t0.dtype))
            v &= ks <= lim.last[rays, None]
            if compact:
                sigma.append(_occupied_sigma(v, t0, t1, rays, sigma_fn, num_rays, None if capacity is None else capacity[1]))
            else:
                every = PackedSamples(rays[:, None].expand_as(ks).reshape(-1), t0.reshape(-1), t1.reshape(-1), num_rays)
                sigma.append(torch.where(v, sigma_fn(every).view(v.shape), 0.0))
            valid.append(v), t_starts.append(t0), t_ends.append(t1)
        valid, t_starts, t_ends, sigma = (torch.cat(t) for t in (valid, t_starts, t_ends, sigma))
        thickness = torch.where(valid, optical_thickness(sigma, (t_ends - t_starts).clamp(min=0)), 0.0)
        before = torch.cumsum(thickness.double(), dim=1) - thickness.double()
        _, trans = weights_from_thickness(thickness, before)
        keep = valid & (trans > min_transmittance)
        if min_alpha is not None:
            keep &= more_opaque_than(sigma.reshape(-1), (t_ends - t_starts).reshape(-1), min_alpha).view(keep.shape)
        intervals = valid.sum()
        if capacity is not None:  # no read back: a CUDA graph can hold the whole step
            flat, count, pad = pack_static(keep.reshape(-1), capacity[0], fill=(num_rays - 1) * span)
            row, col = flat // span, flat % span  # padding: the last ray's first interval, made zero-length
            t0 = t_starts[row, col]
            samples = PackedSamples(row, t0, torch.where(pad, t0, t_ends[row, col]), num_rays, count=count, intervals=intervals)
            return samples, torch.where(pad, 0.0, sigma[row, col])
        row, col = keep.nonzero(as_tuple=True)  # the one read back: how many samples there are
        return PackedSamples(row, t_starts[row, col], t_ends[row, col], num_rays, intervals=intervals), sigma[row, col]

    def _round(self, lim, state, sigma_fn, k_max, steps, min_transmittance, min_alpha):
        """March ``steps`` intervals of the rays in ``state``, evaluate the first ``k_max`` occupied ones."""
        k = state.next_step[:, None] + torch.arange(steps, device=state.rays.device)
        valid, t_starts, t_ends = self._intervals(lim, state.rays, k.to(lim.t0.dtype))
        valid &= k <= lim.last[state.rays, None]
        rank = valid.cumsum(dim=1)
        row, col = (valid & (rank <= k_max)).nonzero(as_tuple=True)
        samples = PackedSamples(state.rays[row], t_starts[row, col], t_ends[row, col], lim.origins.shape[0])
        sigma = sigma_fn(samples) if len(samples) else t_starts.new_zeros(0)
        trans, optical_depth = _transmittance(sigma, samples, row, col, state.optical_depth, valid.shape)
        keep = trans > min_transmittance
        if min_alpha is not None:
            keep &= more_opaque_than(sigma, samples.t_ends - samples.t_starts, min_alpha)
        n_valid = rank[:, -1]
        advance = torch.where(n_valid > k_max, (rank < k_max).sum(dim=1) + 1, steps)
        state = _RayState(state.rays, state.next_step + advance, optical_depth)
        alive = torch.exp(-optical_depth.to(trans.dtype)) > min_transmittance
        alive &= (state.next_step <= lim.last[state.rays]) & (lim.t_start(state.rays, state.next_step) < lim.t1[state.rays])
        return (samples, sigma, keep), state.select(alive)


@dataclass
class Rounds:
    """How many samples per ray :meth:`OccupancyGrid.march_until_opaque` evaluates in each round."""

    first: int = 8
    """Occupied samples per ray evaluated in the first round."""
    most: int = 32
    """The number doubles each round up to this."""
    steps_per_sample: int = 4
    """Intervals marched per round: this many per sample (empty ones are skipped)."""
    chunk_samples: int = 1 << 21
    """Intervals marched at once (bounds memory)."""

    def samples(self, n: int) -> int:
        return min(self.most, self.first << min(n, 30))

    def steps(self, n: int) -> int:
        return self.samples(n) * self.steps_per_sample


@dataclass
class _RayState:
    """Rays still marching: their index, next interval number and optical depth so far (float64)."""

    rays: Tensor
    next_step: Tensor
    optical_depth: Tensor

    @staticmethod
    def start(lim: _Limits) -> "_RayState":
        rays = ((lim.t0 < lim.t1) & (lim.first <= lim.last)).nonzero()[:, 0]
        return _RayState(rays, lim.first[rays], torch.zeros(len(rays), dtype=torch.float64, device=rays.device))

    @staticmethod
    def cat(states: "list[_RayState]") -> "_RayState":
        return _RayState(*(torch.cat(t) for t in zip(*((s.rays, s.next_step, s.optical_depth) for s in states))))

    def slice(self, start: int, stop: int) -> "_RayState":
        return _RayState(self.rays[start:stop], self.next_step[start:stop], self.optical_depth[start:stop])

    def select(self, keep: Tensor) -> "_RayState":
        idx = keep.nonzero()[:, 0]  # once for the three tensors (a mask per tensor: three host syncs on CUDA)
        return _RayState(self.rays[idx], self.next_step[idx], self.optical_depth[idx])


def _occupied_sigma(valid: Tensor, t0: Tensor, t1: Tensor, rays: Tensor, sigma_fn, num_rays: int, slots: "int | None" = None) -> Tensor:
    """Densities ``[R, S]`` of the intervals ``valid`` marks (occupied), evaluated there only; 0 elsewhere. The
    occupied ones are found by a ``nonzero``, or packed into ``slots`` (:func:`pack_static`: no read back; those
    beyond the slots count as empty, the padding is evaluated at the first interval and added as 0)."""
    flat = valid.reshape(-1)
    if slots is None:
        pos, pad = flat.nonzero()[:, 0], None
    else:
        pos, _, pad = pack_static(flat, slots)
    sub = PackedSamples(rays[:, None].expand_as(valid).reshape(-1)[pos], t0.reshape(-1)[pos], t1.reshape(-1)[pos], num_rays)
    sigma = sigma_fn(sub).to(t0.dtype)
    if pad is not None:
        sigma = torch.where(pad, 0.0, sigma)
    return torch.zeros(flat.shape, dtype=t0.dtype, device=t0.device).index_add_(0, pos, sigma).view(valid.shape)


def _transmittance(sigma, samples: PackedSamples, row, col, optical_depth, shape):
    """Transmittance in front of each evaluated sample and each row's optical depth after the round.

    The thickness and transmittance of :mod:`nerfpipe.functional.volrend` (as every renderer's);
    only the optical depth in front of a sample is summed here, in float64, carried across rounds.
    """
    thickness = optical_thickness(sigma, samples.t_ends - samples.t_starts)
    dense = torch.zeros(shape, dtype=torch.float64, device=sigma.device)
    dense[row, col] = thickness.double()
    cum = torch.cumsum(dense, dim=1)
    before = optical_depth[row] + (cum[row, col] - dense[row, col])
    _, trans = weights_from_thickness(thickness, before)
    return trans, optical_depth + cum[:, -1]


def _sorted_by_ray(kept: list, origins: Tensor) -> "tuple[PackedSamples, Tensor]":
    """Concatenate the rounds' evaluated samples, keep those their masks keep and order them by ray (stable:
    each ray's rounds are in order). The masks are applied here, once for all rounds and tensors."""
    num_rays = origins.shape[0]
    if not kept:
        return PackedSamples(torch.zeros(0, dtype=torch.long, device=origins.device), origins.new_zeros(0), origins.new_zeros(0), num_rays), origins.new_zeros(0)
    idx = torch.cat([keep for _, _, keep in kept]).nonzero()[:, 0]
    rays = torch.cat([p.ray_indices for p, _, _ in kept])
    order = idx[torch.sort(rays[idx], stable=True).indices]
    samples = PackedSamples(rays[order], *(torch.cat(t)[order] for t in zip(*((p.t_starts, p.t_ends) for p, _, _ in kept))), num_rays)
    return samples, torch.cat([s for _, s, _ in kept])[order]
