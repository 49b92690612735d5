"""The run folder: ``config.json`` (enough to rebuild scene and model), ``checkpoint.safetensors``
(:mod:`nerfpipe.checkpoint`), outputs.

``config.json`` holds ``{"data": path, "model": name, "model_config": {...}, "trainer": {...}}``;
:func:`load_run` rebuilds the scene (through ``data_adapters.load``) and the trained model.
"""

import dataclasses
import json
import types
import typing
from pathlib import Path

from nerfpipe.atomic import write_json  # noqa: F401 (write_json is part of this module's API)
from nerfpipe.checkpoint import CHECKPOINT, find_checkpoint, load_checkpoint
from nerfpipe.errors import NerfpipeError

CONFIG = "config.json"


def to_dict(obj) -> dict:
    """A (nested) config dataclass as JSON-friendly data."""
    return json.loads(json.dumps(dataclasses.asdict(obj), default=str))


def from_dict(cls: type, data: dict):
    """Rebuild a (nested) config dataclass from :func:`to_dict` output; unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise NerfpipeError(f"unknown {cls.__name__} settings: {', '.join(sorted(unknown))}")
    kwargs = {}
    for key, value in data.items():
        hint = hints[key]
        if dataclasses.is_dataclass(hint) and isinstance(value, dict):
            value = from_dict(hint, value)
        elif isinstance(value, list) and _accepts_tuple(hint):
            value = tuple(value)  # JSON has no tuples
        kwargs[key] = value
    return cls(**kwargs)


def _accepts_tuple(hint) -> bool:
    """Whether a type hint is a tuple, or a union with one (e.g. ``tuple[int, ...] | None``)."""
    if typing.get_origin(hint) is tuple or hint is tuple:
        return True
    return any(_accepts_tuple(a) for a in typing.get_args(hint)) if typing.get_origin(hint) in (typing.Union, types.UnionType) else False


def read_config(run_dir: Path) -> dict:
    path = Path(run_dir) / CONFIG
    if not path.is_file():
        raise NerfpipeError(f"not a run folder (no {CONFIG})", run_dir)
    return json.loads(path.read_text())


def load_run(run_dir: Path, device: str = "cpu"):
    """``(scene, model, config)`` of a finished or checkpointed run, model in eval mode."""
    from data_adapters import load

    from nerfpipe.models.base import SceneInfo  # noqa: F401  (documented return types)
    from nerfpipe.models.registry import get_model
    from nerfpipe.trainer import scene_info

    cfg = read_config(run_dir)
    ckpt_path = find_checkpoint(run_dir)
    if ckpt_path is None:
        raise NerfpipeError(f"run has no {CHECKPOINT} yet", run_dir)
    state = load_checkpoint(ckpt_path)["model"]  # first: a refused checkpoint costs no scene loading
    scene = load(Path(cfg["data"]))
    spec = get_model(cfg["model"])
    model = from_dict(spec.config, cfg["model_config"]).setup(scene_info(scene)).to(device)
    model.load_state_dict(state)
    return scene, model.eval(), cfg
