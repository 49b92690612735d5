"""``nerfpipe run``, ``nerfpipe stage`` and ``nerfpipe stages``: the pipeline from the command line."""

import json
import logging
import warnings
from pathlib import Path
from typing import Annotated

import tyro

Positional = tyro.conf.Positional


def _console():
    """Rich console on stdout; 120 columns when not a terminal (logs, pipes, tests)."""
    import sys

    from rich.console import Console

    return Console(highlight=False, width=None if sys.stdout.isatty() else 120)


def _log_to(console) -> None:
    """Show the stages' INFO log lines through rich (once per process)."""
    from rich.logging import RichHandler

    logger = logging.getLogger("nerfpipe")
    if not any(isinstance(h, RichHandler) for h in logger.handlers):
        logger.addHandler(RichHandler(console=console, show_path=False, show_level=False))
    logger.setLevel(logging.INFO)


def installed_stages(console) -> dict:
    """Discover stages; broken plugins are printed as one warning line each, not raised."""
    from nerfpipe.pipeline.stages import stages

    return _reporting(console, stages)


def _reporting(console, find):
    """``find()`` with its PluginWarnings printed as one line each (other warnings re-raised)."""
    from nerfpipe.util.registry import PluginWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PluginWarning)
        found = find()
    for w in caught:
        if issubclass(w.category, PluginWarning):
            console.print(f"[yellow]warning:[/] {w.message}")
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return found


def _summary_table(result):
    from rich.table import Table

    table = Table(title=f"nerfpipe run: {result.run_dir}")
    for col in ("stage", "status", "seconds", "artifacts"):
        table.add_column(col, justify="right" if col == "seconds" else "left")
    for rec in result.records:
        table.add_row(rec.name, rec.status, f"{rec.seconds:.1f}", ", ".join(rec.artifacts))
    table.add_row("total", "", f"{result.seconds:.1f}", "", end_section=True)
    return table


def _figures(run_dir: Path) -> "list[str]":
    """One line per headline figure found in the run folder (SfM, check, training)."""
    lines, read = [], lambda p: json.loads(p.read_text()) if p.is_file() else None  # noqa: E731
    if (sfm := read(run_dir / "sfm" / "sfm.json")) is not None and "num_registered" not in sfm:
        lines.append(f"sfm: {sfm['num_points3D']} points triangulated with the poses of {sfm.get('num_triangulated_photos', sfm['num_photos'])} "
                     f"of {sfm['num_photos']} photos")
    elif sfm is not None:
        lines.append(f"sfm: {sfm['num_registered']} of {sfm['num_photos']} photos registered, {sfm['num_points3D']} points")
    if (check := read(run_dir / "check.json")) is not None:
        lines.append(f"check: {check['num_cameras']} cameras, conventions consistent (kornia {check['kornia_max_px']:.1e} px)")
    if (metrics := read(run_dir / "train" / "metrics.json")) is not None:
        from nerfpipe.training.evaluation import fitted_figure_note

        lines.append(f"train: val PSNR {metrics['val_psnr']:.2f} dB{fitted_figure_note(metrics)} after {metrics['iterations']} iterations")
    if (mesh := read(run_dir / "mesh" / "mesh_metrics.json")) is not None:
        lines.append(_mesh_line(mesh))
    if (run_dir / "report.html").is_file():
        lines.append(f"report: {(run_dir / 'report.html').resolve()}")
    return lines


def _mesh_line(m: dict) -> str:
    """The mesh figures against the reference: F-score and Chamfer (gt mesh), sparse points within threshold."""
    parts = []
    if "fscore" in m:
        parts.append(f"F-score@1% {m['fscore']:.3f}, Chamfer-L1 {m['chamfer_l1']:.4f} (against {m.get('reference')})")
    if "points_within_threshold" in m:
        parts.append(f"{100 * m['points_within_threshold']:.1f}% of {m['points_used']} sparse points within {m['points_threshold']:.4f}")
    return "mesh: " + "; ".join(parts)


def _pipeline(stages: "str | None", pipeline: "Path | None", registry: dict, overridden: "tuple[str, ...]" = ()):
    from nerfpipe.pipeline.stages import DEFAULT_CHAIN, Pipeline
    from nerfpipe.util.errors import NerfpipeError

    if stages is not None and pipeline is not None:
        raise NerfpipeError("give --stages or --pipeline, not both")
    if pipeline is not None:
        return Pipeline.from_toml(pipeline, registry=registry, overridden=overridden)
    chain = DEFAULT_CHAIN if stages is None else [s.strip() for s in stages.split(",") if s.strip()]
    return Pipeline(list(chain), registry=registry)


def run(
    path: Annotated[Path, Positional],
    stages: "str | None" = None,
    pipeline: "Path | None" = None,
    out: "Path | None" = None,
    time_budget: "float | None" = None,
    resume: bool = True,
    device: str = "auto",
) -> int:
    """Run the pipeline on a dataset, a folder of photos or a video, resuming a previous run (every stage's options
    as --STAGE.OPTION: nerfpipe run --help).

    Args:
        path: dataset (COLMAP folder, transforms.json, .npz), a folder of photos or a video (SfM runs first, on its sharpest frames).
        stages: comma-separated chain, e.g. ``load,check,export`` (none: sfm,load,check,train,render,mesh,export,report).
        pipeline: TOML file with ``stages = [...]`` and one ``[stage]`` table of options each (the defaults of the --STAGE.* options).
        out: run folder (none: ``runs/<input name>``).
        time_budget: seconds the whole run may take, counted from the command's start (stages that can, stop early).
        resume: skip stages that finished before with the same options.
        device: torch device for the stages that compute (auto: CUDA when present, else CPU; printed at start).
    """
    return 2  # never called: ``nerfpipe run ...`` is parsed by :func:`run_main`, from the stages' configs


def run_command_type(registry: dict, defaults: "dict[str, object]") -> type:
    """:func:`run`'s options and one group per installed stage, ``--STAGE.FIELD`` for every field of its config
    (nested configs nested further), at the values of ``defaults`` (a pipeline file's) or the config's."""
    import dataclasses
    import inspect

    import typing

    hints = typing.get_type_hints(run, include_extras=True)
    base = [(name, hints[name], dataclasses.field(default=p.default)) if p.default is not inspect.Parameter.empty else (name, hints[name])
            for name, p in inspect.signature(run).parameters.items()]
    docs = _arg_docs(run)
    base = [(b[0], Annotated[b[1], tyro.conf.arg(help=docs.get(b[0]))], *b[2:]) for b in base]
    groups = [(name, Annotated[spec.config, tyro.conf.arg(help=f"Options of the {name} stage: {spec.description}.")],
               dataclasses.field(default_factory=lambda d=defaults.get(name) or spec.config(): d))
              for name, spec in sorted(registry.items()) if name not in dict.fromkeys(b[0] for b in base)]
    return dataclasses.make_dataclass("RunCommand", base + groups)


def _arg_docs(fn) -> "dict[str, str]":
    """``Args:`` entries of a Google-style docstring."""
    import re

    section = (fn.__doc__ or "").split("Args:", 1)[-1]
    from nerfpipe.commands.helptext import plain

    return {m.group(1): plain(m.group(2)) for m in re.finditer(r"^\s{8}(\w+): (.+?)(?=^\s{8}\w+: |\Z)", section, re.S | re.M)}


def _option_value(argv: "list[str]", name: str) -> "str | None":
    for i, arg in enumerate(argv):
        if arg == name and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith(name + "="):
            return arg.split("=", 1)[1]
    return None


def given_stage_options(argv: "list[str]") -> "tuple[str, ...]":
    """The stage options set on the command line, dotted with underscores: ``--train.trainer.time-budget=9`` ->
    ``train.trainer.time_budget``."""
    names = (a[2:].split("=", 1)[0] for a in argv if a.startswith("--"))
    return tuple(n.replace("-", "_") for n in names if "." in n)


def run_main(argv: "list[str]") -> int:
    """``nerfpipe run PATH [--stages ...|--pipeline FILE] [--STAGE.OPTION VALUE ...]``: a pipeline file's
    options are the defaults, the command line changes them."""
    from nerfpipe.util.errors import NerfpipeError

    console = _console()
    registry = installed_stages(console)
    toml = _option_value(argv, "--pipeline")
    given = given_stage_options(argv)
    defaults = dict(_pipeline(None, Path(toml), registry, given).configs) if toml is not None and "--help" not in argv else {}
    cmd = tyro.cli(run_command_type(registry, defaults), args=argv, prog="nerfpipe run")
    if not Path(cmd.path).exists():
        raise NerfpipeError("no such file or folder", cmd.path)
    _log_to(console)
    pipe = _pipeline(cmd.stages, cmd.pipeline, registry, given)
    pipe.configs.update({name: getattr(cmd, name) for name in pipe.names if hasattr(cmd, name)})
    run_dir = cmd.out if cmd.out is not None else Path("runs") / Path(cmd.path).stem
    from nerfpipe.commands.train import budget_start
    from nerfpipe.util.devices import check_device

    run_and_print(pipe, cmd.path, run_dir, console, resume=cmd.resume, device=check_device(cmd.device), time_budget=cmd.time_budget,
                  started=budget_start())  # from the command's start to its exit
    return 0


def run_and_print(pipe, path, run_dir: Path, console, **options):
    """``pipe.run(path, run_dir, **options)`` with the chain, the stage table and the headline figures printed
    (by rank 0 alone under torchrun)."""
    from nerfpipe.training.distributed import env_world

    if not env_world().writer:
        logging.getLogger("nerfpipe").setLevel(logging.WARNING)
        return pipe.run(path, run_dir, **options)
    from nerfpipe.util.devices import check_device, describe

    console.print(describe(check_device(options.get("device", "auto"))))
    console.print(f"chain: {' -> '.join(pipe.names)}   run folder: {run_dir}")
    result = pipe.run(path, run_dir, **options)
    console.print(_summary_table(result))
    for line in _figures(result.run_dir):
        console.print(line)
    return result


def run_many(
    paths: Annotated["tuple[Path, ...]", Positional],
    out: Path = Path("runs"),
    stages: "str | None" = None,
    pipeline: "Path | None" = None,
    address: "str | None" = None,
    cpus_per_run: float = 1.0,
    gpus_per_run: float = 0.0,
    max_retries: int = 2,
    num_cpus: "int | None" = None,
    time_budget: "float | None" = None,
) -> int:
    """Run the pipeline on many captures, one Ray task each (needs ``pip install nerfpipe[scale]``).

    Each capture runs into OUT/<name>, resuming what is there; a task whose worker dies runs again and
    resumes. A table follows the runs; OUT/index.html links every run's report.html.

    Args:
        paths: dataset folders or files (one run each).
        out: folder of the run folders and of index.html.
        stages: comma-separated chain (default: the whole pipeline).
        pipeline: TOML file with the chain and the stages' options.
        address: an existing Ray cluster (``auto`` or ``ray://host:10001``); default: a local Ray for this command.
        cpus_per_run: CPUs reserved for each capture (its torch threads too).
        gpus_per_run: GPUs reserved for each capture (> 0: it trains on cuda).
        max_retries: times a capture whose worker died is run again.
        num_cpus: CPUs of the local Ray (default: the machine's).
        time_budget: seconds each capture's pipeline may take.
    """
    from nerfpipe.pipeline.many import ManyConfig

    cfg = ManyConfig(address=address, cpus_per_run=cpus_per_run, gpus_per_run=gpus_per_run, max_retries=max_retries,
                     num_cpus=num_cpus, time_budget=time_budget)
    console = _console()
    pipe = _pipeline(stages, pipeline, installed_stages(console))
    console.print(f"chain: {' -> '.join(pipe.names)}   {len(paths)} captures into {out}")
    with _LiveTable(console) as live:
        outcomes = pipe.run_many(list(paths), out, cfg, on_update=live.update)
    console.print(f"index: {(Path(out) / 'index.html').resolve()}")
    return 0 if all(o.status == "done" for o in outcomes) else 1


class _LiveTable:
    """The captures' table, redrawn in place on a terminal, printed on each change otherwise (logs)."""

    def __init__(self, console) -> None:
        self.console, self.live, self.last, self.states = console, None, None, None

    def __enter__(self) -> "_LiveTable":
        if self.console.is_terminal:
            from rich.live import Live

            self.live = Live(console=self.console, refresh_per_second=2).__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self.live is not None:
            self.live.__exit__(*exc)
        elif self.last is not None:
            self.console.print(self.last)

    def update(self, outcomes) -> None:
        table = _many_table(outcomes)
        if self.live is not None:
            self.live.update(table)
            return
        self.last, states = table, [f"{o.name} {o.status}" + (f" ({', '.join(o.stages)})" if o.stages else "")
                                    + (f", attempt {o.attempts}" if o.attempts > 1 else "") for o in outcomes]
        if states != self.states:  # a log gets a line when a capture's state changes, not on every poll
            self.states = states
            done = sum(o.status in ("done", "failed") for o in outcomes)
            self.console.print(f"run-many: {done}/{len(outcomes)} finished; " + "; ".join(states))


def _many_table(outcomes):
    from rich.table import Table

    table = Table(title="nerfpipe run-many")
    for col in ("capture", "status", "attempts", "stages done", "val PSNR", "seconds"):
        table.add_column(col, justify="right" if col in ("attempts", "val PSNR", "seconds") else "left")
    for o in outcomes:
        psnr = f"{o.figures['val_psnr']:.2f}" if "val_psnr" in o.figures else ""
        status = o.status + (f": {o.error[:60]}" if o.error else "")
        table.add_row(o.name, status, str(o.attempts), ", ".join(o.stages), psnr, f"{o.seconds:.0f}")
    return table


def stage(name: Annotated[str, Positional], run_dir: Annotated[Path, Positional]) -> int:
    """Re-run one stage alone in an existing run folder (with the options it last ran with, or as given).

    Args:
        name: stage name (see ``nerfpipe stages``); ``nerfpipe stage NAME --help`` lists its options.
        run_dir: a run folder made by ``nerfpipe run``.
    """
    return 2  # never called: ``nerfpipe stage ...`` is parsed by :func:`stage_main`, from the stage's config


def stage_command_type(registry: dict, last: "dict[str, object]") -> object:
    """One subcommand per stage: ``RUN_DIR`` and every field of the stage's config as an option (nested
    configs with their prefix), at the values of ``last`` (the options it last ran with) or the defaults."""
    import dataclasses
    from typing import Union

    members = []
    for name, spec in sorted(registry.items()):
        default = last.get(name) or spec.config()
        options = Annotated[spec.config, tyro.conf.arg(name="")]  # the stage's own fields unprefixed, nested ones prefixed
        cls = dataclasses.make_dataclass(f"Stage_{name}", [
            ("run_dir", Annotated[Path, Positional, tyro.conf.arg(metavar="RUN_DIR", help="A run folder made by nerfpipe run.")]),
            ("options", options, dataclasses.field(default_factory=lambda d=default: d)),
        ])
        cls.stage_name = name
        members.append(Annotated[cls, tyro.conf.subcommand(name, description=spec.description)])
    return Union[tuple(members)]  # noqa: UP007 (a runtime-built union)


def _positionals(argv: "list[str]") -> "list[str]":
    return [a for a in argv if not a.startswith("-")]


def stage_main(argv: "list[str]") -> int:
    """``nerfpipe stage NAME RUN_DIR [--OPTION VALUE ...]``: the stage's options start at the values it last
    ran with in RUN_DIR (its marker), the command line changes them."""
    from nerfpipe.pipeline.stages import RUN_RECORD, Pipeline, make_config, marker_path, read_marker, run_stage
    from nerfpipe.util.errors import NerfpipeError
    from nerfpipe.util.runlock import run_lock

    console = _console()
    registry = installed_stages(console)
    words = _positionals(argv)
    if words and words[0] not in registry:
        raise NerfpipeError(f"unknown stage '{words[0]}' (installed: {', '.join(sorted(registry))})")
    last, source = {}, None
    if len(words) >= 2 and words[0] in registry and "--help" not in argv and "-h" not in argv:
        name, run_dir = words[0], Path(words[1])
        record = run_dir / RUN_RECORD
        if not record.is_file():
            raise NerfpipeError(f"not a run folder (no {RUN_RECORD})", run_dir)
        try:
            source = json.loads(record.read_text())["source"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise NerfpipeError(f"not a run record ({type(exc).__name__}: {exc})", record) from exc
        ctx = Pipeline([name], registry=registry).context(run_dir, source)
        done = read_marker(ctx, name)
        if done:
            last[name] = make_config(registry[name], done.get("config"), marker_path(ctx, name))
    parsed = tyro.cli(stage_command_type(registry, last), args=argv, prog="nerfpipe stage")
    name, run_dir = parsed.stage_name, Path(parsed.run_dir)
    _log_to(console)
    pipe = Pipeline([name], registry=registry)
    ctx = pipe.context(run_dir, source)
    config = parsed.options  # checked by its own __post_init__ when tyro made it
    with run_lock(run_dir):  # not while a run or another stage works in this folder
        rec = run_stage(pipe.specs[0], config, ctx)
    console.print(f"stage {rec.name}: {rec.status} in {rec.seconds:.1f} s -> {', '.join(rec.artifacts) or 'nothing'}")
    return 0


def list_stages() -> int:
    """List the installed plugins: stages, data adapters and models; broken ones are reported and skipped."""
    from rich.table import Table

    from nerfpipe.data_adapters import adapters
    from nerfpipe.models.registry import models

    console = _console()
    table = Table(title="stages (nerfpipe.stages)")
    for col in ("name", "description", "requires", "produces", "module"):
        table.add_column(col)
    for name, spec in sorted(installed_stages(console).items()):
        produces = ", ".join(spec.produces + spec.provides)
        table.add_row(name, spec.description, ", ".join(spec.requires), produces, spec.run.__module__)
    console.print(table)
    for title, found in (("data adapters (nerfpipe.data_adapters)", adapters), ("models (nerfpipe.models)", models)):
        small = Table(title=title)
        small.add_column("name")
        small.add_column("description")
        for name, spec in sorted(_reporting(console, found).items()):
            small.add_row(name, spec.description)
        console.print(small)
    return 0
