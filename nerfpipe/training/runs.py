"""The run folder: ``config.json`` (enough to rebuild scene and model), ``checkpoint.safetensors``
(:mod:`nerfpipe.training.checkpoint`), outputs.

``config.json`` holds ``{"data": path, "model": name, "model_config": {...}, "trainer": {...}}``, and ``"points"``:
a COLMAP model of sparse points triangulated for the data (the ``sfm`` stage's, for posed photographs without
points) when the scene had them; :func:`load_run` rebuilds the scene (through ``data_adapters.load``, with those
points) and the trained model.
"""

import json
import warnings
from pathlib import Path

from nerfpipe.util.atomic import write_json  # noqa: F401 (write_json is part of this module's API)
from nerfpipe.training.checkpoint import CHECKPOINT, find_checkpoint, load_checkpoint
from nerfpipe.util.configs import from_dict, to_dict  # noqa: F401 (to_dict is part of this module's API)
from nerfpipe.util.devices import check_device
from nerfpipe.util.errors import NerfpipeError

CONFIG = "config.json"


class RetiredOptionWarning(UserWarning):
    """A run's ``config.json`` names model options that this version of nerfpipe no longer has."""


CONFIG_KEYS = {"data": str, "model": str, "model_config": dict, "trainer": dict}
"""What :func:`load_run` needs from ``config.json``, and of which JSON type."""


def read_config(run_dir: Path) -> dict:
    """``config.json`` of a run folder, with the keys of :data:`CONFIG_KEYS`; anything else is one clear error."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise NerfpipeError("not a run folder (no such folder)" if not run_dir.exists() else "not a run folder (a file)", run_dir)
    path = run_dir / CONFIG
    if not path.is_file():
        raise NerfpipeError(f"not a run folder (no {CONFIG})", run_dir)
    try:
        cfg = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise NerfpipeError(f"cannot read the run's config ({type(exc).__name__}: {exc})", path) from exc
    bad = [k for k, kind in CONFIG_KEYS.items() if not isinstance(cfg, dict) or not isinstance(cfg.get(k), kind)]
    if bad:
        raise NerfpipeError(f"not a nerfpipe run config: '{bad[0]}' is missing or of the wrong type", path)
    return cfg


def load_model_state(model, state: dict, ckpt_path: Path, name: str) -> None:
    """``model.load_state_dict(state)``, a checkpoint that does not fit (another model, tensors missing
    or of other shapes) being one line naming it (used by :func:`load_run` and the trainer's resume).

    Tensors are missing only after the model's own loading hooks ran: a model may give tensors that
    older checkpoints lack their old meaning (the fast model's ``density_levels``, ``trained_steps``)."""
    if not isinstance(state, dict):
        raise NerfpipeError(f"checkpoint does not fit the '{name}' model of {CONFIG}: missing tensors (all)", ckpt_path)
    try:
        result = model.load_state_dict(state, strict=False)
    except (RuntimeError, ValueError, TypeError, KeyError) as exc:
        raise NerfpipeError(f"checkpoint does not fit the '{name}' model of {CONFIG} ({' '.join(str(exc).split())[:300]})", ckpt_path) from exc
    for what, keys in (("missing", result.missing_keys), ("unexpected", result.unexpected_keys)):
        if keys:
            raise NerfpipeError(f"checkpoint does not fit the '{name}' model of {CONFIG}: {what} tensors {', '.join(sorted(keys)[:3])}", ckpt_path)


def model_dir(run_dir: Path) -> Path:
    """The folder of a run that holds its model: the run itself (``nerfpipe train``) or its ``train/``
    (``nerfpipe run``); the run itself when neither has a ``config.json`` (so errors name it)."""
    run_dir = Path(run_dir)
    if not (run_dir / CONFIG).is_file() and (run_dir / "train" / CONFIG).is_file():
        return run_dir / "train"
    return run_dir


def find_run(path: Path) -> "Path | None":
    """The folder of ``path`` that holds a trained model (:func:`model_dir`), or None when ``path`` is no
    run folder (a dataset, a file); for readers that take a run or something else (``nerfpipe view``)."""
    folder = model_dir(path)
    return folder if (folder / CONFIG).is_file() else None


def _options_since(config: type, values: dict) -> None:
    """Give ``values`` (a run's stored model config) the value it was trained as for each option added since
    (``config.OPTIONS_SINCE``, dotted names) that it lacks."""
    if not isinstance(values, dict):
        return  # refused, naming the file, by from_dict
    for dotted, old in getattr(config, "OPTIONS_SINCE", {}).items():
        *tables, key = dotted.split(".")
        table = values
        for name in tables:
            table = table.setdefault(name, {})
            if not isinstance(table, dict):
                break
        else:
            table.setdefault(key, old)


def load_run(run_dir: Path, device: str = "auto"):
    """``(scene, model, config)`` of a finished or checkpointed run, model in eval mode, on ``device``
    (``auto``: CUDA when present, else the CPU; :func:`~nerfpipe.util.devices.check_device`).

    ``run_dir`` is a folder of ``nerfpipe train`` or of ``nerfpipe run`` (its ``train/``: :func:`model_dir`),
    so every command that reads a run takes either. Run folders are passed around: a malformed ``config.json``, a checkpoint of another model or one
    with tensors missing or of other shapes is a :class:`NerfpipeError` naming the file.
    """
    from nerfpipe.data_adapters import load

    from nerfpipe.models.base import SceneInfo  # noqa: F401  (documented return types)
    from nerfpipe.models.registry import get_model
    from nerfpipe.training.trainer import scene_info

    device = check_device(device)
    run_dir = model_dir(run_dir)
    cfg = read_config(run_dir)
    ckpt_path = find_checkpoint(run_dir)
    if ckpt_path is None:
        raise NerfpipeError(f"run has no {CHECKPOINT} yet", run_dir)
    state = load_checkpoint(ckpt_path)["model"]  # first: a refused checkpoint costs no scene loading
    config_file = Path(run_dir) / CONFIG
    try:
        spec = get_model(cfg["model"])
        _options_since(spec.config, cfg["model_config"])
        retired: "list[str]" = []
        model_cfg = from_dict(spec.config, cfg["model_config"], dropped=retired)
    except (TypeError, ValueError) as exc:
        raise NerfpipeError(f"model_config does not fit the '{cfg['model']}' model ({exc})", config_file) from exc
    except NerfpipeError as exc:
        raise NerfpipeError(exc.problem, config_file) from exc
    if retired:  # written by an earlier nerfpipe: the checkpoint's tensors still have to fit (load_model_state)
        warnings.warn(f"{config_file}: options this nerfpipe no longer has are ignored: {', '.join(retired)}", RetiredOptionWarning, stacklevel=2)
    scene = load(Path(cfg["data"]))
    if isinstance(cfg.get("points"), str):  # the points the run trained with, which the data itself lacks
        from nerfpipe.data_adapters.colmap import with_points

        scene = with_points(scene, Path(cfg["points"]))
    info = scene_info(scene, cfg.get("trainer", {}).get("train_max_size"))
    if hasattr(model_cfg, "for_checkpoint"):  # a preset changed since the run was written: the capacity it was trained with
        model_cfg = model_cfg.for_checkpoint(state, info)
    model = model_cfg.setup(info).to(device)
    load_model_state(model, state, ckpt_path, cfg["model"])
    return scene, model.eval(), cfg
