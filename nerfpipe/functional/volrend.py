"""Volume rendering as pure functions over densities, colours and interval lengths (nerfacc style).

Glossary:
    sigma    volume density at a sample (>= 0), ``[*bs, num_samples]``
    delta    length of the interval a sample stands for (``t_end - t_start``)
    alpha    probability that the ray stops inside an interval: ``1 - exp(-sigma * delta)``
    T        transmittance: probability that the ray reaches an interval, ``exp(-sum_{j<i} sigma_j delta_j)``
    weight   ``T_i * alpha_i``; the weights of a ray sum to its opacity ``acc`` (<= 1)

Stability: the optical thickness ``sigma * delta`` is computed in float32 (float64 stays float64)
even for half-precision inputs and clamped to :data:`MAX_THICKNESS`, alpha is ``-expm1(-x)`` and
transmittance is the exponential of an exclusive cumulative sum in log space. Values and gradients
stay finite for sigma in [0, 1e10] and delta in [0, 1e3].
"""

import torch

from nerfpipe.util.typing import Float, Tensor

MAX_THICKNESS = 1e4
"""Optical thickness ``sigma * delta`` is clamped here: ``exp(-1e4)`` is 0 in every float type."""


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


def optical_thickness(sigmas: Float[Tensor, "*bs"], deltas: Float[Tensor, "*bs"]) -> Float[Tensor, "*bs"]:
    """``sigma * delta`` in float32 (float64 stays float64), clamped to ``[0, MAX_THICKNESS]``.

    The one place of nerfpipe's stability rule: every renderer (dense, packed, the occupancy
    grid's marching, the mesh's depth scan) computes its thicknesses here.
    """
    ct = _compute_dtype(sigmas.dtype)
    return (sigmas.to(ct) * deltas.to(ct)).clamp(0.0, MAX_THICKNESS)


def weights_from_thickness(
    thickness: Float[Tensor, "*bs"], depth_before: Float[Tensor, "*bs"]
) -> "tuple[Float[Tensor, '*bs'], Float[Tensor, '*bs']]":
    """``(weights, transmittance)`` of samples from their thickness and the optical depth in front of them.

    ``alpha = 1 - exp(-thickness)`` (as ``-expm1``), ``T = exp(-depth_before)``, ``weight = T * alpha``:
    the one implementation of the compositing maths. The callers differ only in how they sum the
    depth in front of a sample: along the last axis (:func:`render_weights`), per ray over packed
    samples (:func:`~nerfpipe.functional.packed.render_weights_packed`), or carried across the
    rounds of early ray termination (:mod:`nerfpipe.estimators.occupancy`).

    Args:
        thickness: from :func:`optical_thickness`.
        depth_before: sum of the thicknesses in front of each sample on its ray (0 for the first).

    Returns:
        ``(weights, transmittance)`` in the dtype of ``thickness``.
    """
    trans = torch.exp(-depth_before.to(thickness.dtype))
    return trans * -torch.expm1(-thickness), trans


def render_weights(
    sigmas: Float[Tensor, "*bs num_samples"], deltas: Float[Tensor, "*bs num_samples"]
) -> "tuple[Float[Tensor, '*bs num_samples'], Float[Tensor, '*bs num_samples']]":
    """Compositing weights and transmittance of samples along rays.

    Args:
        sigmas: densities (>= 0).
        deltas: interval lengths (>= 0), broadcastable to ``sigmas``.

    Returns:
        ``(weights, transmittance)`` in the dtype of ``sigmas``; transmittance is the
        probability of reaching each interval (exclusive: the first is 1).

    Note:
        Differentiable in ``sigmas`` and ``deltas``; thicknesses above :data:`MAX_THICKNESS`
        have zero gradient (the ray is already fully blocked there).

    Example:
        >>> w, t = render_weights(torch.tensor([0.0, 1e10]), torch.tensor([1.0, 1.0]))
        >>> w.tolist(), t.tolist()
        ([0.0, 1.0], [1.0, 1.0])
    """
    thickness = optical_thickness(sigmas, deltas)
    # exclusive cumulative sum (log transmittance), exact zero for the first sample
    excl = torch.cat([torch.zeros_like(thickness[..., :1]), torch.cumsum(thickness[..., :-1], dim=-1)], dim=-1)
    weights, trans = weights_from_thickness(thickness, excl)
    return weights.to(sigmas.dtype), trans.to(sigmas.dtype)


def accumulate(weights: Float[Tensor, "*bs num_samples"], values: Float[Tensor, "*bs num_samples C"]) -> Float[Tensor, "*bs C"]:
    """Weighted sum of per-sample values along each ray: ``sum_i w_i v_i``."""
    return torch.sum(weights[..., None] * values, dim=-2)


def composite(
    weights: Float[Tensor, "*bs num_samples"],
    rgbs: Float[Tensor, "*bs num_samples 3"],
    t_mids: Float[Tensor, "*bs num_samples"],
    background: "Float[Tensor, '*bs 3'] | Float[Tensor, '3'] | None" = None,
) -> "tuple[Float[Tensor, '*bs 3'], Float[Tensor, '*bs'], Float[Tensor, '*bs']]":
    """Composited colour over a background, expected depth and accumulated opacity.

    Args:
        weights: from :func:`render_weights`.
        rgbs: per-sample colours.
        t_mids: sample distances along the rays (interval midpoints).
        background: colour behind the volume (per ray or one colour); ``None`` is black.

    Returns:
        ``(rgb, depth, acc)`` with ``rgb = sum w c + (1 - acc) * background``,
        ``depth = sum w t`` (divide by ``acc`` for the surface distance), ``acc = sum w``.
    """
    acc = weights.sum(dim=-1)
    rgb = accumulate(weights, rgbs)
    if background is not None:
        rgb = rgb + (1.0 - acc)[..., None] * background.to(rgb)
    depth = torch.sum(weights * t_mids, dim=-1)
    return rgb, depth, acc


def volrend(
    sigmas: Float[Tensor, "*bs num_samples 1"],
    rgbs: Float[Tensor, "*bs num_samples 3"],
    step_size: "float | Float[Tensor, '*bs num_samples 1'] | Float[Tensor, '*bs num_samples']",
) -> Float[Tensor, "*bs 3"]:
    """The course's volume renderer: colours composited over black.

    Args:
        sigmas: densities ``[N, S, 1]``.
        rgbs: colours ``[N, S, 3]``.
        step_size: one interval length for all samples, or per-sample lengths ``[N, S(, 1)]``.

    Returns:
        Rendered colours ``[N, 3]``.

    Example:
        >>> torch.manual_seed(42)  # doctest: +ELLIPSIS
        <...>
        >>> volrend(torch.rand(10, 64, 1), torch.rand(10, 64, 3), (6.0 - 2.0) / 64)[0]
        tensor([0.5006, 0.3728, 0.4728])
    """
    sig = sigmas[..., 0]
    deltas = torch.as_tensor(step_size, dtype=sig.dtype, device=sig.device)
    if deltas.ndim == sigmas.ndim and deltas.ndim > 0:
        deltas = deltas[..., 0]
    weights, _ = render_weights(sig, deltas.expand_as(sig))
    return accumulate(weights, rgbs)


def binary_entropy(acc: Float[Tensor, "*bs"], eps: float = 1e-3) -> Float[Tensor, "*bs"]:
    """``-a log a - (1 - a) log(1 - a)`` of opacities ``acc`` clamped to ``[eps, 1 - eps]`` (finite gradients at
    0 and 1): zero for rays that stop or pass, largest (``log 2``) for a half-transparent veil."""
    a = acc.clamp(eps, 1.0 - eps)
    return -(a * torch.log(a) + (1.0 - a) * torch.log1p(-a))


def insert_layer(
    weights: Float[Tensor, "*bs num_samples"], t: Float[Tensor, "*bs num_samples"], layer_t: Float[Tensor, "*bs"],
    layer_alpha: Float[Tensor, "*bs"],
) -> "tuple[Float[Tensor, '*bs num_samples'], Float[Tensor, '*bs']]":
    """Compositing weights of samples along rays with a thin layer inserted at distance ``layer_t`` with opacity
    ``layer_alpha`` (a textured plane among a field's samples): the samples in front of it (``t < layer_t``) keep
    their weights, the layer gets what they let through times its opacity, and the samples behind it are dimmed
    by ``1 - layer_alpha``.

    Returns:
        ``(weights, layer_weight)``; ``1 - weights.sum(-1) - layer_weight`` is what reaches the background.

    Example:
        >>> w, lw = insert_layer(torch.tensor([0.5, 0.5]), torch.tensor([1.0, 3.0]), torch.tensor(2.0), torch.tensor(0.5))
        >>> w.tolist(), lw.item()
        ([0.5, 0.25], 0.25)
    """
    front = t < layer_t[..., None]
    front_weights = torch.where(front, weights, torch.zeros_like(weights))
    passed = 1.0 - front_weights.sum(-1)  # the transmittance at the layer
    return torch.where(front, weights, weights * (1.0 - layer_alpha[..., None])), layer_alpha * passed
