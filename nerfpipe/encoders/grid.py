"""Multiresolution dense/hash grid encoder (Instant-NGP style) for any input dimension D.

Glossary:
    x         coordinates ``[*bs, D]`` in ``[0, 1]^D`` (clamped)
    level     one grid of ``R`` cells per axis, i.e. ``(R+1)^D`` vertices, each holding F features
    dense     a level whose ``(R+1)^D`` vertices fit in the table: vertex index = row-major position
    hashed    a larger level: vertex index = XOR of ``coord_d · prime_d`` modulo ``2^log2_hashmap_size``
    corners   the ``2^D`` vertices of the cell around a point; (multi)linear weights sum to 1

Implementation: all levels share one channels-last table ``[num_vertices, F]``; a single
:func:`nerfpipe.functional.gather.weighted_gather` gathers the ``2^D`` corners of every level and
sums them with their interpolation weights (about 3x faster than ``grid_sample`` on CPU, and it
handles hashed levels). Gradients flow to the table and to ``x`` (through the weights).
:meth:`GridEncoder._reference_forward` is the slow, obvious per-level, per-corner reference.
"""

import itertools
import math
from dataclasses import dataclass

import torch
from torch import nn

from nerfpipe.functional.gather import weighted_gather
from nerfpipe.util.typing import Float, Int, Tensor

# Instant-NGP's per-dimension hashing primes (the first is 1 for cache coherence).
_PRIMES = (1, 2654435761, 805459861, 3674653429, 2097192037, 1434869437, 2165219737)


@dataclass
class GridEncoderConfig:
    """Multiresolution grid of learned features, dense where it fits and hashed above that."""

    num_levels: int = 8
    """Number of resolutions, spaced geometrically from ``base_resolution`` to ``max_resolution``."""
    features_per_level: int = 2
    """F: features stored per vertex and level."""
    base_resolution: int = 16
    """Cells per axis of the coarsest level."""
    max_resolution: int = 512
    """Cells per axis of the finest level (the image size is a sensible choice)."""
    log2_hashmap_size: int = 16
    """Levels with more than ``2^this`` vertices are hashed into ``2^this`` rows."""
    init_scale: float = 1e-4
    """Features start uniform in ``[-init_scale, init_scale]``."""

    def setup(self, in_dim: int) -> "GridEncoder":
        return GridEncoder(self, in_dim)

    def resolutions(self) -> "list[int]":
        if self.num_levels == 1:
            return [self.max_resolution]
        growth = math.exp(math.log(self.max_resolution / self.base_resolution) / (self.num_levels - 1))
        return [int(round(self.base_resolution * growth**lvl)) for lvl in range(self.num_levels)]


class GridEncoder(nn.Module):
    """``[*bs, D] -> [*bs, num_levels·F]``: interpolated features of every level, coarse first."""

    def __init__(self, config: GridEncoderConfig, in_dim: int) -> None:
        super().__init__()
        if in_dim > len(_PRIMES):
            raise ValueError(f"grid encoder supports up to {len(_PRIMES)} dimensions, got {in_dim}")
        self.config, self.in_dim = config, in_dim
        self.out_dim = config.num_levels * config.features_per_level
        res = torch.tensor(config.resolutions(), dtype=torch.long)
        full = (res + 1) ** in_dim
        cap = 2**config.log2_hashmap_size
        sizes = torch.minimum(full, torch.tensor(cap))
        self.register_buffer("resolution", res, persistent=False)
        self.register_buffer("hashed", full > cap, persistent=False)
        self.register_buffer("size", sizes, persistent=False)
        self.register_buffer("offset", torch.cumsum(sizes, 0) - sizes, persistent=False)
        self.register_buffer("stride", (res[:, None] + 1) ** torch.arange(in_dim), persistent=False)
        self.register_buffer("primes", torch.tensor(_PRIMES[:in_dim], dtype=torch.long), persistent=False)
        table = torch.empty(int(sizes.sum()), config.features_per_level)
        self.table = nn.Parameter(table.uniform_(-config.init_scale, config.init_scale))

    def forward(self, x: Float[Tensor, "*bs D"]) -> Float[Tensor, "*bs E"]:
        batch_shape = x.shape[:-1]
        idx, w = self.corners(x.reshape(-1, self.in_dim))
        return self.interpolate(idx, w).reshape(*batch_shape, self.out_dim)

    def interpolate(self, idx: Int[Tensor, "N levels C"], w: Float[Tensor, "N levels C"]) -> Float[Tensor, "N E"]:
        """Features from precomputed :meth:`corners` (cache them when the points never move)."""
        n, levels, n_corners = idx.shape
        out = weighted_gather(self.table, idx.reshape(-1, n_corners), w.reshape(-1, n_corners).to(self.table))
        return out.reshape(n, levels * self.config.features_per_level)

    def corners(self, x: Float[Tensor, "N D"]) -> tuple[Int[Tensor, "N levels C"], Float[Tensor, "N levels C"]]:
        """Table rows and (multi)linear weights of the ``C = 2^D`` cell corners at every level.

        Per-dimension terms (``[N, levels, 2, D]``) are combined dimension by dimension, so the
        full ``[N, levels, C, D]`` corner coordinates are never materialised.
        """
        pos = x.clamp(0.0, 1.0)[:, None, :] * self.resolution[:, None].to(x.dtype)  # [N, levels, D]
        cell = torch.minimum(pos.detach().floor().long(), self.resolution[:, None] - 1)
        frac = pos - cell.to(x.dtype)
        vert = cell[:, :, None, :] + torch.arange(2, device=x.device)[:, None]  # [N, levels, 2, D]
        dense_t, hash_t = vert * self.stride[:, None, :], vert * self.primes
        weight_t = torch.stack([1.0 - frac, frac], dim=-2)
        dense, hashed, w = dense_t[..., 0], hash_t[..., 0], weight_t[..., 0]
        for d in range(1, self.in_dim):
            dense = (dense[..., :, None] + dense_t[..., None, :, d]).flatten(-2)
            hashed = torch.bitwise_xor(hashed[..., :, None], hash_t[..., None, :, d]).flatten(-2)
            w = (w[..., :, None] * weight_t[..., None, :, d]).flatten(-2)
        hashed = torch.bitwise_and(hashed, self.size[:, None] - 1)  # hashed levels have 2^k rows
        rows = torch.where(self.hashed[:, None], hashed, dense) + self.offset[:, None]
        return rows, w

    def _reference_forward(self, x: Float[Tensor, "N D"]) -> Float[Tensor, "N E"]:
        """Slow reference: per level, per corner, explicit vertex index and weight products."""
        out = []
        for lvl in range(self.config.num_levels):
            res = int(self.resolution[lvl])
            pos = x.clamp(0.0, 1.0) * res
            cell = pos.detach().floor().clamp(max=res - 1)
            acc = torch.zeros(x.shape[0], self.config.features_per_level, dtype=self.table.dtype)
            for bits in itertools.product((0, 1), repeat=self.in_dim):
                weight = torch.ones(x.shape[0], dtype=x.dtype)
                vertex = []
                for d, b in enumerate(bits):
                    f = pos[:, d] - cell[:, d]
                    weight = weight * (f if b else 1 - f)
                    vertex.append(cell[:, d].long() + b)
                acc = acc + weight[:, None] * self.table[self._reference_row(lvl, vertex)]
            out.append(acc)
        return torch.cat(out, dim=-1)

    def _reference_row(self, lvl: int, vertex: "list[Tensor]") -> Tensor:
        res, size = int(self.resolution[lvl]), int(self.size[lvl])
        if bool(self.hashed[lvl]):
            h = vertex[0] * _PRIMES[0]
            for d in range(1, len(vertex)):
                h = h ^ (vertex[d] * _PRIMES[d])
            row = h % size
        else:
            row = sum(v * (res + 1) ** d for d, v in enumerate(vertex))
        return row + int(self.offset[lvl])

    def describe(self) -> dict:
        return {
            "type": "grid",
            "resolutions": self.resolution.tolist(),
            "hashed_levels": int(self.hashed.sum()),
            "features_per_level": self.config.features_per_level,
            "table_rows": int(self.size.sum()),
        }


