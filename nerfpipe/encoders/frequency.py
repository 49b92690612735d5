"""Positional (frequency) encoder module: a thin wrapper over :func:`positional_encoding`."""

from dataclasses import dataclass

from torch import nn

from nerfpipe.functional.encoding import positional_encoding, positional_encoding_dim
from nerfpipe.util.typing import Float, Tensor


@dataclass
class PositionalEncoderConfig:
    """NeRF's fixed frequency encoding ``[x, sin(2^k·π·x), cos(2^k·π·x)]_{k<L}`` (exact phases)."""

    num_frequencies: int = 10
    """L: frequencies ``2^0 … 2^(L-1)`` (times π). Values above log2(resolution)+1 only alias."""
    include_input: bool = True
    """Put the raw coordinates first, as the course recipe does."""

    def setup(self, in_dim: int) -> "PositionalEncoder":
        return PositionalEncoder(self, in_dim)


class PositionalEncoder(nn.Module):
    """``[*bs, D] -> [*bs, D·(1+2L)]``; no parameters, so its output can be cached per input."""

    def __init__(self, config: PositionalEncoderConfig, in_dim: int) -> None:
        super().__init__()
        self.config = config
        self.in_dim = in_dim
        self.out_dim = positional_encoding_dim(in_dim, config.num_frequencies, config.include_input)

    def forward(self, x: Float[Tensor, "*bs D"]) -> Float[Tensor, "*bs E"]:
        return positional_encoding(x, self.config.num_frequencies, self.config.include_input)

    def describe(self) -> dict:
        return {
            "type": "positional",
            "num_frequencies": self.config.num_frequencies,
            "phases": "exact: (2^k·x) mod 2 reduced in float64 before multiplying by pi (no cap on L)",
        }


def is_static(encoder: nn.Module) -> bool:
    """Whether an encoder has no trainable parameters (its output can be precomputed)."""
    return not any(p.requires_grad for p in encoder.parameters())


__all__ = ["PositionalEncoderConfig", "PositionalEncoder", "is_static"]
