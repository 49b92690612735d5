"""Weighted gathers from channels-last tables: the kernel of every grid encoding.

``out[n] = sum_k w[n, k] * table[idx[n, k]]``, with ``K`` corners per point (4 for bilinear,
8 for trilinear). The forward is one ``index_select`` and a batched product; the backward into
the table is a single ``index_add_`` (``embedding_bag``'s own backward sorts indices and is
several times slower on CPU).
"""

import torch

from nerfpipe.util.typing import Float, Int, Tensor


class _WeightedGather(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table, idx, w):
        n, k = idx.shape
        rows = table.index_select(0, idx.reshape(-1)).view(n, k, table.shape[1])
        ctx.save_for_backward(table, idx, w)
        return torch.bmm(w[:, None, :], rows)[:, 0]

    @staticmethod
    def backward(ctx, grad_out):
        table, idx, w = ctx.saved_tensors
        grad_table = grad_w = None
        if ctx.needs_input_grad[0]:
            contrib = (w[:, :, None] * grad_out[:, None, :]).reshape(-1, table.shape[1])
            grad_table = torch.zeros_like(table).index_add_(0, idx.reshape(-1), contrib)
        if ctx.needs_input_grad[2]:
            rows = table.index_select(0, idx.reshape(-1)).view(*idx.shape, -1)
            grad_w = torch.bmm(rows, grad_out[:, :, None])[..., 0]
        return grad_table, None, grad_w


def weighted_gather(
    table: Float[Tensor, "num_cells C"], idx: Int[Tensor, "num_points K"], w: Float[Tensor, "num_points K"]
) -> Float[Tensor, "num_points C"]:
    """Weighted sum of ``K`` table rows per point, differentiable in ``table`` and ``w``.

    Example:
        >>> t = torch.arange(6.0).reshape(3, 2)
        >>> weighted_gather(t, torch.tensor([[0, 2]]), torch.tensor([[0.5, 0.5]])).tolist()
        [[2.0, 3.0]]
    """
    return _WeightedGather.apply(table, idx, w)
