"""Fitting an :class:`ImageField` to one image: random pixel batches, Adam, full-image PSNR.

Timing: ``train_seconds`` counts only optimisation steps (and a one-off encoding cache);
periodic full-image evaluation for the PSNR curve is timed separately (``eval_seconds``).
"""

import time
from dataclasses import dataclass, field
from collections.abc import Callable

import numpy as np
import torch

from nerfpipe.encoders import GridEncoder, is_static
from nerfpipe.functional.metrics import psnr_from_mse
from nerfpipe.image_field.field import ImageFieldConfig
from nerfpipe.util.scoped import seeded_init
from nerfpipe.util.typing import Float, Tensor, UInt8


@dataclass
class TrainConfig:
    """Optimisation of a 2D field."""

    iterations: int = 3000
    """Adam steps."""
    lr: float = 1e-2
    """Adam learning rate."""
    lr_final_factor: float = 1.0
    """Exponential decay from ``lr`` to ``lr * lr_final_factor`` over the run (1 = constant)."""
    batch_size: int = 10_000
    """Random pixels per step (drawn with replacement); 0 or >= H·W uses every pixel each step."""
    adam_eps: float = 1e-8
    """Adam epsilon (grid encoders like a tiny one, 1e-15)."""
    num_evals: int = 30
    """Full-image PSNR evaluations spread over the run (plus iteration 0 and the snapshots)."""
    num_snapshots: int = 5
    """Reconstructions kept for ``progress.png``, at geometrically spaced iterations."""
    max_seconds: "float | None" = None
    """Stop when the training time reaches this many seconds (None: run all iterations)."""
    seed: int = 0
    """Seed of the weight initialisation and the pixel sampler."""
    eval_chunk: int = 65536
    """Pixels per forward pass when rendering the full image."""


@dataclass
class FitResult:
    """What a fit produced: the PSNR curve, snapshots, and the final reconstruction."""

    curve_iterations: "list[int]" = field(default_factory=list)
    curve_seconds: "list[float]" = field(default_factory=list)
    """Training seconds (evaluation excluded) at each evaluation."""
    curve_psnr: "list[float]" = field(default_factory=list)
    snapshots: "dict[int, np.ndarray]" = field(default_factory=dict)
    """Iteration -> uint8 ``[H, W, 3]`` reconstruction."""
    final: "np.ndarray | None" = None
    psnr: float = float("nan")
    iterations: int = 0
    train_seconds: float = 0.0
    train_cpu_seconds: float = 0.0
    """CPU time of this process during training (all threads); a load-independent cost measure."""
    eval_seconds: float = 0.0
    params: int = 0

    def psnr_at_seconds(self, seconds: float) -> float:
        """Best PSNR evaluated within ``seconds`` of training (nan if none)."""
        ok = [p for s, p in zip(self.curve_seconds, self.curve_psnr) if s <= seconds]
        return max(ok) if ok else float("nan")


def pixel_grid(height: int, width: int) -> Float[Tensor, "num_points 2"]:
    """Pixel centres ``((j+0.5)/W, (i+0.5)/H)`` in row-major order, in ``(0, 1)^2``."""
    ys = (torch.arange(height, dtype=torch.float64) + 0.5) / height
    xs = (torch.arange(width, dtype=torch.float64) + 0.5) / width
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)
    return grid.reshape(-1, 2).float()


def schedule(cfg: TrainConfig) -> "tuple[set[int], set[int]]":
    """Iterations of the full-image evaluations and of the kept snapshots."""
    n = cfg.iterations
    evals = {int(round(v)) for v in np.linspace(0, n, max(cfg.num_evals, 2))}
    snaps = {int(round(v)) for v in np.geomspace(max(1.0, n / 100), n, max(cfg.num_snapshots, 1))}
    return evals | snaps | {0, n}, snaps | {n}


class _Fitter:
    """One fit's state; :meth:`step` and :meth:`evaluate` are the named points of the loop."""

    def __init__(self, image: UInt8[Tensor, "H W 3"], field_cfg: ImageFieldConfig, cfg: TrainConfig) -> None:
        self.cfg, self.shape = cfg, tuple(image.shape[:2])
        self.model, _ = seeded_init(field_cfg.setup, cfg.seed)  # torch's global stream left as it was
        self.coords = pixel_grid(*self.shape)
        self.target = image.reshape(-1, 3).float() / 255.0
        self.target_img = self.target.reshape(*self.shape, 3)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
        gamma = cfg.lr_final_factor ** (1.0 / max(cfg.iterations, 1))
        self.sched = torch.optim.lr_scheduler.ExponentialLR(self.opt, gamma)
        self.cache: "Tensor | None" = None
        self.corners: "tuple[Tensor, Tensor] | None" = None
        self.result = FitResult(params=self.model.num_parameters())

    def prepare(self) -> None:
        """Precompute what does not change: a parameter-free encoding, or grid corners (timed as training)."""
        encoder = self.model.encoder
        with torch.no_grad():
            if is_static(encoder):
                self.cache = encoder(self.coords)
            elif isinstance(encoder, GridEncoder):
                chunk = self.cfg.eval_chunk  # chunks stay in cache: ~1.5x faster than one pass
                parts = [encoder.corners(self.coords[i : i + chunk]) for i in range(0, len(self.coords), chunk)]
                self.corners = (torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts]))

    def features(self, idx: "Tensor | slice | None") -> Tensor:
        """Encoded pixels ``idx`` (all when None), using whatever :meth:`prepare` cached."""
        if self.cache is not None:
            return self.cache if idx is None else self.cache[idx]
        if self.corners is not None:
            c_idx, c_w = self.corners if idx is None else (self.corners[0][idx], self.corners[1][idx])
            return self.model.encoder.interpolate(c_idx, c_w)
        return self.model.encoder(self.coords if idx is None else self.coords[idx])

    def step(self) -> float:
        n, bs = self.coords.shape[0], self.cfg.batch_size
        idx = None if bs <= 0 or bs >= n else torch.randint(0, n, (bs,), generator=self.gen)
        pred = self.model.decode(self.features(idx))
        loss = torch.mean((pred - (self.target if idx is None else self.target[idx])) ** 2)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.sched.step()
        return float(loss.detach())

    @torch.no_grad()
    def render(self) -> Tensor:
        """The whole image ``[H, W, 3]``, in chunks, through the cached encoding when there is one."""
        n, chunk = self.coords.shape[0], self.cfg.eval_chunk
        out = [self.model.decode(self.features(slice(i, i + chunk))) for i in range(0, n, chunk)]
        return torch.cat(out).reshape(*self.shape, 3)

    def evaluate(self, it: int, keep: bool) -> float:
        img = self.render()
        psnr = psnr_from_mse(float(torch.mean((img - self.target_img) ** 2)))
        r = self.result
        r.curve_iterations.append(it), r.curve_seconds.append(r.train_seconds), r.curve_psnr.append(psnr)
        if keep:
            r.snapshots[it] = to_uint8(img)
        r.final, r.psnr, r.iterations = to_uint8(img), psnr, it
        return psnr


def to_uint8(img: Tensor) -> np.ndarray:
    return (img.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()


def fit_image(
    image: UInt8[Tensor, "H W 3"],
    field_cfg: ImageFieldConfig,
    cfg: TrainConfig,
    on_step: "Callable[[int, float, float], None] | None" = None,
) -> FitResult:
    """Fit a field to ``image``; ``on_step(iteration, loss, last_psnr)`` fires after each step."""
    f = _Fitter(image, field_cfg, cfg)
    evals, snaps = schedule(cfg)
    c0 = time.process_time()
    f.result.train_seconds += _timed(f.prepare)
    f.result.train_cpu_seconds += time.process_time() - c0
    f.result.eval_seconds += _timed(lambda: f.evaluate(0, keep=False))
    for it in range(1, cfg.iterations + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        loss = f.step()
        f.result.train_seconds += time.perf_counter() - t0
        f.result.train_cpu_seconds += time.process_time() - c0
        out_of_time = cfg.max_seconds is not None and f.result.train_seconds >= cfg.max_seconds
        if it in evals or out_of_time:
            f.result.eval_seconds += _timed(lambda: f.evaluate(it, keep=it in snaps or out_of_time))
        if on_step is not None:
            on_step(it, loss, f.result.psnr)
        if out_of_time:
            break
    return f.result


def _timed(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0
