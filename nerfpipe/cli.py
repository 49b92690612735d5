"""The ``nerfpipe`` command: a thin tyro entry point over the command functions.

Each subcommand is a function in ``nerfpipe/commands/<name>.py`` whose typed, documented
arguments become the CLI (tyro). Command modules import heavy libraries lazily, inside the
function, so ``nerfpipe --help`` stays fast.

User errors (:class:`~nerfpipe.errors.NerfpipeError`) print one line and exit 2;
``--debug`` anywhere on the command line shows the traceback instead.

The command is the one place that changes process-wide settings (:func:`nerfpipe.runtime.apply`:
OpenMP waiting, glibc's allocator). It does so first, before anything imports torch, which is why
this module and ``nerfpipe/__init__.py`` import nothing heavy at the top.
"""

import os
import sys
import warnings

from nerfpipe.errors import NerfpipeError


def _commands() -> dict:
    from nerfpipe.commands import check, demo, info, run, synth

    return {
        "info": info.info,
        "train": __import__("nerfpipe.commands.train", fromlist=["train"]).train,
        "render": __import__("nerfpipe.commands.render", fromlist=["render"]).render,
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
        "mesh": __import__("nerfpipe.commands.mesh", fromlist=["mesh"]).mesh,
        "bench": __import__("nerfpipe.commands.bench", fromlist=["bench"]).bench,
        "view": __import__("nerfpipe.commands.view", fromlist=["view"]).view,
    }


def main(argv: "list[str] | None" = None) -> int:
    from nerfpipe import runtime

    runtime.apply()  # before torch loads OpenMP (the command's choice; importing nerfpipe makes none)
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("NERFPIPE_DEBUG") == "1"
    argv = [a for a in argv if a != "--debug"]
    import tyro

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            result = tyro.extras.subcommand_cli_from_dict(_commands(), args=argv, prog="nerfpipe")
    except NerfpipeError as exc:
        if debug:
            raise
        print(f"nerfpipe: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("nerfpipe: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (``nerfpipe info --json | head``): stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit-time flush must not fail again
        return 141  # 128 + SIGPIPE, what a shell reports for a command the pipe ended
    return int(result) if isinstance(result, int) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
