"""Named configurations of a 2D fit: ``course`` (the classic recipe) and ``fast`` (grid + tiny MLP)."""

import copy
import dataclasses
from dataclasses import dataclass

from nerfpipe.encoders import GridEncoderConfig, PositionalEncoderConfig
from nerfpipe.image_field.field import ImageFieldConfig
from nerfpipe.image_field.train import TrainConfig


@dataclass
class Fit2dConfig:
    """A field and how to train it."""

    field: ImageFieldConfig = dataclasses.field(default_factory=ImageFieldConfig)
    """The network: encoder and MLP."""
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    """The optimisation."""


PRESETS: "dict[str, Fit2dConfig]" = {
    # The course: PE with L = 10, 4 linear layers of width 256, Adam 1e-2, 10k random pixels per step.
    "course": Fit2dConfig(
        ImageFieldConfig(PositionalEncoderConfig(num_frequencies=10), hidden_width=256, num_layers=4),
        TrainConfig(iterations=3000, lr=1e-2, batch_size=10_000, num_evals=12),  # a full-image eval costs ~10 steps
    ),
    # Multiresolution grid (dense up to 2^16 vertices per level, hashed above) + one hidden layer of 32.
    # Small batches at a high, decaying learning rate: per CPU second, 8k-pixel steps beat full-image
    # steps (measured on fox.jpg: 600 × 8k reaches ~35 dB for the CPU cost of ~60 full-image steps).
    "fast": Fit2dConfig(
        ImageFieldConfig(
            GridEncoderConfig(num_levels=8, features_per_level=2, base_resolution=16, max_resolution=512),
            hidden_width=32,
            num_layers=2,
        ),
        TrainConfig(iterations=600, lr=5e-2, lr_final_factor=0.1, batch_size=8192, adam_eps=1e-15, num_evals=20),
    ),
}


def preset(name: str) -> Fit2dConfig:
    """A deep copy of a named preset, safe to modify."""
    return copy.deepcopy(PRESETS[name])
