"""A rich progress bar for training: iterations or budget seconds, live PSNR and a true ETA."""

import time

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn


class TrainProgress:
    """Progress over iterations, or over seconds when a time budget is the tighter bound.

    Three cases. With a wall-clock budget (the trainer's ``training_window``) the bar runs over wall
    seconds and the ETA is when the whole run returns: the training window (or the iterations, at the
    wall-clock speed so far, validations included, when they end sooner) plus the final phase. With a
    budget of training seconds the bar runs over training seconds. Otherwise it counts iterations, and
    the ETA follows the training speed (validation pauses excluded).
    """

    def __init__(self, cfg, step: int, seconds: float, window: "float | None" = None) -> None:
        self.cfg, self.window = cfg, window
        self.start_step, self.start_seconds, self.start_wall, self.first_step = step, seconds, None, step
        self.console = Console(stderr=True)
        self.progress = Progress(
            TextColumn("[bold]train"),
            BarColumn(),
            TextColumn("{task.fields[done]}"),
            TextColumn("PSNR {task.fields[psnr]}"),
            TextColumn("ETA {task.fields[eta]}"),
            TimeElapsedColumn(),
            console=self.console,
            transient=False,
        )
        self.task = self.progress.add_task("train", total=self.total(), completed=0, psnr="-", eta="?", done="")

    def total(self) -> float:
        if self.window is not None:
            return self.window
        return float(self.cfg.train_budget if self.cfg.train_budget is not None else self.cfg.max_iters)

    def __enter__(self) -> "TrainProgress":
        self.progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.stop()

    def eta(self, step: int, seconds: float, wall: "float | None" = None) -> float:
        """Seconds until the run returns (wall budget) or training ends (otherwise)."""
        if self.window is not None and wall is not None:
            if self.start_wall is None:  # first update: speed is measured from here (set-up is not training)
                self.start_wall, self.first_step = wall, step
                return max(self.cfg.time_budget - wall, 0.0)
            by_iters = (self.cfg.max_iters - step) * (wall - self.start_wall) / max(step - self.first_step, 1)
            return min(by_iters, max(self.window - wall, 0.0)) + (self.cfg.time_budget - self.window)
        left = (self.cfg.max_iters - step) * (seconds - self.start_seconds) / max(step - self.start_step, 1)
        if self.cfg.train_budget is not None:
            left = min(left, max(self.cfg.train_budget - seconds, 0.0))
        return left

    def completed(self, step: int, seconds: float, wall: "float | None") -> "tuple[float, str]":
        """How far the bar is, and the text beside it."""
        if self.window is not None and wall is not None:
            return min(wall, self.window), f"{wall:.0f}/{self.window:.0f} s, step {step}"
        if self.cfg.train_budget is not None:
            return min(seconds, self.cfg.train_budget), f"{seconds:.0f}/{self.cfg.train_budget:.0f} s, step {step}"
        return float(step), f"{step}/{self.cfg.max_iters}"

    def update(self, step: int, seconds: float, psnr: float, wall: "float | None" = None) -> None:
        eta = time.strftime("%H:%M:%S", time.gmtime(self.eta(step, seconds, wall)))
        completed, done = self.completed(step, seconds, wall)
        self.progress.update(self.task, completed=completed, psnr=f"{psnr:5.2f}", eta=eta, done=done)

    def log(self, text: str) -> None:
        self.progress.console.print(text)


def track(items, description: str, total: "int | None" = None):
    """Iterate ``items`` with a progress bar on stderr (frames rendered, views fused, ...)."""
    from rich.progress import track as rich_track

    return rich_track(items, description=description, total=total, console=Console(stderr=True), transient=True)
