"""Dense voxel grids stored channels-last and read by trilinear interpolation (pure torch).

A grid of resolution ``(rx, ry, rz)`` has one vertex per integer position, vertex ``(i, j, k)``
at normalised coordinate ``(i / (rx - 1), j / (ry - 1), k / (rz - 1))`` in the unit cube
(``align_corners=True``). Its values live in a table ``[rx * ry * rz, C]`` with row
``(i * ry + j) * rz + k``, so one trilinear read is eight row gathers (``index_select``) and a
weighted sum. On CPU this is about 3x faster than ``grid_sample`` on ``[C, rz, ry, rx]`` volumes
for a dozen channels, and the backward pass is a single ``index_add_``.

A level with more vertices than its table has rows is *hashed* (instant-ngp): vertex ``(i, j, k)`` is
stored in row ``(i·p_i XOR j·p_j XOR k) mod rows`` of a table of ``rows`` (a power of two) rows, so memory
is set by the table, not by the resolution; neighbours along the last axis stay in adjacent rows
(its prime is 1), as in the dense layout.

Glossary:
    x01     points in the unit cube ``[0, 1]^3`` (the scene box mapped to it)
    res     vertices per axis ``(rx, ry, rz)``
    idx     ``[N, 8]`` table rows of the eight corners around each point
    w       ``[N, 8]`` trilinear weights of those corners (sum to 1)
"""

import functools

import torch
from torch import nn

from nerfpipe.functional.gather import weighted_gather
from nerfpipe.util.typing import Float, Int, Tensor

# corner offsets (di, dj, dk) in the order of the eight trilinear weights
_CORNERS = ((0, 0, 0), (0, 0, 1), (0, 1, 0), (0, 1, 1), (1, 0, 0), (1, 0, 1), (1, 1, 0), (1, 1, 1))


# hashing primes per axis (instant-ngp's; the last axis gets 1 so that its neighbours share cache lines)
HASH_PRIMES = (2654435761, 805459861, 1)


@functools.lru_cache(maxsize=256)
def _level_constants(
    resolutions: "tuple[tuple[int, int, int], ...]", dtype: torch.dtype, device: torch.device
) -> "tuple[Tensor, Tensor, Tensor, Tensor, Tensor]":
    """The constant tensors of the corner computation of some levels (``[L, 1, ...]``: a level per row), built once
    per resolutions, dtype and device (built on every call, each would be a blocking host-to-device copy on CUDA):
    the last vertex index per axis, the last cell's lower corner, the dense layout's row strides and corner
    offsets, and the hashing primes."""
    size = torch.tensor(resolutions, dtype=dtype, device=device)[:, None, :] - 1
    strides = torch.tensor([[ry * rz, rz, 1] for _, ry, rz in resolutions], device=device)[:, None, :]
    offsets = torch.tensor([[(di * ry + dj) * rz + dk for di, dj, dk in _CORNERS] for _, ry, rz in resolutions], device=device)[:, None, :]
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
    size, last, strides, offsets, primes = _level_constants(tuple(tuple(r) for r in resolutions), x01.dtype, x01.device)
    pos = x01.clamp(0.0, 1.0) * size  # [L, N, 3]
    lo = torch.minimum(pos.floor(), last)
    frac = pos - lo
    w1 = torch.stack([1 - frac, frac], dim=-1)  # [L, N, 3, 2]
    w = (w1[..., 0, :, None, None] * w1[..., 1, None, :, None] * w1[..., 2, None, None, :]).flatten(-3)
    if rows is not None:
        return hashed_rows(lo.long(), rows, primes), w
    base = (lo.long() * strides).sum(-1)
    return base[..., None] + offsets, w


def hashed_rows(lo: Int[Tensor, "*bs 3"], rows: int, primes: "Int[Tensor, '3'] | None" = None) -> Int[Tensor, "*bs 8"]:
    """Hashed table rows of the eight vertices ``lo + (di, dj, dk)`` (in the order of ``_CORNERS``);
    ``primes``: :data:`HASH_PRIMES` as a tensor on ``lo``'s device (default: built here)."""
    if primes is None:
        primes = torch.tensor(HASH_PRIMES, device=lo.device)
    terms = torch.stack([lo, lo + 1], dim=-1) * primes[:, None]  # [*bs, 3, 2]
    h = terms[..., 0, :, None, None] ^ terms[..., 1, None, :, None] ^ terms[..., 2, None, None, :]
    return h.flatten(-3) & (rows - 1)


def hashed_row_reference(i: int, j: int, k: int, rows: int) -> int:
    """The row of vertex ``(i, j, k)`` of a hashed level, one vertex at a time (the reference)."""
    return ((i * HASH_PRIMES[0]) ^ (j * HASH_PRIMES[1]) ^ (k * HASH_PRIMES[2])) % rows


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


class DenseGridEncoding(nn.Module):
    """Several dense grids of increasing resolution over the unit cube, features concatenated.

    Coarse levels see many samples per vertex and converge in a few steps; fine levels add the
    detail (a multiresolution encoding as in instant-ngp, without hashing: every vertex is stored).

    Args:
        resolutions: vertices per axis of each level.
        channels: features per vertex and level.
        init_scale: features start uniform in ``[-init_scale, init_scale]``.
        max_rows: levels with more vertices are hashed into this many rows (a power of two; None: all dense).
    """

    def __init__(
        self, resolutions: "list[tuple[int, int, int]]", channels: int, init_scale: float = 1e-4, max_rows: "int | None" = None
    ) -> None:
        super().__init__()
        if max_rows is not None and (max_rows < 8 or max_rows & (max_rows - 1)):
            raise ValueError(f"max_rows must be a power of two of at least 8, got {max_rows}")
        self.resolutions = [tuple(int(v) for v in r) for r in resolutions]
        self.channels = channels
        full = [r[0] * r[1] * r[2] for r in self.resolutions]
        self.hash_rows: "list[int | None]" = [max_rows if max_rows is not None and n > max_rows else None for n in full]
        """Rows of each hashed level's table (None: the level is dense, one row per vertex)."""
        self.tables = nn.ParameterList(
            nn.Parameter(torch.empty(h or n, channels).uniform_(-init_scale, init_scale)) for n, h in zip(full, self.hash_rows)
        )

    def corners(self, level: int, x01: Float[Tensor, "num_points 3"]) -> "tuple[Tensor, Tensor]":
        """:func:`trilinear_corners` of one level (hashed or dense)."""
        return trilinear_corners(x01, self.resolutions[level], self.hash_rows[level])

    def corners_of(
        self, levels: int, x01: Float[Tensor, "num_points 3"], x_hashed: "Float[Tensor, 'num_points 3'] | None" = None
    ) -> "list[tuple[Tensor, Tensor]]":
        """:meth:`corners` of the coarsest ``levels`` levels, the dense ones at ``x01`` together and the hashed ones
        at ``x_hashed`` (default ``x01``) together (:func:`trilinear_corners_levels`), in level order."""
        out: "list[tuple[Tensor, Tensor] | None]" = [None] * levels
        for rows in dict.fromkeys(self.hash_rows[:levels]):
            group = [lv for lv in range(levels) if self.hash_rows[lv] == rows]
            x = x01 if rows is None or x_hashed is None else x_hashed
            idx, w = trilinear_corners_levels(x, tuple(self.resolutions[lv] for lv in group), rows)
            for i, lv in enumerate(group):
                out[lv] = (idx[i], w[i])
        return out  # type: ignore[return-value]

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
