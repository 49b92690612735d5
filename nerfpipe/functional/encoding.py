"""Positional (frequency) encoding with exact phases.

Glossary:
    x        coordinates ``[*bs, D]``; any D (2 for image pixels, 3 for positions and directions)
    L        number of frequencies ``num_frequencies``; frequency k (``0 <= k < L``) has phase ``2^k·π·x``
    ordering the course ordering ``[x, sin(2^0·π·x), cos(2^0·π·x), ..., sin(2^(L-1)·π·x), cos(2^(L-1)·π·x)]``,
             grouped by frequency; each group is ``D`` wide (all coordinates of one sin, then of one cos)

Why exact phases: in float32, ``2^34·π·x`` has an absolute rounding error far larger than 2π, so
``sin`` of it is noise. Because ``sin(π·t)`` has period 2 in ``t``, only ``(2^k·x) mod 2`` matters.
Multiplying a float by a power of two is exact, and so is ``fmod``; we do both in float64 (every
float32 input is exactly representable there) and only then multiply by π and take sin/cos.
The result is the correctly rounded encoding of the given input for any L up to ~1000.
"""

import math

import torch

from nerfpipe.util.typing import Float, Tensor


def positional_encoding_dim(dim: int, num_frequencies: int, include_input: bool = True) -> int:
    """Width of :func:`positional_encoding` output for a ``dim``-wide input."""
    return dim * (int(include_input) + 2 * num_frequencies)


def reduced_phases(x: Float[Tensor, "*bs D"], num_frequencies: int) -> Float[Tensor, "*bs L D"]:
    """``(2^k · x) mod 2`` for ``k < L``, computed exactly in float64 (differentiable, d/dx = 2^k).

    Args:
        x: coordinates of any float dtype.
        num_frequencies: L.

    Returns:
        float64 ``[*bs, L, D]`` in ``[0, 2)``; ``π`` times it is the phase of frequency k.
    """
    x64 = x.to(torch.float64)
    scales = torch.exp2(torch.arange(num_frequencies, dtype=torch.float64, device=x.device))
    scaled = x64.unsqueeze(-2) * scales[:, None]  # exact: power-of-two scaling
    return torch.remainder(scaled, 2.0)  # exact; gradient 1 w.r.t. ``scaled``


def positional_encoding(
    x: Float[Tensor, "*bs D"], num_frequencies: int, include_input: bool = True
) -> Float[Tensor, "*bs E"]:
    """NeRF positional encoding ``PE(x) = [x, sin(2^k·π·x), cos(2^k·π·x)]_{k<L}`` with exact phases.

    Args:
        x: coordinates ``[*bs, D]``; usually normalised (``[0, 1]`` pixel coordinates or ``[-1, 1]``).
        num_frequencies: L (0 returns ``x`` itself when ``include_input``).
        include_input: put ``x`` first (the course recipe does).

    Returns:
        ``[*bs, D·(1+2L)]`` (or ``D·2L``) in the dtype of ``x``; ordering in the module docstring.

    Note:
        Differentiable w.r.t. ``x`` (the phase reduction has slope ``2^k``). Phases are reduced in
        float64, so the result is exact to the output dtype's rounding even at L = 40.

    Example:
        >>> positional_encoding(torch.tensor([[0.25]]), 2).round(decimals=4)
        tensor([[0.2500, 0.7071, 0.7071, 1.0000, 0.0000]])
    """
    parts = [x] if include_input else []
    if num_frequencies > 0:
        phase = math.pi * reduced_phases(x, num_frequencies)  # [*bs, L, D]
        sc = torch.stack([torch.sin(phase), torch.cos(phase)], dim=-2)  # [*bs, L, 2, D]
        parts.append(sc.flatten(-3).to(x.dtype))
    return torch.cat(parts, dim=-1)


def nyquist_frequencies(resolution: int) -> int:
    """The largest L whose frequencies a ``resolution``-sample grid on ``[0, 1]`` still carries.

    ``sin(2^k·π·x)`` has period ``2/2^k``; sampled every ``1/resolution`` it is below Nyquist while
    ``2^k <= resolution``, i.e. ``k <= log2(resolution)``. Higher frequencies only alias.
    """
    return int(math.floor(math.log2(max(resolution, 1)))) + 1
