"""Stages and the pipeline that chains them (STYLE habits 6 and 7).

A stage is one module with a config dataclass and ``run(config, ctx) -> artifacts``. It reads and
writes *named artifacts*: an artifact's name is its path relative to the run folder
(``scene.json``, ``sfm``, ``export/transforms.json``); its in-memory form (a SceneData, a mesh,
arrays) may be returned as well and is kept in :attr:`StageContext.cache`. Stages are found
through the entry-point group ``nerfpipe.stages`` as :class:`StageSpec` objects, the built-ins
included, so any stage can be re-run alone (``nerfpipe stage NAME RUN_DIR``).

Run folder layout::

    RUN_DIR/run.json                  the input and the chain (written by the pipeline)
    RUN_DIR/stages/<name>.done.json   completion marker: config, config hash, timing, artifacts
    RUN_DIR/<artifacts ...>           written atomically by the stages (:func:`atomic_path`)

Resume rule: :meth:`Pipeline.run` skips the leading stages whose marker exists with the same
config hash, is newer than the markers of the stages before it, and whose artifacts are all on
disk; from the first stage that has to run, every later stage runs too. Before the run folder is
made, the chain is checked (device, run folder, every stage's optional modules, required artifacts);
a user error (:class:`NerfpipeError`) before any stage finished removes the folder this run made. A stage interrupted
half-way leaves neither a marker nor a half-written artifact (markers are written after the
artifacts, both by ``os.replace``); the temporaries of a killed run are swept by the next one.

Under torchrun (``torchrun --nproc-per-node N -m nerfpipe run DATA``) rank 0 runs the chain as one
process would; the other ranks follow: they write nothing and take part only in the *collective*
stages (:attr:`StageSpec.collective`: ``train``, data-parallel), which rank 0 announces as it reaches
them; the scene and other inputs they read from the run folder rank 0 wrote.

One run at a time: :meth:`Pipeline.run` holds the folder's lock (:func:`nerfpipe.util.runlock.run_lock`)
from before it sweeps temporaries until the last stage ends, so a second run into the same folder
refuses instead of deleting the first one's files; a lock left by a killed run is taken over.

Glossary:
    artifact  a named output; ``produces`` lists the ones a stage must leave on disk
    marker    ``stages/<name>.done.json``
"""

import hashlib
import json
import logging
import shutil
import time
import tomllib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nerfpipe.training import distributed
from nerfpipe.util.atomic import TMP_PREFIX, atomic_path, sweep_temporaries, write_json  # noqa: F401 (re-exported for stages)
from nerfpipe.util.configs import from_dict, to_dict
from nerfpipe.util.devices import auto_device, check_device
from nerfpipe.util.errors import NerfpipeError, require_all
from nerfpipe.util.paths import check_output_folder
from nerfpipe.util.registry import STAGE_GROUP, discover
from nerfpipe.util.runlock import run_lock

MARKER_DIR = "stages"
RUN_RECORD = "run.json"
NOT_NEEDED = "not needed"
SKIPPED = "skipped"
DEFAULT_CHAIN = ("sfm", "load", "check", "train", "mesh", "render", "export", "report")
"""The chain of ``nerfpipe run`` without ``--stages`` or ``--pipeline``. The mesh comes before the orbit
render: under a time budget each takes a share of what is left, and the mesh's completeness depends on
the resolution of its TSDF views while the orbit only gets fewer or smaller frames."""

log = logging.getLogger("nerfpipe.stages")


@dataclass(frozen=True)
class StageSpec:
    """A pipeline stage registered in the ``nerfpipe.stages`` entry-point group."""

    name: str
    """Stage name used in chains, TOML files and ``nerfpipe stage NAME``."""
    description: str
    """One line for ``nerfpipe stages``."""
    config: type
    """Config dataclass; every field has a default."""
    run: Callable[[Any, "StageContext"], "dict[str, object]"]
    """``run(config, ctx) -> {artifact name: Path or in-memory object}``."""
    requires: "tuple[str, ...]" = ()
    """Artifacts that must exist (on disk in the run folder, or in the cache) before running."""
    produces: "tuple[str, ...]" = ()
    """Artifacts (paths relative to the run folder) the stage leaves on disk."""
    provides: "tuple[str, ...]" = ()
    """In-memory artifacts ``run`` returns (``scene``, ``mesh``...); ``restore`` rebuilds them from disk."""
    applies: "Callable[[StageContext], bool] | None" = None
    """Whether the stage is needed for this input (e.g. ``sfm`` only for bare photos); None: always."""
    restore: "Callable[[Any, StageContext], dict[str, object]] | None" = None
    """Rebuild the ``provides`` artifacts from the files of a finished run (for resume and re-runs)."""
    dependencies: "tuple[tuple[str, str], ...]" = ()
    """Optional modules ``(module, extra)`` the stage needs; :meth:`Pipeline.run` imports those of every
    stage of the chain before running any, so a missing one never costs the earlier stages' work."""
    shows: "tuple[Any, ...]" = ()
    """What the stage shows in report.html (:class:`nerfpipe.pipeline.report_items.Shown`: file, kind, title)."""
    light: bool = False
    """The stage takes about no time (writing files from what is in memory: ``export``, ``report``): a stage followed
    only by light ones may spend more of the time left (:meth:`StageContext.rest_is_light`)."""
    min_seconds: float = 0.0
    """Under a time budget, the seconds the stages before it leave it at least (:meth:`StageContext.time_for_stage`):
    ``render`` keeps a few for its orbit, which the mesh stage would otherwise take."""
    collective: bool = False
    """Under torchrun, every process runs the stage together (``train``: data-parallel); the others run
    on rank 0 alone. A collective stage writes only from rank 0 (:class:`nerfpipe.training.distributed.World`)."""


@dataclass
class StageContext:
    """What a running stage may use besides its config."""

    run_dir: Path
    """The run folder; artifacts live here."""
    source: "Path | None" = None
    """The input dataset file or folder (None when the input is in memory)."""
    device: str = field(default_factory=auto_device)
    """Torch device for stages that compute (a resolved name: CUDA when present, else the CPU, by default)."""
    time_budget: "float | None" = None
    """Seconds the whole pipeline may take (None: no limit); see :meth:`time_left`."""
    cache: "dict[str, object]" = field(default_factory=dict)
    """In-memory artifacts and inputs (``reconstruction``, ``image_dir``, ``scene.json`` -> SceneData...)."""
    specs: "dict[str, StageSpec]" = field(default_factory=dict)
    """Known stages, used to restore an artifact that is on disk but not in memory."""
    configs: "dict[str, object]" = field(default_factory=dict)
    """Config of each known stage, for :attr:`StageSpec.restore`."""
    started: float = field(default_factory=time.monotonic)
    log: logging.Logger = log
    following: "tuple[StageSpec, ...]" = ()
    """The stages of the chain after the running one (set by :meth:`Pipeline.run` before each stage)."""

    def rest_is_light(self) -> bool:
        """Whether only :attr:`StageSpec.light` stages follow the running one (then it may spend most of the time left)."""
        return all(spec.light for spec in self.following)

    def path(self, artifact: str) -> Path:
        """Where an artifact lives in the run folder."""
        return self.run_dir / artifact

    def _provider(self, artifact: str) -> "StageSpec | None":
        """The stage that can restore an in-memory artifact because its files are on disk."""
        for spec in self.specs.values():
            if artifact in spec.provides and spec.restore is not None and all(self.path(a).exists() for a in spec.produces):
                return spec
        return None

    def has(self, artifact: str) -> bool:
        return artifact in self.cache or self.path(artifact).exists() or self._provider(artifact) is not None

    def get(self, artifact: str) -> object:
        """An artifact: from the cache, else restored by the stage that provides it, else its path on disk."""
        if artifact in self.cache:
            return self.cache[artifact]
        spec = self._provider(artifact)
        if spec is not None:
            self.cache.update(spec.restore(self.configs.get(spec.name) or spec.config(), self))
            return self.cache[artifact]
        if not self.path(artifact).exists():
            raise NerfpipeError(f"artifact '{artifact}' is missing; run the stage that makes it first", self.run_dir)
        return self.path(artifact)

    def time_left(self) -> "float | None":
        """Seconds left of :attr:`time_budget`, never negative; None without a budget."""
        if self.time_budget is None:
            return None
        return max(0.0, self.time_budget - (time.monotonic() - self.started))

    def time_for_stage(self) -> "float | None":
        """Seconds the running stage may plan on: :meth:`time_left` less what the stages after it need at least
        (their :attr:`StageSpec.min_seconds`), of which it keeps at least half; None without a budget."""
        left = self.time_left()
        if left is None:
            return None
        return left - min(sum(spec.min_seconds for spec in self.following), 0.5 * left)


# ---------------------------------------------------------------- discovery and configs


def stages() -> "dict[str, StageSpec]":
    """All installed stages by name (broken plugins are skipped with a PluginWarning)."""
    return discover(STAGE_GROUP, StageSpec)


def config_hash(config: object) -> str:
    text = json.dumps(to_dict(config), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def make_config(spec: StageSpec, values: "dict | None", where: "str | Path | None" = None) -> object:
    """The stage's config with ``values`` (from TOML or a dict) applied; unknown keys are errors."""
    if values is not None and not isinstance(values, dict):
        raise NerfpipeError(f"options of stage '{spec.name}' must be a table of name = value, not {type(values).__name__}", where)
    return from_dict(spec.config(), values or {}, f"stage '{spec.name}'", where, table=spec.name)


# ---------------------------------------------------------------- the pipeline


@dataclass
class StageRecord:
    """What happened to one stage in a pipeline run."""

    name: str
    status: str
    """``ran``, ``skipped`` (finished before), ``not needed`` (``applies`` said no)."""
    seconds: float = 0.0
    artifacts: "list[str]" = field(default_factory=list)


@dataclass
class PipelineResult:
    """Returned by :meth:`Pipeline.run`: per-stage records, and the artifacts by name.

    ``result["scene"]`` is an in-memory artifact (restored from disk on first access when its
    stage was skipped); ``result["scene.json"]`` is the path of an on-disk one.
    """

    run_dir: Path
    records: "list[StageRecord]"
    seconds: float
    context: StageContext
    names: "list[str]"
    """Artifacts of the chain's stages (on-disk and in-memory)."""

    def keys(self) -> "list[str]":
        return [n for n in self.names if self.context.has(n)] + [k for k in self.context.cache if k not in self.names]

    def __contains__(self, name: str) -> bool:
        return name in self.keys()

    def __getitem__(self, name: str) -> object:
        if name not in self:
            raise KeyError(name)
        return self.context.get(name)


class Pipeline:
    """An ordered chain of stages with one config each.

    Example:
        >>> p = Pipeline(["load", "check", "export"], {"check": {"samples": 4}})  # doctest: +SKIP
        >>> result = p.run("data/colmap_mouse", "runs/mouse")  # doctest: +SKIP
        >>> result["scene"].cameras.shape, result["export/transforms.json"]  # doctest: +SKIP

        Another pipeline's SfM result, handed over in memory (no file written by the caller):

        >>> result = p.run(None, "runs/x", reconstruction=rec, images="photos/")  # doctest: +SKIP
    """

    def __init__(
        self,
        chain: "list[str | StageSpec]",
        configs: "dict[str, object] | None" = None,
        registry: "dict[str, StageSpec] | None" = None,
    ) -> None:
        if not chain:
            raise NerfpipeError("a pipeline needs at least one stage (e.g. --stages load,check)")
        self.registry = dict(stages() if registry is None else registry)
        self.specs: list[StageSpec] = [self._spec(s) for s in chain]
        self.registry.update({s.name: s for s in self.specs})
        configs = dict(configs or {})
        self.configs = {s.name: _as_config(s, configs.pop(s.name, None)) for s in self.specs}
        if configs:
            raise NerfpipeError(f"config given for stage(s) not in the chain: {', '.join(sorted(configs))}")

    def _spec(self, s: "str | StageSpec") -> StageSpec:
        if isinstance(s, StageSpec):
            return s
        if s not in self.registry:
            raise NerfpipeError(f"unknown stage '{s}' (installed: {', '.join(sorted(self.registry)) or 'none'})")
        return self.registry[s]

    @property
    def names(self) -> "list[str]":
        return [s.name for s in self.specs]

    @classmethod
    def from_toml(cls, path: "str | Path", registry: "dict[str, StageSpec] | None" = None, overridden: "Iterable[str]" = ()) -> "Pipeline":
        """Read ``stages = [...]`` and one ``[<stage name>]`` table of options per stage; the options named in
        ``overridden`` (dotted, ``train.trainer.iters``: the command line sets them) are left out of the file's
        values unread, so a value there that the command line replaces is not refused.

        Example file (nested config dataclasses take nested tables)::

            stages = ["sfm", "load", "check", "train", "render"]
            [sfm]
            max_image_size = 1600
            [train]
            model = "vanilla"
            [train.trainer]
            iters = 2000
        """
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise NerfpipeError(f"cannot read pipeline file ({type(exc).__name__}: {exc})", path) from exc
        for key in overridden:
            *tables, name = key.split(".")
            table = doc
            for t in tables:
                table = table.get(t) if isinstance(table, dict) else None
            if isinstance(table, dict) and tables:
                table.pop(name, None)
        chain = doc.pop("stages", None)
        if not isinstance(chain, list) or not all(isinstance(s, str) for s in chain) or not chain:
            raise NerfpipeError("a pipeline file needs 'stages = [\"load\", ...]', a list of stage names", path)
        bad = [k for k, v in doc.items() if not isinstance(v, dict)]
        if bad:
            raise NerfpipeError(f"'{bad[0]}' must be a table [{bad[0]}] of stage options", path)
        pipe = cls(chain, registry=registry)
        extra = sorted(set(doc) - set(pipe.names))
        if extra:
            raise NerfpipeError(f"options for stage '{extra[0]}', which is not in 'stages'", path)
        pipe.configs.update({s.name: make_config(s, doc.get(s.name), path) for s in pipe.specs})
        return pipe

    def validate(self, ctx: StageContext) -> None:
        """Fail before running anything when a stage needs an artifact nothing provides."""
        available = set(ctx.cache)
        for spec in self.specs:
            missing = [a for a in spec.requires if a not in available and not ctx.has(a)]
            if missing:
                makers = [s.name for s in self.registry.values() if missing[0] in s.produces + s.provides]
                hint = f" (produced by: {', '.join(makers)})" if makers else ""
                raise NerfpipeError(f"stage '{spec.name}' needs '{missing[0]}', which no earlier stage produces{hint}")
            available.update(spec.produces + spec.provides)

    def context(self, run_dir: "str | Path", source: "str | Path | None" = None, **kw) -> StageContext:
        return StageContext(
            run_dir=Path(run_dir), source=None if source is None else Path(source),
            specs=self.registry, configs=self.configs, **kw,
        )

    def run(
        self,
        source: "str | Path | None",
        run_dir: "str | Path",
        *,
        resume: bool = True,
        cache: "dict[str, object] | None" = None,
        device: str = "auto",
        time_budget: "float | None" = None,
        on_stage: "Callable[[StageRecord], None] | None" = None,
        reconstruction: object = None,
        images: "str | Path | dict | None" = None,
        started: "float | None" = None,
    ) -> PipelineResult:
        """Run the chain in ``run_dir``, skipping stages finished before when ``resume``.

        Args:
            source: the input dataset; None when the input comes in memory.
            run_dir: the run folder (created).
            resume: skip the leading stages that finished with the same config.
            cache: in-memory inputs and artifacts handed to the stages (e.g. ``scene``).
            device: torch device for the stages that compute (``auto``: CUDA when present, else the CPU).
            time_budget: seconds the whole run may take; stages read :meth:`StageContext.time_left`.
            on_stage: called after each stage with its record (for progress output).
            reconstruction: an in-memory ``pycolmap.Reconstruction`` to use as the input.
            images: its images: a folder, or ``{image name: uint8 array [H, W, 3]}``.
            started: when ``time_budget`` began (a ``time.monotonic()`` value; default now): a command gives its
                process's start, so that the budget holds from the user's command to the last file.
        """
        if time_budget is not None and not time_budget > 0:  # before anything is written (NaN included)
            raise NerfpipeError(f"--time-budget must be a positive number of seconds, got {time_budget}")
        cache = dict(cache or {})
        cache.update({k: v for k, v in (("reconstruction", reconstruction), ("images", images)) if v is not None})
        ctx = self.context(check_output_folder(run_dir, "the run folder"), source, device=check_device(device), time_budget=time_budget, cache=cache,
                           **({} if started is None else {"started": started}))
        require_all(tuple(d for s in self.specs for d in s.dependencies))
        self.validate(ctx)
        world = distributed.world(ctx.device) if distributed.env_world().active else distributed.SINGLE
        if not world.writer:
            return self._follow(ctx)
        created = not ctx.run_dir.exists()
        with run_lock(ctx.run_dir):  # makes the folder; taken before the sweep: the temporaries of a live run are not stale
            if (ctx.run_dir / RUN_RECORD).is_file():  # only a folder nerfpipe ran in holds temporaries of ours
                sweep_temporaries(ctx.run_dir)
            t0 = time.monotonic()
            try:
                _check_run_record(ctx, self.names, resume)
                records = self._run_chain(ctx, resume, on_stage)
                if world.active:  # not after an error: the other ranks may be inside a collective, and end with this process
                    distributed.broadcast_object(None)
            except NerfpipeError:
                if created and not any((read_marker(ctx, n) or {}).get("status") == "ran" for n in self.names):
                    shutil.rmtree(ctx.run_dir, ignore_errors=True)  # a refused input, no stage's work: leave no folder behind
                raise
        names = [a for s in self.specs for a in s.produces + s.provides]
        return PipelineResult(ctx.run_dir, records, time.monotonic() - t0, ctx, names)

    def run_many(self, sources: "list[str | Path]", out: "str | Path", config: object = None, on_update: "Callable | None" = None) -> list:
        """Run the chain on every source, one Ray task each, into ``out/<source name>`` (resuming each).

        Args:
            sources: dataset folders or files.
            out: folder of the run folders, ``index.html`` (links to every ``report.html``) and ``run_many.json``.
            config: a :class:`nerfpipe.pipeline.many.ManyConfig`: Ray address, CPUs and GPUs per run, retries, time budget.
            on_update: called with the :class:`nerfpipe.pipeline.many.RunOutcome` list whenever one changes.

        Returns:
            One :class:`nerfpipe.pipeline.many.RunOutcome` per source, in order (``status`` ``done`` or ``failed``).

        Needs Ray (``pip install nerfpipe[scale]``); see :mod:`nerfpipe.pipeline.many`.
        """
        from nerfpipe.pipeline.many import run_many

        return run_many(self, sources, out, config, on_update)

    def _follow(self, ctx: StageContext) -> PipelineResult:
        """Ranks 1 .. N-1 under torchrun: run the collective stages rank 0 announces, until it says the chain ended."""
        records, t0 = [], time.monotonic()
        while (name := distributed.broadcast_object(None)) is not None:
            spec, start = self.registry[name], time.monotonic()
            spec.run(self.configs[name], ctx)
            records.append(StageRecord(name, "ran", time.monotonic() - start))
        names = [a for s in self.specs for a in s.produces + s.provides]
        return PipelineResult(ctx.run_dir, records, time.monotonic() - t0, ctx, names)

    def _run_chain(self, ctx: StageContext, resume: bool, on_stage) -> "list[StageRecord]":
        records, running, last = [], not resume, 0.0
        for k, spec in enumerate(self.specs):
            ctx.following = tuple(self.specs[k + 1 :])
            config = self.configs[spec.name]
            done = None if running else is_done(ctx, spec, config, after=last)
            if done is not None:
                last = done.get("finished_at", 0.0)
                status = NOT_NEEDED if done.get("status") == NOT_NEEDED else SKIPPED
                rec = StageRecord(spec.name, status, artifacts=list(done.get("artifacts", [])))
                ctx.log.info("stage %s: finished before, skipped", spec.name)
            else:
                running = True
                rec = run_stage(spec, config, ctx)
            records.append(rec)
            if on_stage is not None:
                on_stage(rec)
        return records


def _as_config(spec: StageSpec, value: object) -> object:
    if value is None or isinstance(value, dict):
        return make_config(spec, value)
    if not isinstance(value, spec.config):
        raise NerfpipeError(f"config of stage '{spec.name}' must be a {spec.config.__name__}, not {type(value).__name__}")
    return value


def _check_run_record(ctx: StageContext, chain: "list[str]", resume: bool) -> None:
    """Refuse to resume a run folder made from another input; record this run's input and chain."""
    record = ctx.run_dir / RUN_RECORD
    source = None if ctx.source is None else str(ctx.source.resolve())
    if resume and record.is_file():
        old = json.loads(record.read_text())
        if old.get("source") != source:
            raise NerfpipeError(
                f"this run folder was made from {old.get('source')}, not {source}; use another output folder or no resume",
                ctx.run_dir,
            )
    write_json(record, {"source": source, "chain": chain})


def marker_path(ctx: StageContext, name: str) -> Path:
    return ctx.run_dir / MARKER_DIR / f"{name}.done.json"


def read_marker(ctx: StageContext, name: str) -> "dict | None":
    try:
        done = json.loads(marker_path(ctx, name).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return done if isinstance(done, dict) else None


def is_done(ctx: StageContext, spec: StageSpec, config: object, after: float = 0.0) -> "dict | None":
    """The marker, when it has this config's hash, is newer than ``after`` and the artifacts are on disk."""
    done = read_marker(ctx, spec.name)
    if done is None or done.get("config_hash") != config_hash(config) or done.get("finished_at", 0.0) < after:
        return None
    if done.get("status") != NOT_NEEDED and not all(ctx.path(a).exists() for a in spec.produces):
        return None
    return done


def run_stage(spec: StageSpec, config: object, ctx: StageContext) -> StageRecord:
    """Run one stage now (no resume check): remove its marker, run, verify artifacts, write the marker."""
    marker = marker_path(ctx, spec.name)
    marker.unlink(missing_ok=True)
    if spec.applies is not None and not spec.applies(ctx):
        ctx.log.info("stage %s: not needed for this input", spec.name)
        _write_marker(marker, spec, config, NOT_NEEDED, 0.0, [])
        return StageRecord(spec.name, NOT_NEEDED)
    missing = [a for a in spec.requires if not ctx.has(a)]
    if missing:
        raise NerfpipeError(f"stage '{spec.name}' needs artifact '{missing[0]}', which is missing", ctx.run_dir)
    ctx.log.info("stage %s: running", spec.name)
    t0 = time.monotonic()
    if spec.collective and distributed.env_world().active:
        distributed.broadcast_object(spec.name)  # the other ranks of the torchrun group join in (Pipeline._follow)
    out = spec.run(config, ctx) or {}
    seconds = time.monotonic() - t0
    for name, value in out.items():
        if not isinstance(value, Path):
            ctx.cache[name] = value
    absent = [a for a in spec.produces if not ctx.path(a).exists()]
    if absent:
        raise NerfpipeError(f"stage '{spec.name}' finished without writing '{absent[0]}'", ctx.run_dir)
    _write_marker(marker, spec, config, "ran", seconds, list(spec.produces))
    ctx.log.info("stage %s: done in %.1f s", spec.name, seconds)
    return StageRecord(spec.name, "ran", seconds, list(spec.produces))


def _write_marker(marker: Path, spec: StageSpec, config: object, status: str, seconds: float, artifacts: "list[str]") -> None:
    write_json(marker, {
        "stage": spec.name, "status": status, "config": to_dict(config), "config_hash": config_hash(config),
        "seconds": round(seconds, 3), "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "finished_at": time.time(),
        "artifacts": artifacts,
    })  # fmt: skip
