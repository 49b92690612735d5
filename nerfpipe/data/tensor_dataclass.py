"""A dataclass of tensors that share a leading batch shape, indexed and moved like one tensor.

Subclasses name the field that defines the batch shape (``_batch_field``); every other field
has the same leading dimensions plus its own trailing ones (e.g. ``[*bs, 4, 4]``).
"""

from dataclasses import fields
from typing import ClassVar, TypeVar

import torch

T = TypeVar("T", bound="TensorDataclass")


class TensorDataclass:
    """Mixin for ``@dataclass`` containers of batch-shaped tensors (STYLE habit 3)."""

    _batch_field: ClassVar[str]

    @property
    def shape(self) -> torch.Size:
        return getattr(self, self._batch_field).shape

    def __len__(self) -> int:
        return self.shape[0]

    def _map(self: T, fn) -> T:
        """Apply ``fn(tensor, trailing_shape)`` to every field."""
        n = len(self.shape)
        return type(self)(**{f.name: fn(getattr(self, f.name), getattr(self, f.name).shape[n:]) for f in fields(self)})

    def __getitem__(self: T, idx) -> T:
        return self._map(lambda v, _: v[idx])

    def to(self: T, device=None, dtype: "torch.dtype | None" = None) -> T:
        """Move to a device; ``dtype`` changes the floating-point fields only."""
        return self._map(lambda v, _: v.to(device=device, dtype=dtype) if dtype is not None and v.is_floating_point() else v.to(device))

    def reshape(self: T, *shape: int) -> T:
        return self._map(lambda v, extra: v.reshape(*shape, *extra))

    def expand(self: T, *shape: int) -> T:
        """Broadcast to ``shape`` without copying (views)."""
        return self._map(lambda v, extra: v.expand(*shape, *extra))

    @property
    def device(self) -> torch.device:
        return getattr(self, self._batch_field).device
