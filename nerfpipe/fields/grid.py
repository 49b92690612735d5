"""Dense voxel grids stored channels-last and read by trilinear interpolation (pure torch).

A grid of resolution ``(rx, ry, rz)`` has one vertex per integer position, vertex ``(i, j, k)``
at normalised coordinate ``(i / (rx - 1), j / (ry - 1), k / (rz - 1))`` in the unit cube
(``align_corners=True``). Its values live in a table ``[rx * ry * rz, C]`` with row
``(i * ry + j) * rz + k``, so one trilinear read is a weighted sum of eight rows
(:func:`nerfpipe.functional.gather.weighted_gather`: ``embedding_bag`` on the CPU). On CPU a gather and a
weighted sum were about 3x faster than ``grid_sample`` on ``[C, rz, ry, rx]`` volumes for a dozen
channels even before (as ``index_select`` and a product), and the backward pass is a ``scatter_add_`` of each channel on
the CPU (one call for all), one ``index_add_`` elsewhere (:func:`nerfpipe.functional.gather.table_grad`).

A level with more vertices than its table has rows is *hashed* (instant-ngp): vertex ``(i, j, k)`` is
stored in row ``(i·p_i XOR j·p_j XOR k) mod rows`` of a table of ``rows`` (a power of two) rows, so memory
is set by the table, not by the resolution; neighbours along the last axis stay in adjacent rows
(its prime is 1), as in the dense layout.

A level may also be *sparse* (Plenoxels / DVGO's idea with blocks): its vertices are stored in blocks of
``BLOCK`` x ``BLOCK`` x ``BLOCK`` (4 x 4 x 4) vertices, only for the blocks that the occupied space needs, and a small map holds each
block's first row in the table (-1: not stored). Row ``first + (li * BLOCK + lj) * BLOCK + lk`` holds the vertex
at local position ``(li, lj, lk)`` of its block. A corner of an unstored block reads as 0 (its weight is zeroed, so
no gradient reaches any row). The table has free slots (rows of zeros that no map entry points at, so they get no
gradient and Adam leaves them at zero): blocks that the occupancy needs later are stored there, on the device.

Glossary:
    x01     points in the unit cube ``[0, 1]^3`` (the scene box mapped to it)
    res     vertices per axis ``(rx, ry, rz)``
    idx     ``[N, 8]`` table rows of the eight corners around each point
    w       ``[N, 8]`` trilinear weights of those corners (sum to 1)
"""

import functools
import math

import torch
from torch import nn

from nerfpipe.functional.gather import move_rows, weighted_gather
from nerfpipe.util.typing import Bool, Float, Int, Tensor

# corner offsets (di, dj, dk) in the order of the eight trilinear weights
_CORNERS = ((0, 0, 0), (0, 0, 1), (0, 1, 0), (0, 1, 1), (1, 0, 0), (1, 0, 1), (1, 1, 0), (1, 1, 1))


BLOCK = 4
"""Vertices per axis of a sparse level's blocks."""

# hashing primes per axis (instant-ngp's; the last axis gets 1 so that its neighbours share cache lines)
HASH_PRIMES = (2654435761, 805459861, 1)
_HASH_PRIMES_INT32 = tuple(p - (1 << 32) if p >= 1 << 31 else p for p in HASH_PRIMES)
"""The primes' low 32 bits as int32 values (:func:`hashed_rows_per_axis`)."""


@functools.lru_cache(maxsize=256)
def _level_constants(
    resolutions: "tuple[tuple[int, int, int], ...]", dtype: torch.dtype, device: torch.device, index_dtype: torch.dtype = torch.long
) -> "tuple[Tensor, Tensor, Tensor, Tensor, Tensor]":
    """The constant tensors of the corner computation of some levels (``[L, 1, ...]``: a level per row), built once
    per resolutions, dtype and device (built on every call, each would be a blocking host-to-device copy on CUDA):
    the last vertex index per axis, the last cell's lower corner, the dense layout's row strides and corner
    offsets (in ``index_dtype``), and the hashing primes."""
    size = torch.tensor(resolutions, dtype=dtype, device=device)[:, None, :] - 1
    strides = torch.tensor([[ry * rz, rz, 1] for _, ry, rz in resolutions], dtype=index_dtype, device=device)[:, None, :]
    offsets = torch.tensor([[(di * ry + dj) * rz + dk for di, dj, dk in _CORNERS] for _, ry, rz in resolutions], dtype=index_dtype,
                           device=device)[:, None, :]
    primes = torch.tensor(HASH_PRIMES, device=device)
    return size, (size - 1).clamp(min=0), strides, offsets, primes


def trilinear_corners(
    x01: Float[Tensor, "num_points 3"], res: "tuple[int, int, int]", rows: "int | None" = None
) -> "tuple[Int[Tensor, 'num_points 8'], Float[Tensor, 'num_points 8']]":
    """Table rows and trilinear weights of the eight grid vertices around each point.

    Points outside the unit cube are clamped to its surface. ``rows``: the table's rows when the
    level is hashed (a power of two below the vertex count), else None.
    """
    idx, w = trilinear_corners_levels(x01, (tuple(res),), rows)
    return idx[0], w[0]


def trilinear_corners_levels(
    x01: Float[Tensor, "num_points 3"], resolutions: "tuple[tuple[int, int, int], ...]", rows: "int | None" = None
) -> "tuple[Int[Tensor, 'levels num_points 8'], Float[Tensor, 'levels num_points 8']]":
    """:func:`trilinear_corners` of several levels at the same points at once (level ``l`` in row ``l``; all
    dense, or all hashed into tables of ``rows`` rows): one pass of a few dozen tensor operations for all of them,
    not one per level (on a GPU each is a kernel launch)."""
    lo, w = trilinear_lo_levels(x01, resolutions)
    if rows is None:
        return dense_rows(lo, resolutions), w
    if x01.device.type == "cpu":
        return hashed_rows_per_axis(lo, rows), w
    return hashed_rows(lo.long(), rows, _level_constants(tuple(tuple(r) for r in resolutions), x01.dtype, x01.device)[4]), w


def dense_rows(lo: Float[Tensor, "levels num_points 3"], resolutions: "tuple[tuple[int, int, int], ...]") -> Int[Tensor, "levels num_points 8"]:
    """Dense table rows of the eight vertices around each point, from :func:`trilinear_lo_levels`' lower corners: in
    32-bit integers on the CPU where the levels' vertices fit (its gather reads them so: :func:`~nerfpipe.functional.
    gather.gather_rows_sum`), else 64-bit."""
    key = tuple(tuple(r) for r in resolutions)
    fits = lo.device.type == "cpu" and max(rx * ry * rz for rx, ry, rz in key) < 2**31
    index = torch.int32 if fits else torch.long
    _, _, strides, offsets, _ = _level_constants(key, lo.dtype, lo.device, index)
    return (lo.to(index) * strides).sum(-1, dtype=index)[..., None] + offsets


def trilinear_lo_levels(
    x01: Float[Tensor, "num_points 3"], resolutions: "tuple[tuple[int, int, int], ...]"
) -> "tuple[Float[Tensor, 'levels num_points 3'], Float[Tensor, 'levels num_points 8']]":
    """The lower corner vertex of the cell around each point (whole numbers, as floats) and the eight trilinear
    weights, for several levels at once (the part of :func:`trilinear_corners_levels` that every layout shares)."""
    size, last, *_ = _level_constants(tuple(tuple(r) for r in resolutions), x01.dtype, x01.device)
    pos = x01.clamp(0.0, 1.0) * size  # [L, N, 3]
    lo = torch.minimum(pos.floor(), last)
    return lo, trilinear_weights(pos - lo, per_axis=x01.device.type == "cpu")


def trilinear_weights(frac: Float[Tensor, "*bs 3"], per_axis: bool) -> Float[Tensor, "*bs 8"]:
    """The eight trilinear weights (in the order of ``_CORNERS``) of points at ``frac`` in their cells, bit for bit
    alike by two routes: broadcast products of ``[..., 3, 2]`` slices (few operations: the GPU's choice), or products
    of whole per-axis tensors (``per_axis``: twice as fast on the CPU, where the broadcast over strided slices is
    slow: 4.4 against 8.7 ms for 3 levels of 60,000 points), each corner's product written into its column (stacking
    the products took as long again, session 59). Writes into a buffer are not differentiable: weights that need
    gradients (camera refinement) take the broadcast route."""
    if per_axis and not (frac.requires_grad and torch.is_grad_enabled()):
        f = frac.movedim(-1, 0)
        g = 1 - f
        (x0, y0, z0), (x1, y1, z1) = g.unbind(0), f.unbind(0)
        out = frac.new_empty(*frac.shape[:-1], 8)
        cols = out.unbind(-1)
        for c, xy in enumerate(x * y for x in (x0, x1) for y in (y0, y1)):
            torch.mul(xy, z0, out=cols[2 * c])
            torch.mul(xy, z1, out=cols[2 * c + 1])
        return out
    w1 = torch.stack([1 - frac, frac], dim=-1)  # [..., 3, 2]
    return (w1[..., 0, :, None, None] * w1[..., 1, None, :, None] * w1[..., 2, None, None, :]).flatten(-3)


def hashed_rows(lo: Int[Tensor, "*bs 3"], rows: int, primes: "Int[Tensor, '3'] | None" = None) -> Int[Tensor, "*bs 8"]:
    """Hashed table rows of the eight vertices ``lo + (di, dj, dk)`` (in the order of ``_CORNERS``);
    ``primes``: :data:`HASH_PRIMES` as a tensor on ``lo``'s device (default: built here)."""
    if primes is None:
        primes = torch.tensor(HASH_PRIMES, device=lo.device)
    terms = torch.stack([lo, lo + 1], dim=-1) * primes[:, None]  # [*bs, 3, 2]
    h = terms[..., 0, :, None, None] ^ terms[..., 1, None, :, None] ^ terms[..., 2, None, None, :]
    return h.flatten(-3) & (rows - 1)


def hashed_rows_per_axis(lo: "Tensor", rows: int) -> Int[Tensor, "*bs 8"]:
    """:func:`hashed_rows`, bit for bit, by products of whole per-axis tensors in 32-bit integers: the CPU's route.
    The broadcast over strided ``[..., 3, 2]`` slices in 64 bits is slow there (150,000 points of 2 levels: 20 against
    7 ms). A row keeps only the low bits of the hash (``rows`` is a power of two up to 2^31), and products, sums and
    XORs in 32 bits, wrapping, keep the low 32 bits of the 64-bit ones. ``lo``: whole numbers (floats or integers).
    The rows stay 32-bit integers where they fit (the CPU's gather reads them so: :func:`~nerfpipe.functional.gather.
    gather_rows_sum`)."""
    if rows > 1 << 31:
        return hashed_rows(lo.long(), rows)
    # each axis's two terms masked (AND distributes over XOR), then each corner's XOR written into its column: 1.4x
    # faster than XORs of stacked [..., 4] terms, stacked and masked (150,000 points of 2 levels, session 59)
    mask = rows - 1
    terms = []
    for t, p in zip(lo.movedim(-1, 0).int().unbind(0), _HASH_PRIMES_INT32):
        t = t * p if p != 1 else t.clone()
        terms.append(((t + p).bitwise_and_(mask), t.bitwise_and_(mask)))  # (the + p before t is masked in place)
    (a1, a0), (b1, b0), (c1, c0) = terms
    out = torch.empty(*lo.shape[:-1], 8, dtype=torch.int32, device=lo.device)
    cols = out.unbind(-1)
    for c, ab in enumerate(a ^ b for a in (a0, a1) for b in (b0, b1)):  # (di, dj) in the order of _CORNERS
        torch.bitwise_xor(ab, c0, out=cols[2 * c])
        torch.bitwise_xor(ab, c1, out=cols[2 * c + 1])
    return out


def hashed_row_reference(i: int, j: int, k: int, rows: int) -> int:
    """The row of vertex ``(i, j, k)`` of a hashed level, one vertex at a time (the reference)."""
    return ((i * HASH_PRIMES[0]) ^ (j * HASH_PRIMES[1]) ^ (k * HASH_PRIMES[2])) % rows


def block_rows(
    lo: Float[Tensor, "num_points 3"], block_map: Int[Tensor, "num_blocks"], blocks: "tuple[int, int, int]", rows: "int | None" = None
) -> "tuple[Int[Tensor, 'num_points 8'], Bool[Tensor, 'num_points 8']]":
    """Table rows of the eight vertices ``lo + (di, dj, dk)`` of a sparse level (in the order of ``_CORNERS``; ``lo``:
    whole numbers, as floats) and whether each is stored; an unstored one gets some row below ``BLOCK^3`` (its weight is
    to be zeroed). ``blocks``: blocks per axis; ``block_map``: first table row of each block, in row order (-1: not
    stored); ``rows``: the table's rows (None: not known, the sums run in float64).

    Each corner's block index and row in its block are sums of one term per axis; the eight corners' sums are small
    matrix products of the terms, not a dozen broadcast integer operations (3x slower on the CPU), and the block's first
    row is read from the map as a float and added there (integer gathers and sums of ``[N, 8]``: 2.6x slower on the CPU,
    6.3 against 2.4 ms for 75,000 points). The sums are exact for whole numbers below 2^24 in float32 where float32
    products run in full precision (:func:`_exact_float32`), else they run in float64."""
    small = rows is not None and max(block_map.numel(), rows) < 1 << 24
    dtype = torch.float32 if small and _exact_float32(lo.device) else torch.float64
    both = torch.stack([lo, lo + 1], dim=-1).to(dtype).flatten(1)  # [N, 6]: the two vertex positions per axis
    blk = torch.floor(both * (1.0 / BLOCK))  # their blocks
    select_block, select_local = _block_selection(blocks, dtype, lo.device)
    base = block_map.to(dtype).index_select(0, (blk @ select_block).long().view(-1)).view(-1, 8)
    row = torch.addmm(both @ select_local, blk, select_local, alpha=-BLOCK).add_(base)  # + the rows in their blocks
    return row.clamp_(min=0).long(), base >= 0


def _exact_float32(device: torch.device) -> bool:
    """Whether float32 matrix products on ``device`` run in full float32 precision (not TF32 or bfloat16, which
    ``torch.set_float32_matmul_precision`` or ``torch.backends.cuda.matmul.allow_tf32`` may allow)."""
    if torch.get_float32_matmul_precision() != "highest":
        return False
    return device.type != "cuda" or not torch.backends.cuda.matmul.allow_tf32


@functools.lru_cache(maxsize=64)
def _block_selection(blocks: "tuple[int, int, int]", dtype: torch.dtype, device: torch.device) -> "tuple[Tensor, Tensor]":
    """The matrices that sum :func:`block_rows`' per-axis terms (``[N, 6]``: axis-major, the two vertex positions per
    axis) into each corner's block index and into its row in its block, built once per block layout, dtype and device."""
    out = []
    for strides in ((blocks[1] * blocks[2], blocks[2], 1), (BLOCK * BLOCK, BLOCK, 1)):
        m = torch.zeros(6, 8, dtype=dtype)
        for c, corner in enumerate(_CORNERS):
            for axis in range(3):
                m[axis * 2 + corner[axis], c] = strides[axis]
        out.append(m.to(device))
    return out[0], out[1]


def block_row_reference(i: int, j: int, k: int, block_map: "list[int]", blocks: "tuple[int, int, int]") -> int:
    """The row of vertex ``(i, j, k)`` of a sparse level, one vertex at a time (-1: its block is not stored);
    ``block_map``: first table row of each block (-1: not stored)."""
    b = BLOCK
    base = block_map[((i // b) * blocks[1] + j // b) * blocks[2] + k // b]
    return -1 if base < 0 else base + ((i % b) * b + j % b) * b + k % b


def blocks_per_axis(res: "tuple[int, int, int]") -> "tuple[int, int, int]":
    """Blocks of ``BLOCK`` vertices per axis that cover a level of ``res`` vertices."""
    return tuple(-(-int(n) // BLOCK) for n in res)  # type: ignore[return-value]


def needed_blocks(
    occupied: Bool[Tensor, "rx ry rz"], resolutions: "list[tuple[int, int, int]]", dilation: int = 1
) -> "list[Bool[Tensor, 'bx by bz']]":
    """For levels of ``resolutions`` vertices over a box, the blocks that a trilinear read anywhere in the ``occupied``
    cells of a grid over the same box (dilated by ``dilation`` of its cells) reaches: a block is needed when a level
    cell touching one of its vertices overlaps such a cell. Exact, through one summed-area table of the occupancy."""
    grid = tuple(occupied.shape)
    sat = occupied.to(torch.int32)
    for axis in range(3):
        sat = sat.cumsum(axis, dtype=torch.int32)
    sat = torch.nn.functional.pad(sat, (1, 0, 1, 0, 1, 0))  # sat[i, j, k]: occupied cells in [0, i) x [0, j) x [0, k)
    out = []
    for res in resolutions:
        lo, hi = [], []
        for n, r, nb in zip(res, grid, blocks_per_axis(res)):
            first = torch.arange(nb, device=occupied.device) * BLOCK  # a block's first vertex; its cells: first - 1 .. first + BLOCK - 1
            a = (first - 1).clamp(min=0).double() / max(n - 1, 1)
            z = (first + BLOCK).clamp(max=n - 1).double() / max(n - 1, 1)
            lo.append(((a * r).floor().long() - dilation).clamp(0, r))
            hi.append(((z * r).ceil().long() + dilation).clamp(0, r))
        i0, j0, k0 = lo[0][:, None, None], lo[1][None, :, None], lo[2][None, None, :]
        i1, j1, k1 = hi[0][:, None, None], hi[1][None, :, None], hi[2][None, None, :]
        count = (
            sat[i1, j1, k1] - sat[i0, j1, k1] - sat[i1, j0, k1] - sat[i1, j1, k0]
            + sat[i0, j0, k1] + sat[i0, j1, k0] + sat[i1, j0, k0] - sat[i0, j0, k0]
        )
        out.append(count > 0)
    return out


def grid_gather(
    table: Float[Tensor, "num_cells C"], idx: Int[Tensor, "num_points 8"], w: Float[Tensor, "num_points 8"]
) -> Float[Tensor, "num_points C"]:
    """Weighted sum of eight table rows per point (differentiable in ``table`` and ``w``)."""
    return weighted_gather(table, idx, w)


def trilinear(
    table: Float[Tensor, "num_cells C"], res: "tuple[int, int, int]", x01: Float[Tensor, "num_points 3"]
) -> Float[Tensor, "num_points C"]:
    """Trilinear interpolation of a channels-last grid table at points of the unit cube."""
    idx, w = trilinear_corners(x01, res)
    return grid_gather(table, idx, w.to(table.dtype))


def axis_resolution(extent: Float[Tensor, "3"], finest: int) -> "tuple[int, int, int]":
    """Vertices per axis for a box: ``finest`` along its longest side, proportional elsewhere."""
    scale = extent / extent.max()
    return tuple(max(2, int(round(float(s) * finest))) for s in scale)


def _first_rows(flat: Bool[Tensor, "num_blocks"], headroom: float) -> "tuple[Int[Tensor, 'num_blocks'], int, int]":
    """A sparse level's block map storing the blocks ``flat`` marks, in row order (-1 for the others), how many they
    are, and the blocks a table with ``headroom`` free ones holds."""
    count = int(flat.sum())
    first = torch.full(flat.shape, -1, dtype=torch.long, device=flat.device)
    first[flat] = torch.arange(count, device=flat.device) * BLOCK**3
    return first, count, max(1, math.ceil(count * (1 + headroom)))


class DenseGridEncoding(nn.Module):
    """Several dense grids of increasing resolution over the unit cube, features concatenated.

    Coarse levels see many samples per vertex and converge in a few steps; fine levels add the
    detail (a multiresolution encoding as in instant-ngp, without hashing: every vertex is stored).
    A dense level can be made sparse (:meth:`sparsify`): only the blocks of vertices that occupied space needs stay.

    Args:
        resolutions: vertices per axis of each level.
        channels: features per vertex and level.
        init_scale: features start uniform in ``[-init_scale, init_scale]``.
        max_rows: levels with more vertices are hashed into this many rows (a power of two; None: all dense).
        dense_max: levels with at most this many vertices stay dense even above ``max_rows`` (None: ``max_rows``).
        fine_rows: hashed levels with more than ``fine_min_vertices`` vertices get this many rows instead of
            ``max_rows`` (a power of two; None: ``max_rows``).
        fine_min_vertices: see ``fine_rows``.
    """

    def __init__(
        self, resolutions: "list[tuple[int, int, int]]", channels: int, init_scale: float = 1e-4, max_rows: "int | None" = None,
        dense_max: "int | None" = None, fine_rows: "int | None" = None, fine_min_vertices: int = 2**23,
    ) -> None:
        super().__init__()
        for name, rows in (("max_rows", max_rows), ("fine_rows", fine_rows)):
            if rows is not None and (rows < 8 or rows & (rows - 1)):
                raise ValueError(f"{name} must be a power of two of at least 8, got {rows}")
        self.resolutions = [tuple(int(v) for v in r) for r in resolutions]
        self.channels = channels
        full = [r[0] * r[1] * r[2] for r in self.resolutions]
        limit = max_rows if dense_max is None or max_rows is None else max(dense_max, max_rows)
        self.hash_rows: "list[int | None]" = [
            None if max_rows is None or n <= limit else fine_rows if fine_rows is not None and n > fine_min_vertices else max_rows for n in full
        ]
        """Rows of each hashed level's table (None: the level is dense, one row per vertex)."""
        self.tables = nn.ParameterList(
            nn.Parameter(torch.empty(h or n, channels).uniform_(-init_scale, init_scale)) for n, h in zip(full, self.hash_rows)
        )
        for i in range(len(self.resolutions)):
            self.register_buffer(f"block_map_{i}", torch.zeros(0, dtype=torch.long))
            """First table row of each block of a sparse level, in row order (-1: not stored); empty for other levels."""
            self.register_buffer(f"slots_used_{i}", torch.zeros((), dtype=torch.long))
            """Slots of a sparse level's table in use (the rest are free: zeros)."""
            self.register_buffer(f"blocks_missing_{i}", torch.zeros((), dtype=torch.long), persistent=False)
            """Blocks the latest :meth:`grow` needed but found no free slot for (read as zeros)."""

    def block_map(self, level: int) -> Int[Tensor, "num_blocks"]:
        return getattr(self, f"block_map_{level}")

    def slots_used(self, level: int) -> Int[Tensor, ""]:
        """Blocks a sparse level stores (a device scalar)."""
        return getattr(self, f"slots_used_{level}")

    def blocks_missing(self, level: int) -> Int[Tensor, ""]:
        """Blocks the latest :meth:`grow` of a sparse level needed but had no free slot for (a device scalar)."""
        return getattr(self, f"blocks_missing_{level}")

    def sparse(self, level: int) -> bool:
        """Whether the level is stored in blocks (:meth:`sparsify`)."""
        return self.block_map(level).numel() > 0

    def corners(self, level: int, x01: Float[Tensor, "num_points 3"]) -> "tuple[Tensor, Tensor]":
        """:func:`trilinear_corners` of one level (hashed, dense or sparse)."""
        if self.sparse(level):
            return self._sparse_corners(level, trilinear_lo_levels(x01, (self.resolutions[level],)), 0)
        return trilinear_corners(x01, self.resolutions[level], self.hash_rows[level])

    def _sparse_corners(self, level: int, lo_w: "tuple[Tensor, Tensor]", i: int) -> "tuple[Tensor, Tensor]":
        """Rows and weights of a sparse level from row ``i`` of :func:`trilinear_lo_levels`' output (unstored corners
        weigh 0)."""
        lo, w = lo_w
        rows, stored = block_rows(lo[i], self.block_map(level), blocks_per_axis(self.resolutions[level]), self.tables[level].shape[0])
        return rows, torch.where(stored, w[i], 0.0)

    def corners_of(
        self, levels: int, x01: Float[Tensor, "num_points 3"], x_hashed: "Float[Tensor, 'num_points 3'] | None" = None
    ) -> "list[tuple[Tensor, Tensor]]":
        """:meth:`corners` of the coarsest ``levels`` levels, the dense ones at ``x01`` together, the sparse ones at
        ``x01`` together and the hashed ones at ``x_hashed`` (default ``x01``) together
        (:func:`trilinear_corners_levels`), in level order."""
        out: "list[tuple[Tensor, Tensor] | None]" = [None] * levels
        unhashed = [lv for lv in range(levels) if self.hash_rows[lv] is None]
        if any(self.sparse(lv) for lv in unhashed):  # one pass for their cells, then each layout's rows
            lo, w = trilinear_lo_levels(x01, tuple(self.resolutions[lv] for lv in unhashed))
            dense = [i for i, lv in enumerate(unhashed) if not self.sparse(lv)]
            if dense:
                pick = slice(dense[0], dense[-1] + 1) if dense == list(range(dense[0], dense[-1] + 1)) else torch.tensor(dense, device=lo.device)
                idx = dense_rows(lo[pick], tuple(self.resolutions[unhashed[i]] for i in dense))
                for j, i in enumerate(dense):
                    out[unhashed[i]] = (idx[j], w[i])
            for i, lv in enumerate(unhashed):
                if out[lv] is None:
                    out[lv] = self._sparse_corners(lv, (lo, w), i)
        for rows in dict.fromkeys(self.hash_rows[:levels]):
            group = [lv for lv in range(levels) if self.hash_rows[lv] == rows and out[lv] is None]
            if not group:
                continue
            x = x01 if rows is None or x_hashed is None else x_hashed
            idx, w = trilinear_corners_levels(x, tuple(self.resolutions[lv] for lv in group), rows)
            for i, lv in enumerate(group):
                out[lv] = (idx[i], w[i])
        return out  # type: ignore[return-value]

    @torch.no_grad()
    def sparsify(self, level: int, blocks: Bool[Tensor, "bx by bz"], headroom: float = 0.25) -> None:
        """Store a dense level in blocks: only the ``blocks`` given (:func:`needed_blocks`), their vertices' values
        kept, in a table with ``headroom`` times as many free slots (zeros) for blocks needed later (:meth:`grow`)."""
        res = self.resolutions[level]
        if self.hash_rows[level] is not None or self.sparse(level):
            raise ValueError(f"level {level} is not dense")
        nb = blocks_per_axis(res)
        if tuple(blocks.shape) != nb:
            raise ValueError(f"blocks of level {level} are {nb}, got {tuple(blocks.shape)}")
        table = self.tables[level]
        slots, count, capacity = _first_rows(blocks.reshape(-1).to(table.device), headroom)
        new = table.new_zeros(capacity * BLOCK**3, table.shape[1])
        ijk = torch.stack(torch.meshgrid(*(torch.arange(n, device=table.device) for n in res), indexing="ij"), -1).reshape(-1, 3)
        blk, loc = ijk // BLOCK, ijk % BLOCK
        first = slots[(blk[:, 0] * nb[1] + blk[:, 1]) * nb[2] + blk[:, 2]]
        keep = first >= 0
        rows = first + (loc[:, 0] * BLOCK + loc[:, 1]) * BLOCK + loc[:, 2]
        new[rows[keep]] = table.data[keep]  # the dense rows are in vertex order
        table.data = new
        setattr(self, f"block_map_{level}", slots)
        self.slots_used(level).fill_(count)

    @torch.no_grad()
    def grow(self, level: int, blocks: Bool[Tensor, "bx by bz"]) -> None:
        """Store the ``blocks`` of a sparse level that are not stored yet, in free slots, on the device (nothing is
        read back); those beyond the table's capacity stay unstored and are counted in ``blocks_missing_{level}``."""
        slots, used = self.block_map(level), self.slots_used(level)
        new = blocks.reshape(-1).to(slots.device) & (slots < 0)
        slot = used + new.cumsum(0) - 1
        ok = new & (slot < self.capacity(level))
        slots.copy_(torch.where(ok, slot * BLOCK**3, slots))
        used.add_(ok.sum())
        self.blocks_missing(level).copy_((new & ~ok).sum())

    @torch.no_grad()
    def relayout(self, level: int, blocks: Bool[Tensor, "bx by bz"], headroom: float = 0.1) -> None:
        """Store exactly the ``blocks`` given of a sparse level (blocks no longer needed are dropped, new ones start at
        zero), in a table with ``headroom`` times as many free slots. The table's parameter is marked ``row_source``
        (its former row count and, per new row, the row it was, -1 for a new one), so that the optimizer's moments and
        the parameter average move with the rows (:func:`~nerfpipe.training.trainer.drop_stale_optimizer_state`)."""
        table, slots = self.tables[level], self.block_map(level)
        flat = blocks.reshape(-1).to(slots.device)
        new_first, count, capacity = _first_rows(flat, headroom)
        local = torch.arange(BLOCK**3, device=slots.device)
        source = torch.full((capacity * BLOCK**3,), -1, dtype=torch.long, device=slots.device)
        kept = flat & (slots >= 0)
        source.view(-1, BLOCK**3)[new_first[kept] // BLOCK**3] = slots[kept, None] + local
        rows = table.shape[0]
        table.data = move_rows(table.data, source)
        table.row_source = (rows, source)
        slots.copy_(new_first)
        self.slots_used(level).fill_(count)
        self.blocks_missing(level).zero_()

    def capacity(self, level: int) -> int:
        """Blocks a sparse level's table holds."""
        return self.tables[level].shape[0] // BLOCK**3

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        """Checkpoints from before sparse levels have no block maps (every level dense); a sparse level's map and
        table take the checkpoint's sizes."""
        for i in range(len(self.resolutions)):
            key = f"{prefix}block_map_{i}"
            state_dict.setdefault(key, torch.zeros(0, dtype=torch.long))
            state_dict.setdefault(f"{prefix}slots_used_{i}", torch.zeros((), dtype=torch.long))
            if state_dict[key].shape != self.block_map(i).shape:
                setattr(self, f"block_map_{i}", torch.empty_like(state_dict[key], device=self.block_map(i).device))
            table = state_dict.get(f"{prefix}tables.{i}")
            if state_dict[key].numel() and table is not None and table.shape != self.tables[i].shape:
                self.tables[i].data = torch.empty_like(table, device=self.tables[i].device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def out_dim(self) -> int:
        return self.channels * len(self.resolutions)

    def forward(self, x01: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points F"]:
        feats = [grid_gather(t, *self.corners(i, x01)) for i, t in enumerate(self.tables)]
        return feats[0] if len(feats) == 1 else torch.cat(feats, dim=-1)

    def summed(self, x01: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points C"]:
        """The levels' values added instead of concatenated (e.g. one density channel)."""
        out = grid_gather(self.tables[0], *self.corners(0, x01))
        for i, t in enumerate(self.tables[1:], start=1):
            out = out + grid_gather(t, *self.corners(i, x01))
        return out
