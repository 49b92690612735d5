"""Weighted gathers from channels-last tables: the kernel of every grid encoding.

``out[n] = sum_k w[n, k] * table[idx[n, k]]``, with ``K`` corners per point (4 for bilinear,
8 for trilinear). On the CPU the forward is ``embedding_bag``'s weighted sum (one pass over the rows,
no ``K``-times larger intermediate: 3-6x faster than an ``index_select`` and a contraction there,
session 52); elsewhere it is an ``index_select`` and a contraction over the corners (:func:`corner_sum`).
The backward into the table (:func:`table_grad`) is a ``scatter_add_`` of each channel into its own row on the CPU
(1.6-3x faster there than ``index_add_`` of the corners' rows, session 57; one call for all channels, split between
the threads, since session 88) and one ``index_add_`` elsewhere (``embedding_bag``'s own backward sorts indices: as
fast as ``index_add_`` or up to 1.8x slower on CPU).

The backward into the weights (:func:`row_dot`) is a batched matrix product on the CPU (2-4x faster
there than a product and a sum) and a product and a sum elsewhere: on CUDA the batched product of
``1 x K`` by ``K x C`` matrices runs as cuBLAS's batched matrix-vector kernel, which took 5 of the 8
ms of GPU time of a fast training step on an H200 (session 22).
"""

import math

import torch

from nerfpipe.util.typing import Float, Int, Tensor


def corner_sum(w: Float[Tensor, "num_points K"], rows: Float[Tensor, "num_points K C"]) -> Float[Tensor, "num_points C"]:
    """``sum_k w[n, k] * rows[n, k]`` as a product and a sum (off the CPU; on CUDA the batched product of ``1 x K``
    by ``K x C`` matrices ran as cuBLAS's batched matrix-vector kernel, 5 of the 8 ms of a step on an H200)."""
    return (w[:, :, None] * rows).sum(1)


def row_dot(
    rows: Float[Tensor, "num_points K C"], v: Float[Tensor, "num_points C"], batched: bool
) -> Float[Tensor, "num_points K"]:
    """``rows[n, k] . v[n]`` for every corner: :func:`corner_sum`'s derivative in ``w``, by the same two routes."""
    if batched:
        return torch.bmm(rows, v[:, :, None])[..., 0]
    return (rows * v[:, None, :]).sum(-1)


def gather_rows_sum(
    table: Float[Tensor, "num_cells C"], idx: Int[Tensor, "num_points K"], w: Float[Tensor, "num_points K"]
) -> Float[Tensor, "num_points C"]:
    """The gather's forward, not differentiable: ``embedding_bag``'s weighted sum on the CPU, else an
    ``index_select`` and :func:`corner_sum` (the reference route, and CUDA's: its graph-captured step was measured so)."""
    if table.device.type == "cpu":  # 32-bit rows: 1.1x (a real step's rows) to 1.8x (random rows) faster (session 58)
        idx = idx.int() if idx.dtype != torch.int32 and table.shape[0] < 2**31 else idx
        return torch.nn.functional.embedding_bag(idx, table, per_sample_weights=w.to(table.dtype), mode="sum")
    n, k = idx.shape
    rows = table.index_select(0, idx.reshape(-1)).view(n, k, table.shape[1])
    return corner_sum(w, rows)


class _WeightedGather(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table, idx, w):
        ctx.save_for_backward(table, idx, w)
        return gather_rows_sum(table, idx, w)

    @staticmethod
    def backward(ctx, grad_out):
        table, idx, w = ctx.saved_tensors
        grad_table = grad_w = None
        if ctx.needs_input_grad[0]:
            grad_table = table_grad(table, idx, w, grad_out, per_channel=table.device.type == "cpu")
        if ctx.needs_input_grad[2]:
            rows = table.index_select(0, idx.reshape(-1)).view(*idx.shape, -1)
            grad_w = row_dot(rows, grad_out, table.device.type == "cpu")
        return grad_table, None, grad_w


def table_grad(
    table: Float[Tensor, "num_cells C"], idx: Int[Tensor, "num_points K"], w: Float[Tensor, "num_points K"],
    grad_out: Float[Tensor, "num_points C"], per_channel: bool,
) -> Float[Tensor, "num_cells C"]:
    """The gather's derivative in the table, ``grad[idx[n, k]] += w[n, k] * grad_out[n]``, by two routes that add in
    the same order (the same values, bit for bit, where the adds are ordered): ``per_channel``, a ``scatter_add_``
    into a vector per channel (the CPU's route: one call over a channels-first buffer, whose channels torch's threads
    share; on real steps' calls 37 against 28 ms a step of colmap_mouse, session 88), else one ``index_add_`` of the
    corners' rows (one kernel: CUDA's). On the CPU ``index_add_`` adds a matrix row as a slice, about 35 ns each, and
    a vector's elements in a tight loop: on two cores, 552,000 corner reads into 4 channels of 2^20 / 2^19 / 124,800 /
    16,000 rows took 28.8 / 25.4 / 8.1 / 6.8 ms against 17.9 / 7.9 / 3.4 / 2.5 (a weighted ``bincount`` per channel was
    11.4 / 7.4 / 4.1 / 3.3, but its output's size is read from the data: a host sync on CUDA, and in the CPU's count
    of them)."""
    flat = idx.reshape(-1)
    if per_channel:
        rows, channels = table.shape
        flat, w = flat.long(), w.to(grad_out.dtype)
        if channels == 1:
            return table.new_zeros(rows).scatter_add_(0, flat, (w * grad_out).view(-1)).view(rows, 1)
        # channel c's adds in row c, written as the product is computed: into a buffer of that layout (a product of a
        # contiguous transposed grad_out, the same values, took 2x as long: its transposing copy, session 58)
        values = torch.mul(grad_out.t()[:, :, None], w, out=w.new_empty(channels, *w.shape)).view(channels, -1)
        # one scatter along the rows of a channels-first buffer: its lines (channels) are split between the threads,
        # each channel's adds in order; then stacked channels-last (stack writes the interleaved rows 5x faster than a
        # transposing copy_: 1.6 against 8.8 ms for 4 x 2^19; session 88)
        out = table.new_zeros(channels, rows).scatter_add_(1, flat.expand(channels, -1), values)
        return torch.stack(out.unbind(0), dim=1)
    contrib = (w[:, :, None] * grad_out[:, None, :]).reshape(-1, table.shape[1])
    return torch.zeros_like(table).index_add_(0, flat, contrib)


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


def move_rows(old: Tensor, source: Int[Tensor, "num_new"], fill: "Tensor | None" = None) -> Tensor:
    """A table re-laid out: new row ``i`` is ``old``'s row ``source[i]``, or ``fill``'s row ``i`` (default zeros) where
    ``source[i]`` is -1.

    Example:
        >>> move_rows(torch.tensor([[1.0], [2.0]]), torch.tensor([1, -1, 0])).tolist()
        [[2.0], [0.0], [1.0]]
    """
    taken = old.index_select(0, source.clamp(min=0).to(old.device))
    new = (source < 0).to(old.device).view(-1, *([1] * (old.ndim - 1)))
    return torch.where(new, torch.zeros_like(taken) if fill is None else fill, taken)


def equirect_lookup(
    textures: "Float[Tensor, 'rows cols C'] | Float[Tensor, 'num_textures rows cols C']", directions: Float[Tensor, "num_rays 3"],
    texture_index: "Int[Tensor, 'num_rays'] | None" = None, polar_max: float = math.pi,
) -> Float[Tensor, "num_rays C"]:
    """Bilinear reads of equirectangular textures over the sphere of directions about the z axis (row 0 at +z,
    column 0 at azimuth -pi; texel centres at half steps, edge texels held beyond them), differentiable in the
    textures: one texture, or ``textures[texture_index[n]]`` for ray ``n``. The rows span the polar angles from 0 to
    ``polar_max`` (pi: the whole sphere; pi / 2: the upper hemisphere, the last row held below it).
    :func:`equirect_lookup_reference` reads one direction at a time.

    Example:
        >>> t = torch.arange(8.0).reshape(2, 4, 1)  # two rows, four columns
        >>> equirect_lookup(t, torch.tensor([[0.0, 0.0, 1.0]])).tolist()  # straight up: the first row, azimuth 0
        [[1.5]]
    """
    rows, cols, channels = textures.shape[-3:]
    table = textures.reshape(-1, channels)
    d = directions
    u = (torch.atan2(d[:, 1], d[:, 0]) / (2 * math.pi) + 0.5) * cols - 0.5
    v = torch.acos(d[:, 2].clamp(-1.0, 1.0)) / polar_max * rows - 0.5
    u0, v0 = u.detach().floor().clamp(0, cols - 2), v.detach().floor().clamp(0, rows - 2)
    fu, fv = (u - u0).clamp(0, 1), (v - v0).clamp(0, 1)
    base = v0.long() * cols + u0.long()
    if texture_index is not None:
        base = base + texture_index.long() * (rows * cols)
    idx = torch.stack([base, base + 1, base + cols, base + cols + 1], dim=-1)
    w = torch.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], dim=-1).detach()
    return weighted_gather(table, idx, w.to(table.dtype))


def equirect_lookup_reference(texture: Float[Tensor, "rows cols C"], direction: "tuple[float, float, float]", polar_max: float = math.pi) -> Float[Tensor, "C"]:
    """:func:`equirect_lookup` of one texture at one direction, written out (the slow, obvious reference)."""
    rows, cols = texture.shape[:2]
    x, y, z = direction
    u = (math.atan2(y, x) / (2 * math.pi) + 0.5) * cols - 0.5
    v = math.acos(max(-1.0, min(1.0, z))) / polar_max * rows - 0.5
    u = min(max(u, 0.0), cols - 1.0)
    v = min(max(v, 0.0), rows - 1.0)
    i, j = min(int(math.floor(v)), rows - 2), min(int(math.floor(u)), cols - 2)
    fv, fu = v - i, u - j
    return ((1 - fv) * ((1 - fu) * texture[i, j] + fu * texture[i, j + 1])
            + fv * ((1 - fu) * texture[i + 1, j] + fu * texture[i + 1, j + 1]))
