"""The run folder: ``config.json`` (enough to rebuild scene and model), ``checkpoint.pt``, outputs.

``config.json`` holds ``{"data": path, "model": name, "model_config": {...}, "trainer": {...}}``;
:func:`load_run` rebuilds the scene (through ``data_adapters.load``) and the trained model.
"""

import dataclasses
import json
import typing
from pathlib import Path

import torch

from nerfpipe.atomic import atomic_write, write_json  # noqa: F401 (write_json is part of this module's API)
from nerfpipe.errors import NerfpipeError

CONFIG = "config.json"
CHECKPOINT = "checkpoint.pt"


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
        kwargs[key] = from_dict(hint, value) if dataclasses.is_dataclass(hint) and isinstance(value, dict) else value
    return cls(**kwargs)


def save_checkpoint(path: Path, state: dict) -> None:
    """Write a checkpoint atomically: tensors, numbers, strings and plain containers only (what
    :func:`load_checkpoint` accepts)."""
    atomic_write(path, lambda p: torch.save(state, p))


def load_checkpoint(path: Path, device: "str | torch.device" = "cpu") -> dict:
    """Read a checkpoint without executing code from it.

    Checkpoints are what users pass around, so they are read with PyTorch's restricted unpickler
    (``weights_only=True``: tensors, numbers, strings and plain containers; any other object in the
    pickle, such as a call to ``os.system``, is refused before it runs).

    Raises:
        NerfpipeError: naming the file, when it is missing, not a checkpoint, or holds anything else.
    """
    path = Path(path)
    if not path.is_file():
        raise NerfpipeError("checkpoint is missing", path)
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError... for foreign files
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:160]
        raise NerfpipeError(f"not a nerfpipe checkpoint, or one holding objects other than tensors and plain data (refused: {first})", path) from exc
    if not isinstance(state, dict) or "model" not in state:
        raise NerfpipeError("not a nerfpipe checkpoint (no model state)", path)
    return state


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
    ckpt_path = Path(run_dir) / CHECKPOINT
    if not ckpt_path.is_file():
        raise NerfpipeError(f"run has no {CHECKPOINT} yet", run_dir)
    scene = load(Path(cfg["data"]))
    spec = get_model(cfg["model"])
    model = from_dict(spec.config, cfg["model_config"]).setup(scene_info(scene)).to(device)
    model.load_state_dict(load_checkpoint(ckpt_path, device)["model"])
    return scene, model.eval(), cfg
