"""Registered models: everything in the ``nerfpipe.models`` entry-point group (built-ins included)."""

from dataclasses import dataclass

from nerfpipe.models.base import ModelSpec
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.registry import MODEL_GROUP, discover


def models() -> "dict[str, ModelSpec]":
    """All models that load, by name."""
    return discover(MODEL_GROUP, ModelSpec)


def get_model(name: str) -> ModelSpec:
    """The model registered as ``name``, or a user error listing the known ones."""
    found = models()
    if name not in found:
        raise NerfpipeError(f"unknown model '{name}'; registered: {', '.join(sorted(found)) or 'none'}")
    return found[name]


@dataclass(frozen=True)
class Preset:
    """A named default of ``nerfpipe train`` and the bench: a model, its config and trainer options."""

    model: str
    """Registered model name."""
    config: object
    """The model's config."""
    trainer: dict
    """TrainerConfig fields that differ from its defaults."""


TRAINER_DEFAULTS = {"fast": {"rays_per_step": None}, "vanilla": {"rays_per_step": 1024}}
"""Trainer options the built-in models are trained with by default (their measured recipes: README); the fast
model's rays per step follow the device and, on the CPU, the images of an object on a transparent background
(:func:`nerfpipe.training.trainer.default_rays_per_step`)."""


def presets() -> "dict[str, Preset]":
    """Named defaults: every registered model under its own name, and ``fast-<size>`` for each capacity
    preset of the fast field (:data:`nerfpipe.models.fast.PRESETS`)."""
    from nerfpipe.models.fast import PRESETS, FastConfig

    found = {name: Preset(name, spec.config(), TRAINER_DEFAULTS.get(name, {})) for name, spec in models().items()}
    found.update({f"fast-{size}": Preset("fast", FastConfig(preset=size), TRAINER_DEFAULTS["fast"]) for size in PRESETS})
    return found


def get_preset(name: str) -> Preset:
    """The named default ``name``, or a user error listing them."""
    found = presets()
    if name not in found:
        raise NerfpipeError(f"unknown model '{name}'; registered models and presets: {', '.join(sorted(found))}")
    return found[name]
