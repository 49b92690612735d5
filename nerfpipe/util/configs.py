"""Config dataclasses to JSON-friendly dicts and back: the one converter of nerfpipe.

Run folders (``config.json``), stage markers and their hashes, pipeline TOML files and model
options all go through :func:`to_dict` and :func:`from_dict`. Nested config dataclasses become
nested tables, tuples become lists and paths strings; on the way back unknown keys are one clear
error naming the option and the file, lists become tuples where the field takes one and strings
become paths where it takes a :class:`~pathlib.Path`.
"""

import dataclasses
import json
import re
import types
import typing
from pathlib import Path
from typing import Annotated

import tyro

from nerfpipe.util.atomic import _json_default
from nerfpipe.util.errors import NerfpipeError


JsonTable = Annotated[dict, tyro.constructors.PrimitiveConstructorSpec(
    nargs=1, metavar="JSON", instance_from_str=lambda args: _json_table(args[0]), is_instance=lambda x: isinstance(x, dict),
    str_from_instance=lambda x: [json.dumps(x)])]
"""A free-form table field of a config (e.g. a model's options): a JSON object on the command line."""


def _json_table(text: str) -> dict:
    try:
        value = json.loads(text)
    except ValueError as exc:
        raise NerfpipeError(f"not a JSON object: {text!r} ({exc})") from exc
    if not isinstance(value, dict):
        raise NerfpipeError(f"not a JSON object: {text!r}")
    return value


def to_dict(config: object) -> dict:
    """A (nested) config dataclass as JSON-friendly data.

    Example:
        >>> @dataclasses.dataclass
        ... class Toy:
        ...     size: tuple = (2, 3)
        ...     out: Path = Path("runs")
        >>> to_dict(Toy())
        {'size': [2, 3], 'out': 'runs'}
    """
    return json.loads(json.dumps(dataclasses.asdict(config), default=_json_default))


def from_dict(
    default: object, values: dict, what: "str | None" = None, where: "str | Path | None" = None, dropped: "list[str] | None" = None,
    table: "str | None" = None,
) -> object:
    """``default`` (a config dataclass instance, or its class for the class's defaults) with ``values`` applied.

    Args:
        default: the config to start from.
        values: option name -> value, as :func:`to_dict` writes them; nested configs take nested tables.
        what: how errors name the config (default: its class name).
        where: the file the values came from, named in errors.
        dropped: for values an earlier nerfpipe wrote (a run's ``config.json``): unknown options (one this version
            no longer has) are left out and their dotted names appended here, instead of refused.
        table: the dotted name of ``values``' table in that file (``train.trainer``): a value the config refuses is
            named by its key there (``train.trainer.iters must be 0 or more``), not by the config's own option.

    Raises:
        NerfpipeError: an unknown option (unless ``dropped`` is given), or a value the config refuses.
    """
    if isinstance(default, type):
        default = default()
    what = what or default.__class__.__name__
    if not isinstance(values, dict):
        raise NerfpipeError(f"{what} must be a table of name = value, not {type(values).__name__}", where)
    hints = typing.get_type_hints(type(default))
    names = [f.name for f in dataclasses.fields(default)]
    unknown = sorted(set(values) - set(names))
    if unknown and dropped is None:
        raise NerfpipeError(f"{what} has no option {unknown[0]!r} (options: {', '.join(names)})", where)
    if unknown:
        dropped.extend(unknown)
    inner = {key: [] for key in values if key in names}
    values = {key: _value(getattr(default, key), hints[key], value, f"{what} option '{key}'", where, None if dropped is None else inner[key],
                          None if table is None else f"{table}.{key}")
              for key, value in values.items() if key in names}  # fmt: skip
    if dropped is not None:
        dropped.extend(f"{key}.{name}" for key, names_ in inner.items() for name in names_)
    try:
        return dataclasses.replace(default, **values)
    except (TypeError, ValueError) as exc:  # a value of the wrong type or range meets the config's own checks
        raise NerfpipeError(f"{what}: {(str(exc).strip().splitlines() or [type(exc).__name__])[0]}", where) from exc
    except NerfpipeError as exc:  # the config's own check of a value: name the file it came from
        if exc.path is not None or where is None:
            raise
        problem = exc.problem if table is None else re.sub(r"^--([\w-]+) must be ", lambda m: f"{table}.{m.group(1).replace('-', '_')} must be ", exc.problem)
        raise NerfpipeError(problem, where) from exc


def _value(current: object, hint: object, value: object, what: str, where: "str | Path | None", dropped: "list[str] | None" = None,
           table: "str | None" = None) -> object:
    """One option's value from its JSON/TOML form, by the field's current value and type hint (``dropped`` and
    ``table``: as :func:`from_dict`'s, for a nested config)."""
    if hint in _SCALARS and not _SCALARS[hint](value):
        raise NerfpipeError(f"{what} must be {hint.__name__}, not {type(value).__name__} ({value!r})", where)
    if isinstance(value, dict) and dataclasses.is_dataclass(current):
        return from_dict(current, value, what, where, dropped, table)
    if isinstance(value, dict) and isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return from_dict(hint, value, what, where, dropped, table)
    if isinstance(value, list) and (isinstance(current, tuple) or _accepts(hint, tuple)):
        return tuple(value)  # JSON and TOML have no tuples
    if isinstance(value, str) and (isinstance(current, Path) or (_accepts(hint, Path) and not _accepts(hint, str))):
        return Path(value)
    return value


_SCALARS = {
    bool: lambda v: isinstance(v, bool),
    int: lambda v: isinstance(v, int) and not isinstance(v, bool),
    float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    str: lambda v: isinstance(v, str),
}
"""Plain scalar fields and the JSON/TOML values they take (an int where a float goes, not a bool for an int)."""


def _accepts(hint: object, kind: type) -> bool:
    """Whether a type hint is ``kind`` (or generic over it), or a union with one (``tuple[int, ...] | None``)."""
    if hint is kind or typing.get_origin(hint) is kind:
        return True
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return any(_accepts(a, kind) for a in typing.get_args(hint))
    return False
