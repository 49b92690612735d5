"""The classic NeRF field (Mildenhall et al. 2020; CS180 project 4, part 2).

``PE_10(x)`` -> 8 linear layers of width 256 with ReLU, ``PE_10(x)`` concatenated back in before
the fifth -> density head (ReLU, so density >= 0) and a feature layer -> concatenate ``PE_4(d)``
-> one 128-wide layer (ReLU) -> RGB through a sigmoid.
"""

from dataclasses import dataclass

import torch
from torch import nn

from nerfpipe.functional.encoding import positional_encoding, positional_encoding_dim
from nerfpipe.util.typing import Float, Tensor


@dataclass
class VanillaFieldConfig:
    """Sizes of the classic NeRF MLP."""

    pos_frequencies: int = 10
    """Positional-encoding frequencies L for positions."""
    dir_frequencies: int = 4
    """Positional-encoding frequencies L for view directions."""
    width: int = 256
    """Width of the trunk layers."""
    depth: int = 8
    """Number of trunk layers."""
    skip: int = 4
    """The encoded position is concatenated to the input of this trunk layer (0-based)."""
    head_width: int = 128
    """Width of the view-dependent colour layer."""


class VanillaField(nn.Module):
    """Density and view-dependent colour at world points."""

    def __init__(self, cfg: VanillaFieldConfig = VanillaFieldConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        pos_dim = positional_encoding_dim(3, cfg.pos_frequencies)
        dir_dim = positional_encoding_dim(3, cfg.dir_frequencies)
        ins = [pos_dim] + [cfg.width + (pos_dim if i == cfg.skip else 0) for i in range(1, cfg.depth)]
        self.trunk = nn.ModuleList([nn.Linear(n, cfg.width) for n in ins])
        self.density_head = nn.Linear(cfg.width, 1)
        self.feature = nn.Linear(cfg.width, cfg.width)
        self.color_hidden = nn.Linear(cfg.width + dir_dim, cfg.head_width)
        self.color_out = nn.Linear(cfg.head_width, 3)

    def _trunk(self, positions: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs width"]:
        enc = positional_encoding(positions, self.cfg.pos_frequencies)
        h = enc
        for i, layer in enumerate(self.trunk):
            if i == self.cfg.skip:
                h = torch.cat([h, enc], dim=-1)
            h = torch.relu(layer(h))
        return h

    def density(self, positions: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs"]:
        """Volume density (>= 0) at world points."""
        return torch.relu(self.density_head(self._trunk(positions)))[..., 0]

    def forward(
        self, positions: Float[Tensor, "*bs 3"], directions: Float[Tensor, "*bs 3"]
    ) -> "tuple[Float[Tensor, '*bs'], Float[Tensor, '*bs 3']]":
        """``(density, rgb)`` at world points seen along unit ``directions``."""
        h = self._trunk(positions)
        sigma = torch.relu(self.density_head(h))[..., 0]
        d_enc = positional_encoding(directions, self.cfg.dir_frequencies)
        c = torch.relu(self.color_hidden(torch.cat([self.feature(h), d_enc], dim=-1)))
        return sigma, torch.sigmoid(self.color_out(c))
