"""Layer 2: coordinate encoders as ``nn.Module`` s with one config dataclass each.

Every encoder maps ``[*bs, D] -> [*bs, out_dim]`` and is built by ``Config.setup(in_dim)``.
"""

from nerfpipe.encoders.frequency import PositionalEncoder, PositionalEncoderConfig, is_static
from nerfpipe.encoders.grid import GridEncoder, GridEncoderConfig

__all__ = ["GridEncoder", "GridEncoderConfig", "PositionalEncoder", "PositionalEncoderConfig", "is_static"]
