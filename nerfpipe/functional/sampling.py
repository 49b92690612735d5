"""Where to put samples along rays: stratified intervals and inverse-CDF (importance) resampling.

Glossary:
    edges    interval boundaries along a ray, ``[*bs, num_samples + 1]``, sorted
    t_mids   interval midpoints, where the field is evaluated
    perturb  training-time jitter: each boundary moves uniformly inside its stratum, so every
             point of ``[near, far]`` is sampled over the iterations
"""

import torch

from nerfpipe.util.typing import Float, Tensor


def stratified_samples(
    near: Float[Tensor, "*bs"],
    far: Float[Tensor, "*bs"],
    num_samples: int,
    perturb: bool = False,
    generator: "torch.Generator | None" = None,
) -> Float[Tensor, "*bs num_edges"]:
    """Boundaries of ``num_samples`` contiguous intervals between ``near`` and ``far``.

    Without ``perturb`` the intervals are uniform (evaluate at their midpoints). With it, each
    inner boundary is drawn uniformly between the midpoints of its neighbouring uniform intervals
    (the first and last stay at near and far), a random offset inside each interval.

    Returns:
        ``[*bs, num_samples + 1]`` sorted boundaries (``num_edges = num_samples + 1``).

    Example:
        >>> stratified_samples(torch.tensor(2.0), torch.tensor(6.0), 4).tolist()
        [2.0, 3.0, 4.0, 5.0, 6.0]
    """
    u = torch.linspace(0.0, 1.0, num_samples + 1, dtype=near.dtype, device=near.device)
    u = u.expand(*near.shape, num_samples + 1)
    if perturb:
        mids = 0.5 * (u[..., 1:] + u[..., :-1])
        lower, upper = mids[..., :-1], mids[..., 1:]  # inner edge k moves within [mid_{k-1}, mid_k]
        r = torch.rand(lower.shape, dtype=u.dtype, device=u.device, generator=generator)
        u = torch.cat([u[..., :1], lower + (upper - lower) * r, u[..., -1:]], dim=-1)
    return near[..., None] + (far - near)[..., None] * u


def pdf_samples(
    bins: Float[Tensor, "*bs num_edges"],
    weights: Float[Tensor, "*bs num_bins"],
    num: int,
    perturb: bool = False,
    generator: "torch.Generator | None" = None,
    eps: float = 1e-5,
) -> Float[Tensor, "*bs num"]:
    """Draw ``num`` distances from the piecewise-constant density ``weights`` over ``bins``.

    Inverse transform sampling of the classic NeRF (``sample_pdf``): the CDF of the normalised
    weights is inverted at ``num`` sorted quantiles, evenly spaced (or stratified-random when
    ``perturb``), and interpolated linearly inside each bin.

    Args:
        bins: interval boundaries (``num_edges = num_bins + 1``), sorted.
        weights: non-negative mass per interval (e.g. coarse render weights, detached).
        num: samples per ray.
        eps: added to every weight, so empty rays fall back to uniform sampling.

    Returns:
        ``[*bs, num]`` sorted distances inside ``[bins[0], bins[-1]]``. Not differentiable.
    """
    w = weights.detach() + eps
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[..., :1]), torch.cumsum(pdf, dim=-1)], dim=-1).clamp(max=1.0)
    shape = (*w.shape[:-1], num)
    if perturb:
        u = (torch.arange(num, dtype=w.dtype, device=w.device) + torch.rand(shape, dtype=w.dtype, device=w.device, generator=generator)) / num
    else:
        u = ((torch.arange(num, dtype=w.dtype, device=w.device) + 0.5) / num).expand(shape)
    u = u.contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(0, bins.shape[-1] - 1)
    above = idx.clamp(0, bins.shape[-1] - 1)
    cdf_lo, cdf_hi = torch.gather(cdf, -1, below), torch.gather(cdf, -1, above)
    bin_lo, bin_hi = torch.gather(bins.detach(), -1, below), torch.gather(bins.detach(), -1, above)
    denom = cdf_hi - cdf_lo
    frac = torch.where(denom > 0, (u - cdf_lo) / torch.where(denom > 0, denom, 1.0), 0.0)
    return bin_lo + frac.clamp(0.0, 1.0) * (bin_hi - bin_lo)


def merge_edges(edges: Float[Tensor, "*bs n"], extra: Float[Tensor, "*bs m"]) -> Float[Tensor, "*bs k"]:
    """Sorted union of interval boundaries and new sample distances (``k = n + m``)."""
    return torch.sort(torch.cat([edges, extra], dim=-1), dim=-1).values
