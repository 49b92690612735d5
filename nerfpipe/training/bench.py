"""Speed against error of the NeRF models: each preset trained once, scored at several time budgets.

Run: ``nerfpipe bench PATH --out DIR --budgets 20 60 600`` (or ``python -m nerfpipe.training.bench``).
Every preset (the classic ``vanilla`` and the ``fast`` field at several sizes) trains in one run;
when its training seconds pass a budget, the model as it is then is scored on the validation views
(render time excluded from the training seconds) and training goes on to the next budget.
Writes ``table.md``, ``table.json`` and ``psnr_vs_seconds.png`` (val PSNR against training
seconds, marker area following model MB) to DIR, with each preset's progress images under
``DIR/<preset>/``. The load average is recorded with every row: wall-clock seconds are inflated on a
shared machine, so CPU seconds of the process are recorded too, and ``clock="cpu"`` budgets by
them (divided by the thread count).
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path


COUNTED_STEPS = 4
"""Training steps after each budget whose ATen ops and host syncs are counted (:mod:`nerfpipe.training.opcount`)."""

PROFILED_STEPS = 8
"""On CUDA, training steps after those whose GPU busy share and kernel launches are measured under torch's profiler
(:func:`nerfpipe.training.opcount.gpu_profile`). They train on off the budget's clock (the profiler would add its own
overhead to it): each later budget of a CUDA run gets these few steps more than its seconds bought."""

PRESET_NAMES = ("vanilla", "fast-small", "fast-medium", "fast-large")
"""Default presets; ``fast`` (capacity chosen from the scene) is also available."""


def resolve_preset(name: str):
    """``(model name, model config, trainer overrides)`` of a preset, with optional model-option
    overrides after a colon: ``fast-small:distortion_weight=0.001,tv_weight=1e-5``."""
    import dataclasses

    from nerfpipe.util.errors import NerfpipeError

    from nerfpipe.models.registry import presets as named_presets

    base, _, options = name.partition(":")
    presets = named_presets()
    if base not in presets:
        raise NerfpipeError(f"unknown bench preset {base!r}; choose from {', '.join(presets)}")
    model_name, model_cfg, over = presets[base].model, presets[base].config, dict(presets[base].trainer)
    for item in filter(None, options.split(",")):
        key, _, value = item.partition("=")
        if key not in {f.name for f in dataclasses.fields(model_cfg)}:
            raise NerfpipeError(f"bench preset {name!r}: {model_name} has no option {key!r}")
        kind = type(getattr(model_cfg, key))
        try:
            model_cfg = dataclasses.replace(model_cfg, **{key: kind(value) if kind in (int, float, str) else float(value)})
        except ValueError as exc:
            raise NerfpipeError(f"bench preset {name!r}: {key}={value!r} is not a {kind.__name__}") from exc
    return model_name, model_cfg, over


@dataclass
class BenchConfig:
    """What to benchmark."""

    budgets: "tuple[float, ...]" = (20.0, 60.0, 600.0)
    """Training seconds at which each preset is scored."""
    presets: "tuple[str, ...]" = PRESET_NAMES
    """Presets to train: vanilla, fast-small, fast-medium, fast-large."""
    eval_views: int = 0
    """Validation views scored at each budget (0: all)."""
    eval_scale: float = 1.0
    """Resolution factor of the validation renders."""
    threads: int = 2
    """torch CPU threads."""
    clock: str = "wall"
    """Budget clock: ``wall`` seconds, or ``cpu`` (process CPU seconds / threads; fairer on a busy machine)."""
    seed: int = 0
    device: str = "auto"
    """Torch device (auto: CUDA when present, else CPU)."""
    rays_per_step: "int | None" = None
    """Override every preset's rays per step."""
    cuda_graph: "bool | None" = None
    """Replay each training step as a CUDA graph (``TrainerConfig.cuda_graph``; None: on CUDA)."""
    cache_rays: "bool | None" = None
    """Keep every training pixel's ray on the device (``TrainerConfig.cache_rays``; None: on CUDA where they fit)."""

    def __post_init__(self) -> None:
        from nerfpipe.util.devices import check_device
        from nerfpipe.util.errors import refuse_unless

        refuse_unless((
            ("budgets", len(self.budgets) > 0 and all(b > 0 for b in self.budgets), "positive seconds", self.budgets),
            ("presets", len(self.presets) > 0, "at least one preset", self.presets),
            ("eval_views", self.eval_views >= 0, "0 or more", self.eval_views),
            ("eval_scale", 0 < self.eval_scale <= 16, "a positive factor (at most 16)", self.eval_scale),
            ("threads", self.threads >= 1, "at least 1", self.threads), ("clock", self.clock in ("wall", "cpu"), "wall or cpu", self.clock),
            ("rays_per_step", self.rays_per_step is None or self.rays_per_step >= 1, "at least 1", self.rays_per_step),
        ))  # fmt: skip
        check_device(self.device)


@dataclass
class _Clock:
    kind: str
    threads: int
    wall: float = 0.0
    cpu: float = 0.0

    def add(self, wall: float, cpu: float) -> None:
        self.wall += wall
        self.cpu += cpu

    @property
    def seconds(self) -> float:
        return self.cpu / self.threads if self.kind == "cpu" else self.wall


def _trainer(scene, name: str, cfg: BenchConfig, out: Path):
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    model_name, model_cfg, over = resolve_preset(name)
    if cfg.rays_per_step:
        over = dict(over, rays_per_step=cfg.rays_per_step)
    tcfg = TrainerConfig(
        iters=10**9, eval_every=0, video_frames=0, checkpoint_every=0, seed=cfg.seed, device=cfg.device,
        eval_scale=cfg.eval_scale, cuda_graph=cfg.cuda_graph, cache_rays=cfg.cache_rays, **over,
    )
    return Trainer(tcfg, scene, model_name, model_cfg, out / name.replace(":", "__").replace(",", "_"))


def _score(trainer, cfg: BenchConfig, name: str, budget: float, clock: _Clock) -> dict:
    from nerfpipe.training import evaluation
    from nerfpipe.util import runtime

    t0 = time.perf_counter()
    psnr, ssim = evaluation.validate(trainer, cfg.eval_views)
    stats = trainer.model.stats()
    return {
        "preset": name, "budget_s": budget, "clock": clock.kind, "clock_s": clock.seconds, "train_s": clock.wall, "train_cpu_s": clock.cpu,
        "iterations": trainer.step, "val_psnr": psnr, "val_ssim": ssim,
        "model_params": int(stats.get("model_params", 0)), "model_mb": float(stats.get("model_mb", 0.0)),
        "occupied_fraction": stats.get("occupied_fraction"), "samples_per_ray": stats.get("samples_per_ray"),
        "finest_resolution": stats.get("finest_resolution"),
        "eval_s": time.perf_counter() - t0, "loadavg": os.getloadavg()[0], "omp_wait": runtime.OMP_WAIT,
        **({} if trainer.graph is None else {**trainer.graph.stats(), "graph_failed": trainer.graph.failed}),
    }


def bench_preset(scene, name: str, cfg: BenchConfig, out: Path, on_row=None) -> "list[dict]":
    """Train one preset until the last budget, scoring it as each budget passes (``on_row(row)`` after each)."""
    trainer = _trainer(scene, name, cfg, out)
    trainer.out.mkdir(parents=True, exist_ok=True)
    trainer.model.train()
    import torch

    from nerfpipe.training.opcount import count_steps, gpu_profile

    clock, rows = _Clock(cfg.clock, cfg.threads), []

    def step() -> None:
        w0, c0 = time.perf_counter(), time.process_time()
        trainer.train_step()
        clock.add(time.perf_counter() - w0, time.process_time() - c0)

    for budget in sorted(cfg.budgets):
        while clock.seconds < budget:
            step()
        rows.append(_score(trainer, cfg, name, budget, clock))
        r = rows[-1]
        r.update(count_steps(step, COUNTED_STEPS).row())  # the next steps (training goes on), after the score
        if torch.device(trainer.cfg.device).type == "cuda":
            r["peak_gpu_mb"] = torch.cuda.max_memory_allocated(trainer.cfg.device) / 2**20
            r.update(gpu_profile(trainer.train_step, PROFILED_STEPS, trainer.cfg.device))  # off the clock: see PROFILED_STEPS
        print(f"{name:12s} {budget:6g} s: {r['val_psnr']:.2f} dB after {r['iterations']} it "
              f"({r['train_s']:.0f} s wall, load {r['loadavg']:.1f}, OpenMP waits: {r['omp_wait']})", flush=True)
        if on_row is not None:
            on_row(r)
    return rows


def write_table(rows: "list[dict]", out: Path, scene_name: str, cfg: BenchConfig) -> None:
    """table.json, table.md and psnr_vs_seconds.png in ``out`` (written atomically)."""
    from nerfpipe.util.atomic import atomic_write, write_json

    write_json(out / "table.json", {"scene": scene_name, "config": dataclasses.asdict(cfg), "rows": rows})
    lines = [
        f"# Speed against error on {scene_name}", "",
        "| preset | budget s | train s (wall) | CPU s | iters | val PSNR | SSIM | params | MB | finest level | occupied | samples/ray | ATen ops/step | syncs/step | "
        "kernel launches/step | GPU busy | peak GPU MB | load | OpenMP waits |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    for r in rows:
        lines.append(
            f"| {r['preset']} | {r['budget_s']:g} | {r['train_s']:.1f} | {r['train_cpu_s']:.1f} | {r['iterations']} | "
            f"{r['val_psnr']:.2f} | {r['val_ssim']:.3f} | {r['model_params']:,} | {r['model_mb']:.1f} | {fmt(r.get('finest_resolution'), '.0f')} | "
            f"{fmt(r['occupied_fraction'], '.3f')} | {fmt(r['samples_per_ray'], '.1f')} | {fmt(r.get('aten_ops_per_step'), '.0f')} | "
            f"{fmt(r.get('host_syncs_per_step'), '.1f')} | {fmt(r.get('kernel_launches_per_step'), '.0f')} | {fmt(r.get('gpu_busy_share'), '.0%')} | "
            f"{fmt(r.get('peak_gpu_mb'), '.0f')} | {r['loadavg']:.1f} | {r.get('omp_wait', '-')} |"
        )
    atomic_write(out / "table.md", lambda p: Path(p).write_text("\n".join(lines) + "\n"))
    plot(rows, out / "psnr_vs_seconds.png", scene_name)


def plot(rows: "list[dict]", path: Path, title: str) -> None:
    """Val PSNR against training seconds, one line per preset, marker area ~ model MB."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name in dict.fromkeys(r["preset"] for r in rows):
        mine = [r for r in rows if r["preset"] == name]
        xs, ys = [r["clock_s"] for r in mine], [r["val_psnr"] for r in mine]
        sizes = [20 + 4 * r["model_mb"] for r in mine]
        line = ax.plot(xs, ys, "-", alpha=0.6)[0]
        ax.scatter(xs, ys, s=sizes, color=line.get_color(), alpha=0.7, label=f"{name} ({mine[-1]['model_mb']:.0f} MB)")
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # label the budgets instead
    budgets = sorted({r["budget_s"] for r in rows})
    ax.set_xticks(budgets, [f"{b:g}" for b in budgets])
    ax.set_xlabel("training seconds" + (" (CPU s / threads)" if rows and rows[0]["clock"] == "cpu" else ""))
    ax.set_ylabel("val PSNR (dB)")
    ax.set_title(f"{title}: speed against error (marker area ~ model MB)")
    ax.grid(True, which="both", alpha=0.3)
    legend = ax.legend(fontsize=8, loc="lower right")
    for handle in legend.legend_handles:  # one marker size in the legend: the areas are in the plot
        handle.set_sizes([40])
    fig.tight_layout()
    from nerfpipe.util.atomic import atomic_write

    atomic_write(path, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)


def run(path: Path, out: Path, cfg: BenchConfig) -> "list[dict]":
    """Benchmark every preset of ``cfg`` on the dataset at ``path``; returns the table rows."""
    from nerfpipe.data_adapters import load

    from nerfpipe.training import evaluation
    from nerfpipe.training.trainer import TrainerConfig
    from nerfpipe.util.errors import require_all
    from nerfpipe.util.paths import check_output_folder
    from nerfpipe.util.scoped import torch_threads

    for name in cfg.presets:
        resolve_preset(name)  # every name is checked before anything trains
    check_output_folder(out)
    require_all(evaluation.dependencies(TrainerConfig(video_frames=0)))  # scores and the table's figure
    scene = load(path)
    out.mkdir(parents=True, exist_ok=True)
    rows: "list[dict]" = []
    def on_row(row: dict) -> None:  # partial tables survive an interrupted run
        rows.append(row)
        write_table(rows, out, Path(path).name, cfg)

    with torch_threads(cfg.threads):  # handed back after (a caller's own count stays)
        for name in cfg.presets:
            bench_preset(scene, name, cfg, out, on_row)
    return rows


def main() -> None:
    import tyro

    @dataclass
    class Args:
        path: Path
        out: Path = Path("bench_out")
        cfg: BenchConfig = field(default_factory=BenchConfig)

    a = tyro.cli(Args)
    run(a.path, a.out, a.cfg)


if __name__ == "__main__":
    main()
