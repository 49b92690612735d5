"""A rich progress bar for training: iterations (or budget seconds), live PSNR and ETA."""

import time

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn


class TrainProgress:
    """Progress over iterations, or over training seconds when a time budget is the tighter bound.

    The ETA is estimated from the recent training speed (iterations per training second), so
    validation pauses do not distort it.
    """

    def __init__(self, cfg, step: int, seconds: float) -> None:
        self.cfg = cfg
        self.start_step, self.start_seconds = step, seconds
        self.console = Console(stderr=True)
        self.progress = Progress(
            TextColumn("[bold]train"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("PSNR {task.fields[psnr]}"),
            TextColumn("ETA {task.fields[eta]}"),
            TimeElapsedColumn(),
            console=self.console,
            transient=False,
        )
        self.task = self.progress.add_task("train", total=cfg.iters, completed=step, psnr="-", eta="?")

    def __enter__(self) -> "TrainProgress":
        self.progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.stop()

    def eta(self, step: int, seconds: float) -> float:
        rate = (seconds - self.start_seconds) / max(step - self.start_step, 1)
        left = (self.cfg.iters - step) * rate
        if self.cfg.time_budget is not None:
            left = min(left, max(self.cfg.time_budget - seconds, 0.0))
        return left

    def update(self, step: int, seconds: float, psnr: float) -> None:
        eta = time.strftime("%H:%M:%S", time.gmtime(self.eta(step, seconds)))
        self.progress.update(self.task, completed=step, psnr=f"{psnr:5.2f}", eta=eta)

    def log(self, text: str) -> None:
        self.progress.console.print(text)


def track(items, description: str, total: "int | None" = None):
    """Iterate ``items`` with a progress bar on stderr (frames rendered, views fused, ...)."""
    from rich.progress import track as rich_track

    return rich_track(items, description=description, total=total, console=Console(stderr=True), transient=True)
