"""Many captures, one pipeline each, as Ray tasks (``nerfpipe run-many``, :meth:`Pipeline.run_many`).

Each capture is one Ray task that runs the whole chain into ``OUT/<capture name>`` with the
resources asked for (``cpus_per_run``, ``gpus_per_run``); Ray places the tasks on a local Ray
started for the call (``address=None``: at most the machine's CPUs, no dashboard, no usage
reporting, nothing downloaded) or on an existing cluster (``address="auto"`` or ``"ray://host:10001"``;
nerfpipe and the captures must then be reachable from every node, e.g. installed and on a shared
file system).

A worker that dies (killed, out of memory, a lost node) makes Ray run the task again, up to
``max_retries`` times; the new attempt resumes the run folder as ``nerfpipe run`` does: finished
stages are skipped by their markers and training continues from its last checkpoint
(``metrics.json`` ``resumed_at`` holds the step). An error of the capture itself (a
:class:`~nerfpipe.util.errors.NerfpipeError`: a broken image, a missing file) is not retried: it is that
capture's result, and the others go on.

While the tasks run, the driver shows a table read from the run folders (stage markers and the
attempt records); at the end it writes ``OUT/index.html``, one page linking every run's
``report.html`` with its headline figures, and ``OUT/run_many.json``.

Glossary:
    capture   one input (dataset folder or file); its run folder is ``OUT/<name>``
    attempt   one execution of a capture's task; ``OUT/.attempts/<name>.json`` lists them
"""

import html
import json
import os
import socket
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from nerfpipe.util.atomic import atomic_write, write_json
from nerfpipe.util.errors import NerfpipeError, require_all

RAY = (("ray", "scale"),)
"""The optional module ``run_many`` needs, with its extra (``pip install nerfpipe[scale]``)."""
INDEX = "index.html"
SUMMARY = "run_many.json"
ATTEMPTS = ".attempts"


@dataclass
class ManyConfig:
    """How ``run_many`` places the captures' tasks."""

    address: "str | None" = None
    """Ray cluster to use: None starts a local Ray for this call; ``auto`` (the cluster this machine
    belongs to) or ``ray://host:10001`` (Ray Client) uses an existing one."""
    cpus_per_run: float = 1.0
    """CPUs reserved for each capture's task (also its torch threads)."""
    gpus_per_run: float = 0.0
    """GPUs reserved for each capture's task (> 0: the task trains on ``cuda``)."""
    max_retries: int = 2
    """Times a task whose worker died is run again (resuming its run folder)."""
    num_cpus: "int | None" = None
    """CPUs of the local Ray (None: the machine's); ignored with an ``address``."""
    time_budget: "float | None" = None
    """Seconds each capture's pipeline may take (as ``nerfpipe run --time-budget``)."""
    poll_seconds: float = 1.0
    """How often the live table is refreshed."""

    def __post_init__(self) -> None:
        from nerfpipe.util.errors import refuse_unless

        refuse_unless([
            ("cpus_per_run", self.cpus_per_run > 0, "positive", self.cpus_per_run),
            ("gpus_per_run", self.gpus_per_run >= 0, "0 or more", self.gpus_per_run),
            ("max_retries", self.max_retries >= 0, "0 or more", self.max_retries),
            ("num_cpus", self.num_cpus is None or self.num_cpus >= 1, "at least 1", self.num_cpus),
            ("time_budget", self.time_budget is None or self.time_budget > 0, "positive seconds", self.time_budget),
        ])  # fmt: skip


@dataclass
class RunOutcome:
    """What became of one capture."""

    name: str
    source: str
    run_dir: str
    status: str = "queued"
    """``queued``, ``running``, ``done`` or ``failed``."""
    error: str = ""
    attempts: int = 0
    seconds: float = 0.0
    stages: "dict[str, str]" = field(default_factory=dict)
    """Stage name -> ``ran``, ``skipped`` or ``not needed`` (of the last attempt)."""
    figures: "dict[str, float]" = field(default_factory=dict)
    """Headline figures (``val_psnr``, ``iterations``, ``resumed_at``) from the run folder."""


# ---------------------------------------------------------------- the task


def run_capture(pipeline, source: str, run_dir: str, attempts_file: str, device: str, threads: int, time_budget) -> dict:
    """One capture's pipeline, resumed from what the folder holds; runs in a Ray worker.

    Records the attempt first (``attempts_file``), so a retried task shows how often it ran."""
    import torch

    previous = _read_json(Path(attempts_file)) or []
    record = {"attempt": len(previous) + 1, "pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
    write_json(attempts_file, [*previous, record])
    torch.set_num_threads(max(1, threads))  # this worker's own process, reserved for the task
    result = pipeline.run(source, run_dir, device=device, time_budget=time_budget)
    return {"stages": {r.name: r.status for r in result.records}, "seconds": result.seconds}


# ---------------------------------------------------------------- the driver


def run_many(pipeline, sources: "list[str | Path]", out: "str | Path", config: "ManyConfig | None" = None,
             on_update: "Callable[[list[RunOutcome]], None] | None" = None) -> "list[RunOutcome]":
    """Run ``pipeline`` on every source as a Ray task; returns one outcome per source (in order).

    Args:
        pipeline: a :class:`nerfpipe.pipeline.stages.Pipeline` (sent to the workers).
        sources: dataset folders or files; each runs into ``out/<its name>``.
        out: the folder of the run folders, ``index.html`` and ``run_many.json``.
        config: placement and retries (:class:`ManyConfig`).
        on_update: called with the outcomes whenever one changes (the CLI's live table).
    """
    cfg = config or ManyConfig()
    out = Path(out)
    outcomes = plan(sources, out)
    require_all(RAY)
    import ray

    started = _start_ray(ray, cfg)
    try:
        refs = _submit(ray, pipeline, outcomes, out, cfg)
        _follow(ray, refs, outcomes, out, cfg, on_update)
    finally:
        if started:
            ray.shutdown()
    write_index(out, outcomes)
    return outcomes


def plan(sources: "list[str | Path]", out: Path) -> "list[RunOutcome]":
    """One outcome per source, refused before anything runs: a missing source, two with one name."""
    if not sources:
        raise NerfpipeError("give at least one capture (a dataset folder or file)")
    outcomes, names = [], {}
    for src in map(Path, sources):
        if not src.exists():
            raise NerfpipeError("no such file or folder", src)
        name = src.stem
        if name in names:
            raise NerfpipeError(f"two captures are named '{name}' ({names[name]} and {src}); their run folders would collide", src)
        names[name] = src
        outcomes.append(RunOutcome(name, str(src.resolve()), str((out / name).resolve())))
    return outcomes


def _start_ray(ray, cfg: ManyConfig) -> bool:
    """Connect to the cluster, or start a local Ray; True when this call started it (and stops it)."""
    if ray.is_initialized():
        return False
    key, before = "RAY_USAGE_STATS_ENABLED", os.environ.get("RAY_USAGE_STATS_ENABLED")
    os.environ[key] = before or "0"  # read by the processes ray.init starts: no usage report sent (unless asked for)
    try:
        if cfg.address is not None:
            ray.init(address=cfg.address, log_to_driver=False, configure_logging=False)
        else:
            cpus = cfg.num_cpus or os.cpu_count() or 1
            ray.init(num_cpus=cpus, num_gpus=None if cfg.gpus_per_run else 0, include_dashboard=False, log_to_driver=False,
                     configure_logging=False, object_store_memory=100 * 2**20)  # results are small dicts: the minimum store
    finally:
        if before is None:  # the host process's environment as it was
            del os.environ[key]
    return True


def _submit(ray, pipeline, outcomes: "list[RunOutcome]", out: Path, cfg: ManyConfig) -> dict:
    task = ray.remote(run_capture).options(
        num_cpus=cfg.cpus_per_run, num_gpus=cfg.gpus_per_run, max_retries=cfg.max_retries, retry_exceptions=False,
    )
    device = "cuda" if cfg.gpus_per_run > 0 else "cpu"
    (out / ATTEMPTS).mkdir(parents=True, exist_ok=True)
    piped = ray.put(pipeline)
    refs = {}
    for o in outcomes:
        attempts = out / ATTEMPTS / f"{o.name}.json"
        attempts.unlink(missing_ok=True)
        refs[task.remote(piped, o.source, o.run_dir, str(attempts), device, max(1, int(cfg.cpus_per_run)), cfg.time_budget)] = o
    return refs


def _follow(ray, refs: dict, outcomes: "list[RunOutcome]", out: Path, cfg: ManyConfig, on_update) -> None:
    """Wait for the tasks, refreshing every outcome from its folder between waits."""
    t0, pending, shown = time.monotonic(), list(refs), None
    while pending:
        ready, pending = ray.wait(pending, num_returns=1, timeout=cfg.poll_seconds)
        for ref in ready:
            _finish(ray, ref, refs[ref], out)
        for o in outcomes:
            if o.status not in ("done", "failed"):
                _refresh(o, out, time.monotonic() - t0)
        now = json.dumps([asdict(o) for o in outcomes])
        if on_update is not None and now != shown:
            on_update(outcomes)
            shown = now


def _finish(ray, ref, o: RunOutcome, out: Path) -> None:
    try:
        result = ray.get(ref)
        o.status, o.stages, o.seconds = "done", result["stages"], result["seconds"]
    except ray.exceptions.RayTaskError as exc:  # the capture's own error: one line
        cause = exc.cause if getattr(exc, "cause", None) is not None else exc
        o.status, o.error = "failed", " ".join(str(cause).split())[:300]
    except ray.exceptions.RayError as exc:  # the worker died once more than max_retries allow
        o.status, o.error = "failed", f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}"
    o.attempts = len(_read_json(out / ATTEMPTS / f"{o.name}.json") or [])
    o.figures = figures(Path(o.run_dir))


def _refresh(o: RunOutcome, out: Path, elapsed: float) -> None:
    """A running capture's state from disk: its attempts and the stages whose markers exist."""
    from nerfpipe.pipeline.stages import MARKER_DIR

    o.attempts = len(_read_json(out / ATTEMPTS / f"{o.name}.json") or [])
    if o.attempts:
        o.status, o.seconds = "running", elapsed
    markers = Path(o.run_dir) / MARKER_DIR
    done = sorted(markers.glob("*.done.json"), key=lambda p: p.stat().st_mtime) if markers.is_dir() else []
    o.stages = {p.name.removesuffix(".done.json"): "done" for p in done}


def figures(run_dir: Path) -> "dict[str, float]":
    """Headline figures of a run folder (what exists of them)."""
    metrics = _read_json(run_dir / "train" / "metrics.json") or {}
    keep = ("val_psnr", "val_ssim", "iterations", "train_seconds", "resumed_at")
    return {k: metrics[k] for k in keep if k in metrics}


def _read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


# ---------------------------------------------------------------- the index


def write_index(out: Path, outcomes: "list[RunOutcome]") -> Path:
    """``OUT/index.html`` (a table linking every run's report) and ``OUT/run_many.json``."""
    write_json(out / SUMMARY, [asdict(o) for o in outcomes])
    rows = "\n".join(_index_row(out, o) for o in outcomes)
    done = sum(o.status == "done" for o in outcomes)
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>nerfpipe run-many: {html.escape(out.name)}</title>
<style>body{{font-family:sans-serif;margin:2em}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 10px;text-align:left}} .failed{{color:#b00}}</style></head>
<body><h1>nerfpipe run-many</h1><p>{done} of {len(outcomes)} captures done; written {time.strftime("%Y-%m-%d %H:%M:%S")}</p>
<table><tr><th>capture</th><th>status</th><th>attempts</th><th>val PSNR (dB)</th><th>iterations</th><th>resumed at step</th><th>seconds (last attempt)</th><th>report</th></tr>
{rows}
</table></body></html>
"""
    return atomic_write(out / INDEX, lambda p: p.write_text(page))


def _index_row(out: Path, o: RunOutcome) -> str:
    from nerfpipe.pipeline.report import REPORT_FILE

    f, esc = o.figures, html.escape
    report = Path(o.run_dir) / REPORT_FILE
    link = f'<a href="{esc(os.path.relpath(report, out))}">report.html</a>' if report.is_file() else "not produced"
    psnr = f"{f['val_psnr']:.2f}" if "val_psnr" in f else ""
    status = esc(o.status) + (f'<br><span class="failed">{esc(o.error)}</span>' if o.error else "")
    resumed = ", ".join(str(s) for s in f.get("resumed_at", []))
    return (f"<tr><td>{esc(o.name)}</td><td>{status}</td><td>{o.attempts}</td><td>{psnr}</td><td>{f.get('iterations', '')}</td>"
            f"<td>{resumed}</td><td>{o.seconds:.0f}</td><td>{link}</td></tr>")
