"""The one error type that reaches users.

Every problem caused by the user's input (a file, a flag, a dataset) is raised as
:class:`NerfpipeError` naming the file and the problem. The CLI prints it as one
line and exits non-zero; ``--debug`` shows the traceback.
"""

from pathlib import Path


class NerfpipeError(Exception):
    """A user-facing error: ``"<path>: <problem>"``.

    Args:
        problem: what is wrong, in one sentence a user can act on.
        path: the file or folder at fault, if any.
    """

    def __init__(self, problem: str, path: "str | Path | None" = None) -> None:
        self.problem = problem
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class MissingDependencyError(NerfpipeError):
    """An optional dependency is not installed."""

    def __init__(self, module: str, extra: str) -> None:
        super().__init__(f"this needs the optional dependency '{module}': pip install 'nerfpipe[{extra}]'")


def require(module: str, extra: str):
    """Import an optional dependency lazily, or fail with an actionable message.

    Example:
        >>> np = require("numpy", "core")
    """
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(module, extra) from exc


Dependencies = "tuple[tuple[str, str], ...]"
"""``((module, extra), ...)``: the optional modules an output needs, as :func:`require` takes them."""


def require_all(dependencies: "Dependencies") -> None:
    """Import every optional dependency now, or fail with the first missing one.

    Called before training or any other long work, so a missing writer (the MP4 encoder, the
    plotting library) is reported before there is a result to lose, not when it is written.

    Example:
        >>> require_all((("numpy", "core"), ("json", "core")))
    """
    for module, extra in dependencies:
        require(module, extra)


def refuse_unless(checks) -> None:
    """Each check ``(name, ok, what, value)``: when not ``ok``, ``"--<name> must be <what>, got <value>"``.

    The one shape of a parameter error, used by every config's ``__post_init__`` and command, so an
    impossible value (a negative budget, zero frames, NaN) stops before anything runs or is written.

    Example:
        >>> refuse_unless([("iters", 10 >= 0, "0 or more", 10)])
    """
    for name, ok, what, value in checks:
        if not ok:
            raise NerfpipeError(f"--{name.replace('_', '-')} must be {what}, got {value}")
