"""Connected components of a 3D boolean grid, on the device (label propagation by max-pooling)."""

import torch
from torch.nn import functional as F

from nerfpipe.util.typing import Bool, Int, Tensor


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
    labels = torch.where(mask.reshape(-1), torch.arange(1, n + 1, device=mask.device, dtype=torch.float32), 0.0)
    labels = labels.view(1, 1, *mask.shape)
    keep = mask.view(1, 1, *mask.shape)
    while True:
        before = labels
        for _ in range(check_every):
            labels = torch.where(keep, F.max_pool3d(labels, 3, stride=1, padding=1), 0.0)
        if torch.equal(labels, before):
            return labels.view(mask.shape).long()
