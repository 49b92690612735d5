"""Volume rendering over packed (ragged) samples: every ray has its own number of samples.

Samples of all rays are stored back to back in flat tensors, sorted by ray, with
``ray_indices[i]`` the ray sample ``i`` belongs to (nerfacc's packed layout). No padding, so
the cost follows the samples that exist, not the longest ray.

Glossary:
    ray_indices  ``[num_samples]`` int64, non-decreasing: the ray of each sample
    num_rays     number of rays (rays without samples render as background)
    sigma, delta, alpha, T, weight   as in :mod:`nerfpipe.functional.volrend`

Stability: the thicknesses and weights are the dense renderer's
(:func:`~nerfpipe.functional.volrend.optical_thickness`, :func:`~nerfpipe.functional.volrend.weights_from_thickness`). The exclusive
cumulative sum within each ray is a global cumulative sum in float64 minus its value at the
ray's first sample, so long packed batches keep full float32 accuracy per ray.
"""

import torch

from nerfpipe.functional.volrend import optical_thickness, weights_from_thickness
from nerfpipe.util.typing import Bool, Float, Int, Tensor


def pack_static(mask: Bool[Tensor, "n"], capacity: int, fill: int = 0) -> "tuple[Int[Tensor, 'capacity'], Int[Tensor, ''], Bool[Tensor, 'capacity']]":
    """The positions of ``mask``'s true entries, in order, in exactly ``capacity`` slots: ``nonzero`` with a size known
    on the host, so nothing is read back (what ``torch.nonzero_static`` does, in a cumulative sum and a scatter that
    every device and a CUDA graph can run).

    Returns:
        ``(positions, count, padding)``: the first ``capacity`` true positions, the unused slots at the end holding
        ``fill``; how many entries were true (more than ``capacity``: the later ones are dropped); which slots are
        padding.

    Example:
        >>> pos, count, pad = pack_static(torch.tensor([False, True, True, False, True]), 4, fill=9)
        >>> pos.tolist(), int(count), pad.tolist()
        ([1, 2, 4, 9], 3, [False, False, False, True])
    """
    rank = torch.cumsum(mask, 0)  # 1-based rank of each true entry
    count = mask.sum()
    every = torch.arange(mask.shape[0], device=mask.device)
    # the others into slots cut off below (spread over _DUMP_SLOTS of them: millions of writes to one address serialise)
    slot = torch.where(mask & (rank <= capacity), rank - 1, capacity + (every & (_DUMP_SLOTS - 1)))
    out = torch.full((capacity + _DUMP_SLOTS,), fill, dtype=torch.long, device=mask.device)
    out.scatter_(0, slot, every)
    return out[:capacity], count, torch.arange(capacity, device=mask.device) >= count


_DUMP_SLOTS = 1024


def segment_starts(ray_indices: Int[Tensor, "num_samples"]) -> Int[Tensor, "num_samples"]:
    """For each sample, the position of the first sample of its ray (``ray_indices`` sorted)."""
    n = ray_indices.shape[0]
    pos = torch.arange(n, device=ray_indices.device)
    is_start = torch.ones(n, dtype=torch.bool, device=ray_indices.device)
    if n > 1:
        is_start[1:] = ray_indices[1:] != ray_indices[:-1]
    return torch.cummax(torch.where(is_start, pos, torch.zeros_like(pos)), dim=0).values


def exclusive_segment_cumsum(
    values: Float[Tensor, "num_samples"], ray_indices: Int[Tensor, "num_samples"]
) -> Float[Tensor, "num_samples"]:
    """``out[i] = sum of values[j]`` over earlier samples ``j < i`` of the same ray (float64 inside).

    The ray's start is read with ``index_select``, whose backward is ``index_add_``: advanced indexing's backward on
    CUDA sorts the indices and adds each run of equal ones in one thread, and every sample of a ray (every padding
    slot of a fixed-shape buffer too) reads the same start: 27 % of an H200's step (session 58)."""
    v = values.double()
    excl = torch.cumsum(v, dim=0) - v
    return (excl - excl.index_select(0, segment_starts(ray_indices))).to(values.dtype)


def render_weights_packed(
    sigmas: Float[Tensor, "num_samples"],
    deltas: Float[Tensor, "num_samples"],
    ray_indices: Int[Tensor, "num_samples"],
) -> "tuple[Float[Tensor, 'num_samples'], Float[Tensor, 'num_samples']]":
    """Compositing weights and transmittance of packed samples.

    Args:
        sigmas: densities (>= 0).
        deltas: interval lengths (>= 0).
        ray_indices: ray of each sample, non-decreasing.

    Returns:
        ``(weights, transmittance)``, equal to the dense ``render_weights`` of the same rays
        padded with zero-density samples.

    Note:
        Differentiable in ``sigmas`` and ``deltas``.

    Example:
        >>> w, t = render_weights_packed(torch.tensor([1e10, 0.0, 1e10]), torch.ones(3), torch.tensor([0, 1, 1]))
        >>> w.tolist(), t.tolist()
        ([1.0, 0.0, 1.0], [1.0, 1.0, 1.0])
    """
    thickness = optical_thickness(sigmas, deltas)
    weights, trans = weights_from_thickness(thickness, exclusive_segment_cumsum(thickness, ray_indices))
    return weights.to(sigmas.dtype), trans.to(sigmas.dtype)


def prune_mask(
    sigmas: Float[Tensor, "num_samples"],
    deltas: Float[Tensor, "num_samples"],
    ray_indices: Int[Tensor, "num_samples"],
    min_transmittance: float,
    min_alpha: "float | None" = None,
) -> Bool[Tensor, "num_samples"]:
    """Samples worth shading: the ray still reaches them (transmittance above ``min_transmittance``)
    and, unless ``min_alpha`` is ``None``, they are more opaque than ``min_alpha``.

    The full-pass reference of early ray termination (every sample's density is needed); see
    :meth:`~nerfpipe.estimators.occupancy.OccupancyGrid.march_until_opaque` for the fast path.
    """
    _, trans = render_weights_packed(sigmas, deltas, ray_indices)
    keep = trans > min_transmittance
    if min_alpha is not None:
        keep &= more_opaque_than(sigmas, deltas, min_alpha)
    return keep


def more_opaque_than(sigmas: Float[Tensor, "num_samples"], deltas: Float[Tensor, "num_samples"], min_alpha: float) -> Bool[Tensor, "num_samples"]:
    """Samples whose opacity ``1 - exp(-sigma * delta)`` exceeds ``min_alpha``."""
    return -torch.expm1(-optical_thickness(sigmas, deltas)) > min_alpha


def accumulate_packed(
    values: Float[Tensor, "num_samples C"], ray_indices: Int[Tensor, "num_samples"], num_rays: int
) -> Float[Tensor, "num_rays C"]:
    """Sum per-sample values over each ray (rays without samples give 0)."""
    out = torch.zeros(num_rays, values.shape[-1], dtype=values.dtype, device=values.device)
    return out.index_add(0, ray_indices, values)


def composite_packed(
    weights: Float[Tensor, "num_samples"],
    rgbs: Float[Tensor, "num_samples 3"],
    t_mids: Float[Tensor, "num_samples"],
    ray_indices: Int[Tensor, "num_samples"],
    background: Float[Tensor, "num_rays 3"],
) -> "tuple[Float[Tensor, 'num_rays 3'], Float[Tensor, 'num_rays'], Float[Tensor, 'num_rays']]":
    """Packed counterpart of ``volrend.composite``: ``(rgb, depth, acc)`` per ray, over ``background``."""
    num_rays = background.shape[0]
    stacked = torch.cat([weights[:, None] * rgbs, weights[:, None], (weights * t_mids)[:, None]], dim=-1)
    sums = accumulate_packed(stacked, ray_indices, num_rays)
    acc = sums[:, 3]
    rgb = sums[:, :3] + (1.0 - acc)[:, None] * background.to(sums)
    return rgb, sums[:, 4], acc


def quantile_depth_packed(
    weights: Float[Tensor, "num_samples"],
    t_starts: Float[Tensor, "num_samples"],
    t_ends: Float[Tensor, "num_samples"],
    ray_indices: Int[Tensor, "num_samples"],
    num_rays: int,
    quantile: float = 0.5,
) -> Float[Tensor, "num_rays"]:
    """Distance at which each ray's accumulated opacity reaches ``quantile`` (the median depth at 0.5:
    where the ray stops, which a thin fog in front of a surface does not move, unlike the expected depth
    ``sum w t / sum w``); linear within the sample that crosses it. NaN for rays that never reach it.

    Example:
        >>> w = torch.tensor([0.2, 0.6, 0.2, 0.3])
        >>> quantile_depth_packed(w, torch.tensor([0.0, 1.0, 2.0, 0.0]), torch.tensor([1.0, 2.0, 3.0, 1.0]), torch.tensor([0, 0, 0, 1]), 2).tolist()
        [1.5, nan]
    """
    before = exclusive_segment_cumsum(weights, ray_indices)
    crossing = (before < quantile) & (before + weights >= quantile)
    frac = ((quantile - before) / weights.clamp(min=torch.finfo(weights.dtype).tiny)).clamp(0.0, 1.0)
    t = t_starts + frac * (t_ends - t_starts)
    sums = accumulate_packed(torch.stack([torch.where(crossing, t, torch.zeros_like(t)), crossing.to(t.dtype)], dim=-1), ray_indices, num_rays)
    return torch.where(sums[:, 1] > 0, sums[:, 0], torch.full_like(sums[:, 0], float("nan")))


def distortion_loss_packed(
    weights: Float[Tensor, "num_samples"],
    t_starts: Float[Tensor, "num_samples"],
    t_ends: Float[Tensor, "num_samples"],
    ray_indices: Int[Tensor, "num_samples"],
    num_rays: int,
) -> Float[Tensor, "num_rays"]:
    """Mip-NeRF 360 distortion loss per ray over packed samples (O(n) form).

    ``sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (t_end_i - t_start_i)``, with sample midpoints ``m``.
    """
    mids = 0.5 * (t_starts + t_ends)
    w_cum = exclusive_segment_cumsum(weights, ray_indices)
    wm_cum = exclusive_segment_cumsum(weights * mids, ray_indices)
    inter = 2.0 * weights * (mids * w_cum - wm_cum)
    intra = weights**2 * (t_ends - t_starts) / 3.0
    return accumulate_packed((inter + intra)[:, None], ray_indices, num_rays)[:, 0]
