"""The ``nerfpipe`` command: a thin tyro entry point over the command functions.

Each subcommand is a function in ``nerfpipe/commands/<name>.py`` whose typed, documented
arguments become the CLI (tyro). Command modules import heavy libraries lazily, inside the
function, so ``nerfpipe --help`` stays fast.

User errors (:class:`~nerfpipe.util.errors.NerfpipeError`) print one line and exit 2;
``--debug`` anywhere on the command line shows the traceback instead.

The command is the one place that changes process-wide settings (:func:`nerfpipe.util.runtime.apply`:
OpenMP waiting, glibc's allocator). It does so first, before anything imports torch, which is why
this module and ``nerfpipe/__init__.py`` import nothing heavy at the top.
"""

import os
import sys
import warnings

from nerfpipe.util.errors import NerfpipeError


def _commands() -> dict:
    from nerfpipe.commands import check, demo, info, run, synth

    return {
        "info": info.info,
        "train": _train,
        "render": _render,
        "eval": __import__("nerfpipe.commands.eval", fromlist=["eval_run"]).eval_run,
        "fit2d": __import__("nerfpipe.commands.fit2d", fromlist=["fit2d"]).fit2d,
        "check": check.check,
        "synth": synth.synth,
        "demo": demo.demo,
        "run": run.run,
        "run-many": run.run_many,
        "stage": run.stage,
        "stages": run.list_stages,
        "eval-mesh": __import__("nerfpipe.commands.eval_mesh", fromlist=["eval_mesh"]).eval_mesh,
        "mesh": _mesh,
        "bench": __import__("nerfpipe.commands.bench", fromlist=["bench"]).bench,
        "view": __import__("nerfpipe.commands.view", fromlist=["view"]).view,
    }


def _train() -> int:
    """Train a radiance field on a dataset into a run folder (every TrainerConfig field and the model's config as options)."""
    return 2  # never called: ``nerfpipe train ...`` is parsed by nerfpipe.commands.train.main, from the configs


def _render() -> int:
    """Render a camera path of a trained run into RUN/render/ (every RenderConfig field as an option)."""
    return 2  # never called: nerfpipe.commands.render.main parses it, from the config


def _mesh() -> int:
    """Extract a mesh from a trained run into RUN/mesh/ (every MeshConfig field as an option, RenderedViews' as --views.*)."""
    return 2  # never called: nerfpipe.commands.mesh.main parses it, from the configs


GENERATED = {"train": ("nerfpipe.commands.train", "main"), "stage": ("nerfpipe.commands.run", "stage_main"),
             "run": ("nerfpipe.commands.run", "run_main"), "render": ("nerfpipe.commands.render", "main"),
             "mesh": ("nerfpipe.commands.mesh", "main")}
"""Subcommands that parse their command line themselves, from the config dataclasses (listed in ``nerfpipe --help``
through the entries above): their options depend on one of their own arguments (``--model``, the stage), or are a
config's fields (render, mesh), whose module imports the config and so torch, which ``nerfpipe --help`` does not need."""


def _dispatch(argv: "list[str]"):
    import importlib

    import tyro

    from nerfpipe.commands.helptext import plain_help

    with plain_help():
        if argv and argv[0] in GENERATED:
            module, function = GENERATED[argv[0]]
            return getattr(importlib.import_module(module), function)(argv[1:])
        return tyro.extras.subcommand_cli_from_dict(_commands(), args=argv, prog="nerfpipe")


def main(argv: "list[str] | None" = None) -> int:
    code = _main(argv)
    if "nerfpipe.training.distributed" in sys.modules:  # only it joins a torchrun group; importing it here would load torch
        sys.modules["nerfpipe.training.distributed"].end_process(code)  # a rank of a group ends here (nerfpipe.training.distributed.leave)
    return code


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` for the command line: ``nerfpipe: warning: MESSAGE`` on stderr."""
    print(f"nerfpipe: warning: {message}", file=sys.stderr if file is None else file)


def _main(argv: "list[str] | None") -> int:
    from nerfpipe.util import runtime

    runtime.apply()  # before torch loads OpenMP (the command's choice; importing nerfpipe makes none)
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("NERFPIPE_DEBUG") == "1"
    argv = [a for a in argv if a != "--debug"]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            if not debug:  # one line a warning, as errors are (where it was raised: with --debug)
                warnings.showwarning = _one_line_warning
            result = _dispatch(argv)
    except NerfpipeError as exc:
        if debug:
            raise
        print(f"nerfpipe: error: {_as_given(str(exc), argv)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("nerfpipe: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (``nerfpipe info --json | head``): stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit-time flush must not fail again
        return 141  # 128 + SIGPIPE, what a shell reports for a command the pipe ended
    return int(result) if isinstance(result, int) else 0


def _as_given(message: str, argv: "list[str]") -> str:
    """A parameter error (``--iters must be …``, as a config names its own field) names the option as it was typed
    when one option of ``argv`` ends with that field (``--train.trainer.iters``)."""
    import re

    m = re.search(r"--([\w-]+) must be ", message)
    if m is None:
        return message
    typed = {a.split("=", 1)[0] for a in argv if a.startswith("--")}
    given = sorted(f for f in typed if f.replace("_", "-").endswith("." + m.group(1).replace("_", "-")))
    return message.replace(f"--{m.group(1)}", given[0], 1) if len(given) == 1 else message


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
