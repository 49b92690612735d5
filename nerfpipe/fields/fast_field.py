"""A radiance field of dense multiresolution grids and a small colour MLP, fast on CPU.

Density is one channel per grid level, the levels summed and then activated (``softplus`` after
interpolation, as in DVGO, so surfaces can be sharper than a voxel). Colour comes from
feature grids at the same levels, concatenated with an encoding of the viewing direction and
decoded by a two-layer MLP.

Glossary:
    x01   points mapped from the scene box to the unit cube
    raw   density before activation
"""

import functools
import math

import torch
from torch import nn

from nerfpipe.fields.grid import DenseGridEncoding, grid_gather
from nerfpipe.util.typing import Float, Tensor


# Real spherical harmonics of degree <= 3 as polynomials in (x, y, z): per basis function, its terms as
# (coefficient, the monomial's factors among 0 = 1, 1 = x, 2 = y, 3 = z, three of them)
_SH_TERMS = (
    ((0.28209479177387814, (0, 0, 0)),),
    ((-0.48860251190291987, (0, 0, 2)),),
    ((0.48860251190291987, (0, 0, 3)),),
    ((-0.48860251190291987, (0, 0, 1)),),
    ((1.0925484305920792, (0, 1, 2)),),
    ((-1.0925484305920792, (0, 2, 3)),),
    ((0.94617469575755997, (0, 3, 3)), (-0.31539156525251999, (0, 0, 0))),
    ((-1.0925484305920792, (0, 1, 3)),),
    ((0.54627421529603959, (0, 1, 1)), (-0.54627421529603959, (0, 2, 2))),
    ((-3 * 0.59004358992664352, (1, 1, 2)), (0.59004358992664352, (2, 2, 2))),
    ((2.8906114426405538, (1, 2, 3)),),
    ((0.45704579946446572, (0, 0, 2)), (-5 * 0.45704579946446572, (2, 3, 3))),
    ((5 * 0.3731763325901154, (3, 3, 3)), (-3 * 0.3731763325901154, (0, 0, 3))),
    ((0.45704579946446572, (0, 0, 1)), (-5 * 0.45704579946446572, (1, 3, 3))),
    ((1.4453057213202769, (1, 1, 3)), (-1.4453057213202769, (2, 2, 3))),
    ((-0.59004358992664352, (1, 1, 1)), (3 * 0.59004358992664352, (1, 2, 2))),
)


@functools.lru_cache(maxsize=16)
def _sh_matrix(dtype: torch.dtype, device: torch.device) -> Float[Tensor, "64 16"]:
    """The basis functions' coefficients over the 64 products ``m_a m_b m_c`` of ``m = (1, x, y, z)`` (built once)."""
    out = torch.zeros(64, 16, dtype=torch.float64)
    for j, terms in enumerate(_SH_TERMS):
        for coef, (a, b, c) in terms:
            out[a * 16 + b * 4 + c, j] += coef
    return out.to(dtype=dtype, device=device)


def direction_encoding(d: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 16"]:
    """Real spherical harmonics of degree <= 3 of unit directions (instant-ngp's colour input), as one product
    of the monomials of degree <= 3 with a constant matrix: a handful of tensor operations (each a kernel launch
    on a GPU) instead of one per term. :func:`direction_encoding_reference` writes the functions out."""
    m = nn.functional.pad(d, (1, 0), value=1.0)  # [N, 4]: 1, x, y, z
    cubic = (m[:, :, None, None] * m[:, None, :, None] * m[:, None, None, :]).reshape(-1, 64)
    return cubic @ _sh_matrix(d.dtype, d.device)


def direction_encoding_reference(d: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 16"]:
    """:func:`direction_encoding`, each basis function written out (the slow, obvious reference)."""
    x, y, z = d.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    return torch.stack(
        [
            torch.full_like(x, 0.28209479177387814),
            -0.48860251190291987 * y,
            0.48860251190291987 * z,
            -0.48860251190291987 * x,
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * x * z,
            0.54627421529603959 * (xx - yy),
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * x * y * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ],
        dim=-1,
    )


class FastField(nn.Module):
    """Density and view-dependent colour from dense grids over ``aabb``.

    Args:
        aabb: scene box ``[min, max]``.
        resolutions: vertices per axis of each grid level (shared by density and features).
        feature_channels: colour features per vertex and level.
        hidden: width of the colour MLP.
        init_density: density everywhere at the start (sets the activation shift).
        max_rows: levels with more vertices are hashed into tables of this many rows (None: all dense).
        dense_max: levels with at most this many vertices stay dense even above ``max_rows`` (None: ``max_rows``).
        fine_rows: rows of the hashed levels of more than ``fine_min_vertices`` vertices (None: ``max_rows``).
            Hashed levels live on the lattice of the box the field was built in (``lattice``), which
            tightening the box leaves alone: only the dense levels are resampled to the new box.
    """

    def __init__(
        self,
        aabb: Float[Tensor, "2 3"],
        resolutions: "list[tuple[int, int, int]]",
        feature_channels: int = 4,
        hidden: int = 64,
        init_density: float = 0.1,
        max_rows: "int | None" = None,
        dense_max: "int | None" = None,
        fine_rows: "int | None" = None,
        fine_min_vertices: int = 2**23,
    ) -> None:
        super().__init__()
        self.register_buffer("aabb", aabb.detach().clone().float())
        self.register_buffer("lattice", aabb.detach().clone().float())
        rows = dict(max_rows=max_rows, dense_max=dense_max, fine_rows=fine_rows, fine_min_vertices=fine_min_vertices)
        self.density_grid = DenseGridEncoding(resolutions, 1, init_scale=0.0, **rows)
        self.feature_grid = DenseGridEncoding(resolutions, feature_channels, **rows)
        self.shift = math.log(math.expm1(init_density))
        self.active_levels = len(resolutions)
        """Levels in use (coarse-to-fine training switches finer ones on later; inactive read as 0)."""
        self.density_levels = len(resolutions)
        """Density is the sum of the coarsest this many levels (colour reads every active level)."""
        self._voxel_sizes: "dict[tuple, float]" = {}
        self.mlp = nn.Sequential(
            nn.Linear(self.feature_grid.out_dim + 16, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, 3),
        )

    def normalize(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 3"]:
        return (points - self.aabb[0]) / (self.aabb[1] - self.aabb[0])

    def hashed(self, level: int) -> bool:
        return self.density_grid.hash_rows[level] is not None

    def corners(self, points: Float[Tensor, "num_points 3"], levels: "int | None" = None) -> list:
        """Trilinear corners of every active level (shared by the density and feature reads), or of the coarsest
        ``levels`` of them."""
        n = self.active_levels if levels is None else min(levels, self.active_levels)
        x_lat = (points - self.lattice[0]) / (self.lattice[1] - self.lattice[0]) if any(map(self.hashed, range(n))) else None
        return self.density_grid.corners_of(n, self.normalize(points), x_lat)

    def voxel_size(self, level: int) -> float:
        """Smallest vertex spacing of a level, in scene units (read from the box once per box: it is asked
        for on every training step, and each read is a host sync on CUDA)."""
        box = self.lattice if self.hashed(level) else self.aabb
        res = self.density_grid.resolutions[level]
        key = (level, res, box.data_ptr(), box._version)
        if key not in self._voxel_sizes:  # a new box: tightened or loaded (a few times per run)
            host = box.detach().cpu()
            self._voxel_sizes[key] = float(((host[1] - host[0]) / (torch.tensor(res, dtype=host.dtype) - 1)).min())
        return self._voxel_sizes[key]

    def density_from_corners(self, corners: list) -> Float[Tensor, "num_points"]:
        raw = None
        for table, (idx, w) in zip(self.density_grid.tables, corners[: self.density_levels]):
            v = grid_gather(table, idx, w)
            raw = v if raw is None else raw + v
        return nn.functional.softplus(raw[:, 0] + self.shift)

    def rgb_from_corners(self, corners: list, dir_code: Float[Tensor, "num_points 16"]) -> Float[Tensor, "num_points 3"]:
        """Colour from precomputed corners and :func:`direction_encoding` of the viewing directions."""
        feats = [grid_gather(t, idx, w) for t, (idx, w) in zip(self.feature_grid.tables, corners)]
        missing = self.feature_grid.out_dim - self.feature_grid.channels * len(feats)
        if missing:
            feats.append(dir_code.new_zeros(dir_code.shape[0], missing))
        h = torch.cat(feats + [dir_code], dim=-1)
        return torch.sigmoid(self.mlp(h))

    def density(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points"]:
        return self.density_from_corners(self.corners(points, self.density_levels))

    def rgb(self, points: Float[Tensor, "num_points 3"], directions: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 3"]:
        return self.rgb_from_corners(self.corners(points), direction_encoding(directions))

    def density_tv(self, num_cells: int, generator: "torch.Generator | None" = None) -> Float[Tensor, ""]:
        """Total variation of the finest dense density level on ``num_cells`` random vertices."""
        level = max(i for i in range(len(self.density_grid.tables)) if not self.hashed(i) and not self.density_grid.sparse(i))
        table, res = self.density_grid.tables[level], self.density_grid.resolutions[level]
        ijk = torch.stack([torch.randint(0, r - 1, (num_cells,), device=table.device, generator=generator) for r in res], dim=-1)
        row = (ijk[:, 0] * res[1] + ijk[:, 1]) * res[2] + ijk[:, 2]
        v = table[row]
        steps = (res[1] * res[2], res[2], 1)
        return sum(((table[row + s] - v) ** 2).mean() for s in steps)
