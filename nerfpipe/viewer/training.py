"""The viewer watching a training run (``nerfpipe train --view``, the train stage's ``view``).

Rendering shares the CPU with training, so it is done in the training thread, between steps (an
``AFTER_TRAIN_ITERATION`` hook), in the small units of :class:`~nerfpipe.viewer.progressive.ProgressiveRenderer`,
only while the time spent rendering stays under ``share`` of the time since training started: the
training loses at most about ``share`` of its iterations per second to the live view (plus viser's
own thread, which only sends what changed). Rendering between steps also means the model is never
read while the optimiser writes it. The model's random stream is put back after each render, so a
watched run trains exactly as an unwatched one.

The panel's "Training" folder shows the step, iterations per second and the PSNR curves
(training batches and validation), refreshed every ``plot_every`` seconds.
"""

import time

import numpy as np

from nerfpipe.models.base import Callback


class TrainingView:
    """Attach a :class:`~nerfpipe.viewer.server.Viewer` to a :class:`~nerfpipe.training.trainer.Trainer`.

    Args:
        trainer: the training to watch (its model is rendered live).
        viewer: a viewer of the trainer's scene whose ``render`` renders ``trainer.model``.
        share: the most of the training time spent rendering.
        plot_every: seconds between refreshes of the curves.
    """

    def __init__(self, trainer, viewer, share: float = 0.04, plot_every: float = 2.0) -> None:
        self.trainer, self.viewer, self.share, self.plot_every = trainer, viewer, share, plot_every
        self.render_seconds = 0.0
        """Time spent rendering in the training thread."""
        self._start: "float | None" = None
        self._last_plot = -1e9
        gui = viewer.server.gui
        with gui.add_folder("Training"):
            self.text = gui.add_markdown("starting")
            self.plot = gui.add_uplot(
                data=(np.zeros(1), np.zeros(1), np.full(1, np.nan)),
                series=({"label": "step"}, {"label": "train PSNR", "stroke": "#1f77b4", "width": 1}, {"label": "val PSNR", "stroke": "#d62728", "width": 2, "points": {"show": True}}),
                title="PSNR (dB)", aspect=1.6,
            )  # fmt: skip
        trainer.hooks.setdefault(Callback.AFTER_TRAIN_ITERATION, []).append(self.after_step)
        trainer.hooks.setdefault(Callback.AFTER_TRAIN, []).append(self.after_train)

    def after_step(self, step: int) -> None:
        now = time.perf_counter()
        if self._start is None:
            self._start = now
        if self.render_seconds < self.share * (now - self._start):
            self._render_some(now)
        if now - self._last_plot >= self.plot_every:
            self._last_plot = now
            self.update_panel(step, now - self._start)

    def after_train(self, step: int) -> None:
        elapsed = time.perf_counter() - self._start if self._start is not None else 0.0
        share = self.render_seconds / elapsed if elapsed > 0 else 0.0
        print(f"nerfpipe: the live view rendered {self.render_seconds:.1f} s of the {elapsed:.1f} s of training ({100 * share:.1f} %)", flush=True)

    def _render_some(self, now: float) -> None:
        """Units of render work until the time spent reaches ``share`` of the elapsed (one unit at least)."""
        generator = getattr(self.trainer.model, "generator", None)
        state = generator.get_state() if generator is not None else None
        try:
            while self.render_seconds < self.share * (now - self._start):
                t = time.perf_counter()
                worked = [r.step() for r in self.viewer.renderers()]
                self.render_seconds += time.perf_counter() - t
                if not any(worked):
                    break
        finally:
            if state is not None:
                generator.set_state(state)

    def update_panel(self, step: int, seconds: float) -> None:
        train = self.trainer.history["train"]
        val = {int(row[0]): row[2] for row in self.trainer.history["val"]}
        if train:
            rows = np.asarray(train, dtype=np.float64)[-2000:]
            steps = rows[:, 0]
            val_col = np.array([val.get(int(s), np.nan) for s in steps])
            self.plot.data = (steps, rows[:, 2], val_col)
        its = step / seconds if seconds > 0 else 0.0
        last_val = f", val PSNR {list(val.values())[-1]:.2f} dB" if val else ""
        share = self.render_seconds / seconds if seconds > 0 else 0.0
        self.text.content = f"step **{step}**, {its:.1f} it/s{last_val}; live render {100 * share:.1f} % of the time"
        for r in self.viewer.renderers():
            if not r.busy:
                r.refresh(again=True)  # the field moved on: show it again


def watch(trainer, host: str = "127.0.0.1", port: int = 7007, share: float = 0.04) -> TrainingView:
    """Start a viewer of a trainer's scene and model and attach it (prints the URL)."""
    from nerfpipe.data.background import background_colors
    from nerfpipe.viewer.server import Viewer
    from nerfpipe.viewer.source import model_renderer

    bg = background_colors(trainer.eval_bg, 1)[0]
    viewer = Viewer(trainer.scene, model_renderer(trainer.model, bg, trainer.cfg.device), host, port, trainer.out / "camera_path.json", max_size=256)
    print(f"nerfpipe: watching the training at {viewer.url}", flush=True)
    return TrainingView(trainer, viewer, share)


def train_watched(trainer, view: bool, port: int = 7007) -> "dict | None":
    """``trainer.train()``, shown in a viewer while it runs when ``view`` (on rank 0 of a torchrun group
    only); the page closes with the training."""
    watcher = watch(trainer, port=port) if view and trainer.world.writer else None
    try:
        return trainer.train()
    finally:
        if watcher is not None:
            watcher.viewer.stop()


__all__ = ["TrainingView", "train_watched", "watch"]
