"""Registered models: everything in the ``nerfpipe.models`` entry-point group (built-ins included)."""

from nerfpipe.errors import NerfpipeError
from nerfpipe.models.base import ModelSpec
from nerfpipe.registry import MODEL_GROUP, discover


def models() -> "dict[str, ModelSpec]":
    """All models that load, by name."""
    return discover(MODEL_GROUP, ModelSpec)


def get_model(name: str) -> ModelSpec:
    """The model registered as ``name``, or a user error listing the known ones."""
    found = models()
    if name not in found:
        raise NerfpipeError(f"unknown model '{name}'; registered: {', '.join(sorted(found)) or 'none'}")
    return found[name]
