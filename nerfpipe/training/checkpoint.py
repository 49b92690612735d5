"""The checkpoint file: tensors in safetensors, everything else as JSON in its header. No pickle.

Checkpoints are what users pass around, so reading one must not be able to run code. A pickle
(``torch.save``) can: its loader calls whatever the file names. A safetensors file holds only a
JSON header and raw tensor bytes, both parsed as data.

Layout of ``checkpoint.safetensors``:

* the tensors, each named by its path in the state (``model/field.aabb``,
  ``optimizer/state/0/exp_avg``, ``torch_rng``);
* the header's ``__metadata__``: ``format`` (:data:`FORMAT`), ``version`` (:data:`VERSION`) and
  ``state``, the state as JSON in which each tensor is ``{"$tensor": name}``. JSON has no
  tuples and only string keys, so a tuple is ``{"$tuple": [...]}`` and a dict with other keys
  (the optimiser's parameter indices) or with a ``state_dict`` version table is
  ``{"$items": [[key, value], ...], "$metadata": ...}``.

A state is made of tensors, ``None``, bools, ints, floats, strings, and lists, tuples and dicts
of these; saving anything else is a ``TypeError``. Loading gives the same values back, tensors
on the CPU (``load_state_dict`` of modules and optimisers moves them to the parameters' device).
"""

import json
from collections import OrderedDict
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from nerfpipe.util.atomic import atomic_write
from nerfpipe.util.errors import NerfpipeError

CHECKPOINT = "checkpoint.safetensors"
"""The checkpoint's name in a run folder."""
LEGACY_CHECKPOINT = "checkpoint.pt"
"""The pickle checkpoint of earlier versions: recognised, never read."""
FORMAT = "nerfpipe-checkpoint"
VERSION = 1

_OLD_FORMAT = "checkpoint is in the old pickle format, which can run code when loaded, so it is not read; retrain to write " + CHECKPOINT
_PICKLE_MAGIC = (b"PK\x03\x04", b"\x80")  # torch.save's zip archive, a bare pickle (protocol >= 2)
_SCALARS = (type(None), bool, int, float, str)


def save_checkpoint(path: "str | Path", state: dict) -> Path:
    """Write ``state`` to ``path`` atomically (see the module docstring for what it may hold).

    Example:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / CHECKPOINT
        >>> _ = save_checkpoint(path, {"model": {"w": torch.ones(2)}, "step": 3})
        >>> load_checkpoint(path)["step"]
        3
    """
    tensors: dict[str, torch.Tensor] = {}
    meta = {"format": FORMAT, "version": str(VERSION), "state": json.dumps(_encode(state, "", tensors))}
    return atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=meta))


def load_checkpoint(path: "str | Path") -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`; nothing in the file is executed.

    Raises:
        NerfpipeError: naming the file, when it is missing, an old pickle checkpoint, or not a
            nerfpipe checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise NerfpipeError("checkpoint is missing", path)
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            if meta.get("format") != FORMAT:
                raise NerfpipeError("not a nerfpipe checkpoint (a safetensors file without its state)", path)
            if int(meta.get("version", "0")) > VERSION:
                raise NerfpipeError(f"checkpoint has format version {meta['version']}, newer than this nerfpipe reads ({VERSION})", path)
            # owned, writable copies: the optimiser keeps these, and must not share pages with the file
            tensors = {name: f.get_tensor(name).clone() for name in f.keys()}
        state = _decode(json.loads(meta["state"]), tensors)
    except SafetensorError as exc:
        raise NerfpipeError(_OLD_FORMAT if _looks_pickled(path) else "not a nerfpipe checkpoint (unreadable)", path) from exc
    except (ValueError, KeyError, TypeError, RecursionError) as exc:  # JSON errors are ValueErrors
        raise NerfpipeError(f"not a nerfpipe checkpoint (malformed state: {exc})", path) from exc
    if not isinstance(state, dict) or "model" not in state:
        raise NerfpipeError("not a nerfpipe checkpoint (no model state)", path)
    return state


def find_checkpoint(run_dir: "str | Path") -> "Path | None":
    """The run folder's checkpoint, or ``None`` when there is none yet.

    Raises:
        NerfpipeError: when the folder holds only an old pickle checkpoint (resuming from
            scratch, or reporting "no checkpoint", would hide that it was refused).
    """
    path = Path(run_dir) / CHECKPOINT
    if path.is_file():
        return path
    legacy = Path(run_dir) / LEGACY_CHECKPOINT
    if legacy.is_file():
        raise NerfpipeError(_OLD_FORMAT, legacy)
    return None


def _looks_pickled(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(4)
    return head.startswith(_PICKLE_MAGIC)


def _encode(value: object, name: str, tensors: "dict[str, torch.Tensor]") -> object:
    """``value`` as JSON data; its tensors go into ``tensors`` under their path ``name``."""
    if isinstance(value, torch.Tensor):
        return {"$tensor": _put(tensors, name, value)}
    if isinstance(value, _SCALARS):
        return value
    if isinstance(value, list):
        return [_encode(v, f"{name}/{i}", tensors) for i, v in enumerate(value)]
    if isinstance(value, tuple):
        return {"$tuple": [_encode(v, f"{name}/{i}", tensors) for i, v in enumerate(value)]}
    if isinstance(value, dict):
        return _encode_dict(value, name, tensors)
    raise TypeError(f"a checkpoint holds tensors, numbers, strings, None and lists/tuples/dicts of them; {name or 'the state'} is a {type(value).__name__}")


def _encode_dict(value: dict, name: str, tensors: "dict[str, torch.Tensor]") -> dict:
    metadata = getattr(value, "_metadata", None)  # a state_dict's module versions
    plain = metadata is None and all(isinstance(k, str) and not k.startswith("$") for k in value)
    if plain:
        return {k: _encode(v, f"{name}/{k}".lstrip("/"), tensors) for k, v in value.items()}
    for key in value:
        if not isinstance(key, _SCALARS):
            raise TypeError(f"checkpoint dict keys are numbers or strings; {name} has a {type(key).__name__} key")
    out: dict = {"$items": [[k, _encode(v, f"{name}/{k}".lstrip("/"), tensors)] for k, v in value.items()]}
    if metadata is not None:
        out["$metadata"] = _encode(dict(metadata), f"{name}/$metadata", tensors)
    return out


def _put(tensors: "dict[str, torch.Tensor]", name: str, tensor: torch.Tensor) -> str:
    while name in tensors:  # e.g. keys 1 and "1" in one dict
        name += "'"
    tensor = tensor.detach().cpu().contiguous()
    storage = tensor.untyped_storage().data_ptr()
    shared = tensor.numel() == 0 or any(t.untyped_storage().data_ptr() == storage for t in tensors.values())
    tensors[name] = tensor.clone() if shared else tensor  # safetensors refuses tensors that share memory
    return name


def _decode(data: object, tensors: "dict[str, torch.Tensor]") -> object:
    """Inverse of :func:`_encode`; a malformed structure raises ``ValueError``/``KeyError``/``TypeError``."""
    if isinstance(data, list):
        return [_decode(v, tensors) for v in data]
    if not isinstance(data, dict):
        return data
    if "$tensor" in data:
        return tensors[data["$tensor"]]
    if "$tuple" in data:
        return tuple(_decode(v, tensors) for v in data["$tuple"])
    if "$items" not in data:
        return {k: _decode(v, tensors) for k, v in data.items()}
    items = [(_key(k), _decode(v, tensors)) for k, v in data["$items"]]
    if "$metadata" not in data:
        return dict(items)
    out = OrderedDict(items)  # a state_dict, as ``Module.state_dict`` returns it
    out._metadata = _decode(data["$metadata"], tensors)  # type: ignore[attr-defined]
    return out


def _key(key: object) -> object:
    if not isinstance(key, _SCALARS):
        raise TypeError(f"dict key of type {type(key).__name__}")
    return key
