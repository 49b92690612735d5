"""Samples along rays: :class:`RaySamples`, the container between a sampler and a field.

Glossary:
    t_starts, t_ends   interval boundaries along each ray (distance along unit directions)
    positions          world points at the interval midpoints, where the field is evaluated
"""

from dataclasses import dataclass
from typing import ClassVar


from nerfpipe.data.rays import RayBundle
from nerfpipe.data.tensor_dataclass import TensorDataclass
from nerfpipe.util.typing import Float, Tensor


@dataclass
class RaySamples(TensorDataclass):
    """Intervals along a batch of rays and the world points that stand for them."""

    t_starts: Float[Tensor, "*bs num_samples"]
    """Start of each interval."""
    t_ends: Float[Tensor, "*bs num_samples"]
    """End of each interval."""
    positions: Float[Tensor, "*bs num_samples 3"]
    """World points at the interval midpoints."""
    directions: Float[Tensor, "*bs num_samples 3"]
    """Unit ray directions, repeated for each sample (an expanded view, not a copy)."""

    _batch_field: ClassVar[str] = "t_starts"

    @classmethod
    def from_edges(cls, rays: RayBundle, edges: Float[Tensor, "*bs num_edges"]) -> "RaySamples":
        """Samples at the midpoints of the intervals between consecutive ``edges``."""
        starts, ends = edges[..., :-1], edges[..., 1:]
        mids = 0.5 * (starts + ends)
        positions = rays.origins[..., None, :] + mids[..., None] * rays.directions[..., None, :]
        directions = rays.directions[..., None, :].expand_as(positions)
        return cls(t_starts=starts, t_ends=ends, positions=positions, directions=directions)

    @property
    def deltas(self) -> Float[Tensor, "*bs num_samples"]:
        return self.t_ends - self.t_starts

    @property
    def t_mids(self) -> Float[Tensor, "*bs num_samples"]:
        return 0.5 * (self.t_starts + self.t_ends)
