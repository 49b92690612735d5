"""Plugin discovery through entry-point groups (STYLE habit 7).

Built-in and third-party plugins register the same way, in ``pyproject.toml``::

    [project.entry-points."nerfpipe.data_adapters"]
    myformat = "my_package.my_module:ADAPTER"

A plugin that fails to import or has the wrong type is skipped with a warning naming it;
a name registered twice keeps the first and warns.
"""

import importlib.metadata
import warnings
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

ADAPTER_GROUP = "nerfpipe.data_adapters"
STAGE_GROUP = "nerfpipe.stages"
MODEL_GROUP = "nerfpipe.models"


class PluginWarning(UserWarning):
    """A plugin could not be loaded or is invalid; it was skipped."""


@dataclass(frozen=True)
class AdapterSpec:
    """A data adapter: reads one input format into a :class:`~nerfpipe.data.scene.SceneData`."""

    name: str
    """Short format name, e.g. ``colmap``."""
    description: str
    """One line for ``nerfpipe info`` and listings."""
    detect: Callable[[Path], int]
    """Cheap check of a path: 0 when not this format, higher for a more specific match."""
    read: Callable[[Path], object]
    """``read(path) -> SceneData``; raises :class:`~nerfpipe.util.errors.NerfpipeError` on bad input."""


def discover(group: str, expected: "type[T]") -> "dict[str, T]":
    """Load every entry point of ``group`` whose object is an instance of ``expected``."""
    found: dict[str, T] = {}
    for ep in importlib.metadata.entry_points(group=group):
        try:
            obj = ep.load()
        except Exception as exc:  # a broken plugin must not break the tool
            warnings.warn(f"plugin '{ep.name}' ({ep.value}) in {group} failed to load: {exc!r}", PluginWarning, stacklevel=2)
            continue
        if not isinstance(obj, expected):
            warnings.warn(
                f"plugin '{ep.name}' ({ep.value}) in {group} is a {type(obj).__name__}, not a {expected.__name__}; skipped",
                PluginWarning,
                stacklevel=2,
            )
            continue
        if ep.name in found:
            warnings.warn(f"plugin name '{ep.name}' in {group} is registered twice; keeping the first", PluginWarning, stacklevel=2)
            continue
        found[ep.name] = obj
    return found
