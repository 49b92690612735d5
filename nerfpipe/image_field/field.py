"""The 2D neural field: pixel coordinate ``(x, y)`` in ``[0, 1]^2`` -> RGB in ``[0, 1]``."""

from dataclasses import dataclass, field

from torch import nn

from nerfpipe.encoders import GridEncoderConfig, PositionalEncoderConfig
from nerfpipe.util.typing import Float, Tensor


@dataclass
class ImageFieldConfig:
    """Encoder followed by an MLP with ReLU between linear layers and a sigmoid on RGB."""

    encoder: "PositionalEncoderConfig | GridEncoderConfig" = field(default_factory=PositionalEncoderConfig)
    """Coordinate encoding: fixed frequencies (course) or a learned multiresolution grid (fast)."""
    hidden_width: int = 256
    """Width of the hidden layers."""
    num_layers: int = 4
    """Number of linear layers (1 = linear read-out of the encoding)."""

    def setup(self) -> "ImageField":
        return ImageField(self)


class ImageField(nn.Module):
    """``encoder -> [Linear, ReLU] * (num_layers-1) -> Linear -> sigmoid``."""

    def __init__(self, config: ImageFieldConfig) -> None:
        super().__init__()
        self.config = config
        self.encoder = config.encoder.setup(2)
        self.mlp = _mlp(self.encoder.out_dim, config.hidden_width, config.num_layers, 3)

    def forward(self, xy: Float[Tensor, "*bs 2"]) -> Float[Tensor, "*bs 3"]:
        return self.decode(self.encoder(xy))

    def decode(self, features: Float[Tensor, "*bs E"]) -> Float[Tensor, "*bs 3"]:
        """RGB from already encoded coordinates (lets callers cache a parameter-free encoding)."""
        return self.mlp(features).sigmoid()

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def _mlp(in_dim: int, width: int, num_layers: int, out_dim: int) -> nn.Sequential:
    if num_layers < 1:
        raise ValueError("num_layers must be >= 1")
    dims = [in_dim] + [width] * (num_layers - 1) + [out_dim]
    layers: "list[nn.Module]" = []
    for i in range(num_layers):
        layers.append(nn.Linear(dims[i], dims[i + 1]))
        if i < num_layers - 1:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)
