"""Progressive live rendering of a browser camera: a small frame at once, sharper ones once it stays still.

A :class:`ProgressiveRenderer` holds the latest camera a client asked for and does its work in small
units (:meth:`ProgressiveRenderer.step`), so whoever drives it decides when the CPU is spent: a
thread while a finished run is viewed, or the training loop between its steps (within a share of
its time) while training is watched. Each camera is rendered as

1. one **low** frame, whose pixel count is chosen from the measured cost of a render (:class:`RenderCost`:
   a fixed time per call plus a time per pixel) so that it takes about ``low_seconds``, at most half the
   first level's width (the first answer to a move; the time the camera moved to the time the image is
   ready is its latency);
2. then, once no new camera came for ``settle`` seconds, each finer level (``levels``, as fractions of
   ``max_size`` on the longer side) in **strips** of rows that take about ``strip_seconds`` each (sized at
   the rate the strip above rendered), each strip one unit of work, so a new camera interrupts a
   refinement within one strip.

While the camera moves only low frames are made, each of the newest camera (a camera that arrives while
a unit runs replaces the one waiting; the same camera sent twice, as the browser does, is rendered once).
The refinement also leaves the CPU to the browser: it waits ``settle`` after a move (the page shows the
low frame meanwhile) and then, while other processes keep half a CPU or more busy (:class:`OtherLoad`: a
browser drawing on the same machine, other work), renders at most ``refine_share`` of the time (it rests
after each strip; a new camera is served at once). Measured on colmap_mouse with headless Chromium on the
same two cores (load 4-5; a viewer in-process, timed by the page's clock), a refinement rendering without
rest kept the page from sending a moved camera for 0.06-1.3 s, and with half the time 1 ms; move to low
frame shown 0.50-1.87 s against 0.22-0.44 s (docs/measured.md, viewer rows).

A strip is the same camera with its principal point moved up by the strip's first row and its
height cut to the strip (:func:`strip_camera`), rendered by the one renderer
(:func:`nerfpipe.outputs.render.render_cameras`): a refined frame is the frame ``nerfpipe render`` makes of
that camera, strip by strip.
"""

import logging
import math
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.outputs.render import RenderedView, to_uint8
from nerfpipe.util.runtime import cpu_ticks


@dataclass(frozen=True)
class ViewRequest:
    """A camera the browser asked for."""

    world_from_cam: np.ndarray
    """Camera-to-world ``[4, 4]``, OpenCV axes (viser's cameras are OpenCV too)."""
    fov: float
    """Vertical field of view in radians."""
    aspect: float
    """Width over height of the browser's canvas."""
    stamp: float
    """``time.perf_counter()`` when the camera moved."""
    size: "tuple[int, int] | None" = None
    """Render exactly ``(width, height)`` after the low frame (a camera path's frame), instead of the levels."""
    again: bool = False
    """The same camera once more (the field changed): straight to the sharpest level, no low frame."""


@dataclass
class Frame:
    """A rendered frame, ready to show."""

    image: np.ndarray
    """uint8 ``[H, W, 3]``: the colour, or the depth colour-mapped."""
    view: RenderedView
    """What the renderer returned."""
    seconds: float
    """Render time of this frame (its strips added up)."""
    latency: float
    """Seconds from the request to this frame being ready."""
    level: int
    """0 for the low frame, then 1, 2, ... up to ``levels``."""
    levels: int
    """Number of refinement levels after the low frame."""


def pinhole_camera(world_from_cam: np.ndarray, fov: float, width: int, height: int) -> Cameras:
    """A float32 pinhole camera ``[1]``: square pixels, principal point at the centre, vertical ``fov`` (radians)."""
    focal = (height / 2) / math.tan(fov / 2)
    m = torch.as_tensor(np.asarray(world_from_cam, dtype=np.float64))[None]
    return Cameras.create(m, focal, focal, width / 2, height / 2, width, height, dtype=torch.float64).to(dtype=torch.float32)


def strip_camera(cameras: Cameras, row: int, rows: int) -> Cameras:
    """Rows ``row .. row + rows - 1`` of every camera, as cameras of their own."""
    return replace(cameras, cy=cameras.cy - row, height=torch.full_like(cameras.height, rows))


def size_for(aspect: float, pixels: float, max_size: int) -> "tuple[int, int]":
    """``(width, height)`` with about ``pixels`` pixels at ``aspect``, the longer side at most ``max_size``.

    Example:
        >>> size_for(2.0, 200.0, 512), size_for(1.0, 1e9, 64)
        ((20, 10), (64, 64))
    """
    h = math.sqrt(pixels / aspect)
    w, h = aspect * h, h
    s = min(1.0, max_size / max(w, h))
    return max(1, round(w * s)), max(1, round(h * s))


def level_size(aspect: float, fraction: float, max_size: int) -> "tuple[int, int]":
    """``(width, height)`` of a level: its longer side ``fraction * max_size``."""
    long = max(1, round(fraction * max_size))
    return (long, max(1, round(long / aspect))) if aspect >= 1 else (max(1, round(long * aspect)), long)


def join_strips(parts: "list[RenderedView]") -> RenderedView:
    """One view from strips in row order."""
    stop = None if any(p.stop_depth is None for p in parts) else torch.cat([p.stop_depth for p in parts])
    return RenderedView(torch.cat([p.rgb for p in parts]), torch.cat([p.depth for p in parts]), torch.cat([p.acc for p in parts]), stop)


def depth_image(view: RenderedView) -> np.ndarray:
    """The depth of a view colour-mapped over its own range (:mod:`nerfpipe.outputs.colormap`)."""
    from nerfpipe.outputs.colormap import colorize_depth, depth_range

    lo, hi = depth_range([view.depth], [view.acc])
    return colorize_depth(view.depth, view.acc, lo, hi)


class RenderCost:
    """The time a render takes, ``overhead`` per call plus ``pixels / rate``, fitted to the last renders.

    A render call has a fixed cost (setting up the rays, the model's per-call work: 13-18 ms for the
    colmap_mouse run on this CPU) besides its cost per pixel, so a rate alone (pixels over seconds)
    measured on small frames is too low and on large ones too high. Both terms are fitted by least
    squares to the last ``window`` renders of whole views: low frames (one call) and finished levels
    (one call per strip; a strip alone is not a sample of the view: rows of sky cost less than rows
    through the object).

    Args:
        rate: pixels per second before anything was measured.
        overhead: seconds per call before anything was measured.
        window: renders the fit uses (the newest: the machine's load changes).

    Example:
        >>> cost = RenderCost()
        >>> for pixels, calls in ((500, 1), (20_000, 10), (700, 1), (80_000, 40)):
        ...     cost.observe(pixels, calls * 0.02 + pixels / 10_000, calls)
        >>> round(cost.overhead, 3), round(cost.rate), round(cost.pixels(0.12))
        (0.02, 10000, 1000)
    """

    def __init__(self, rate: float = 20_000.0, overhead: float = 0.01, window: int = 16) -> None:
        self.rate, self.overhead = rate, overhead
        self._seen: "deque[tuple[float, float, float]]" = deque(maxlen=window)

    def observe(self, pixels: int, seconds: float, calls: int = 1) -> None:
        """Record the time of ``pixels`` pixels rendered in ``calls`` calls, and refit."""
        if seconds <= 0 or pixels <= 0:
            return
        self._seen.append((float(calls), float(pixels), float(seconds)))
        n, p, t = np.array(self._seen).T
        (overhead, per_pixel), *_ = np.linalg.lstsq(np.stack([n, p], 1), t, rcond=None)
        per_call = p / n
        if per_call.max() < 1.5 * per_call.min() or overhead < 0 or per_pixel <= 0:
            overhead = self.overhead  # pixels per call too alike to tell the terms apart: keep the overhead
        self.overhead = float(np.clip(overhead, 0.0, (t / n).min()))
        # the rate: the median of the renders' own (one render under a burst of load does not swing it)
        self.rate = float(np.median(p / np.maximum(t - self.overhead * n, 0.1 * t)))

    def seconds(self, pixels: float, calls: int = 1) -> float:
        """Predicted time of ``pixels`` pixels in ``calls`` calls."""
        return calls * self.overhead + pixels / self.rate

    def pixels(self, seconds: float) -> float:
        """Pixels one call can have to take ``seconds`` (at least a tenth of what ``seconds`` buys without the overhead)."""
        return max(seconds - self.overhead, 0.1 * seconds) * self.rate


def others_busy(before: "tuple[float, float, float]", after: "tuple[float, float, float]", cpus: int) -> float:
    """CPUs that other processes kept busy between two :func:`cpu_sample` s: the machine's busy CPUs less
    this process's.

    Example:
        >>> others_busy((1000.0, 400.0, 500.0), (1400.0, 500.0, 550.0), cpus=2)  # 1.5 CPUs busy, 0.25 of them ours
        1.25
    """
    total, idle, own = (a - b for a, b in zip(after, before))
    return max(0.0, cpus * (total - idle - own) / total) if total > 0 else 0.0


def cpu_sample() -> "tuple[float, float, float] | None":
    """``(ticks of all CPUs, their idle ticks, this process's CPU time in ticks)`` now (Linux), or None."""
    ticks = cpu_ticks()
    if ticks is None:
        return None
    hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    return float(ticks[0]), float(ticks[1]), time.process_time() * hz


class OtherLoad:
    """Whether other processes want the CPUs (a browser drawing on the same machine, other work): at least
    ``threshold`` CPUs busy that are not this process's, since the last call (measured from ``/proc/stat``;
    elsewhere never)."""

    def __init__(self, threshold: float = 0.5) -> None:
        self.threshold, self.cpus = threshold, os.cpu_count() or 1
        self._last = cpu_sample()

    def __call__(self) -> bool:
        now = cpu_sample()
        before, self._last = self._last, now
        return now is not None and before is not None and others_busy(before, now, self.cpus) >= self.threshold


def same_camera(a: ViewRequest, b: "ViewRequest | None") -> bool:
    """Whether two requests ask for the same image (the browser sends a camera again when nothing moved)."""
    return (
        b is not None
        and a.size == b.size
        and a.fov == b.fov
        and a.aspect == b.aspect
        and bool(np.array_equal(np.asarray(a.world_from_cam), np.asarray(b.world_from_cam)))
    )


class ProgressiveRenderer:
    """Renders the latest requested camera, coarse first (see the module docstring).

    Args:
        render: renders a ``[1]`` batch of cameras (the run's model through
            :func:`nerfpipe.outputs.render.render_cameras`).
        show: called with each finished :class:`Frame`.
        max_size: longer side of the finest level, in pixels.
        levels: finer levels after the low frame, as fractions of ``max_size``.
        low_seconds: the time the low frame should take.
        strip_seconds: the time one unit of refinement work (a strip) should take: a move waits at most this long.
        settle: seconds without a new camera before the refinement starts.
        refine_share: the most of the time the refinement renders while ``contended``: after a strip of
            ``t`` seconds it rests ``t * (1 / refine_share - 1)`` (a new camera is served at once all the same).
        contended: whether other processes want the CPU, asked after each strip (default :class:`OtherLoad`:
            half a CPU or more busy besides this process).
        clock: the time in seconds (``time.perf_counter``; tests pass their own).
    """

    def __init__(
        self,
        render: "Callable[[Cameras], RenderedView]",
        show: "Callable[[Frame], None]",
        max_size: int = 512,
        levels: "tuple[float, ...]" = (0.5, 1.0),
        low_seconds: float = 0.1,
        strip_seconds: float = 0.05,
        settle: float = 0.35,
        refine_share: float = 0.5,
        contended: "Callable[[], bool] | None" = None,
        clock: "Callable[[], float]" = time.perf_counter,
    ) -> None:
        self.render, self.show, self.clock = render, show, clock
        self.max_size, self.levels, self.low_seconds, self.strip_seconds, self.settle = max_size, levels, low_seconds, strip_seconds, settle
        self.refine_share, self.contended = refine_share, contended if contended is not None else OtherLoad()
        self.mode = "rgb"
        """``rgb`` or ``depth``: what :attr:`Frame.image` shows."""
        self.cost = RenderCost()
        """Measured cost of a render: sets the low frame's size and the strips' height."""
        self._lock = threading.Lock()
        self._pending: "ViewRequest | None" = None
        self._last: "ViewRequest | None" = None
        self._moved = -math.inf
        """``clock()`` when the newest camera came."""
        self._rested = -math.inf
        """``clock()`` when the rest after the last strip ends."""
        self._job: "dict | None" = None

    @property
    def rays_per_second(self) -> float:
        return self.cost.rate

    def request(self, req: ViewRequest) -> None:
        """Ask for a camera; replaces whatever was asked before (thread-safe). The camera being rendered
        (or waiting) asked for again is ignored."""
        with self._lock:
            if not req.again and same_camera(req, self._pending if self._pending is not None else self._last):
                return
            self._pending = req
            self._moved = self.clock()

    def refresh(self, again: bool = False) -> None:
        """Render the last camera again: from its low frame (the mode or size changed), or with ``again``
        only at its sharpest level, strip by strip (the field changed while training: no flash of a blurred frame)."""
        with self._lock:
            if self._pending is None and self._last is not None:
                self._pending = replace(self._last, stamp=time.perf_counter(), again=again)

    @property
    def busy(self) -> bool:
        return self._pending is not None or self._job is not None

    def wait_seconds(self) -> "float | None":
        """Seconds until :meth:`step` has work: 0 now, more while a refinement waits for the camera to
        settle or rests after a strip, None when there is nothing to do."""
        if self._pending is not None:
            return 0.0
        if self._job is None:
            return None
        return max(0.0, self._moved + self.settle - self.clock(), self._rested - self.clock())

    def step(self) -> bool:
        """Do one unit of work (a low frame or a strip); False when there was none now (see :meth:`wait_seconds`).

        A render that fails (out of memory, a model that cannot render this camera) drops the camera and
        is logged: the viewer, and the training it may watch, go on."""
        try:
            return self._step()
        except Exception as exc:  # noqa: BLE001 - see the docstring
            self._job = None
            logging.getLogger(__name__).warning("live render failed (%s: %s)", type(exc).__name__, exc)
            return False

    def _step(self) -> bool:
        with self._lock:
            req, self._pending = self._pending, None
        if req is not None and req.again:
            self._job = {"req": req, "level": 0, "parts": [], "row": 0, "seconds": 0.0, "levels": self._levels(req)[-1:]}
            self._next_level()
        elif req is not None:
            self._low(req)
            return True
        if self._job is None or self.wait_seconds():
            return False
        self._strip()
        return True

    def _timed(self, cams: Cameras) -> "tuple[RenderedView, float]":
        start = self.clock()
        with torch.no_grad():
            view = self.render(cams)
        return view, self.clock() - start

    def _levels(self, req: ViewRequest) -> "list[tuple[int, int]]":
        """``(width, height)`` of each refinement of a request."""
        if req.size is not None:
            return [req.size]
        return [level_size(req.aspect, f, self.max_size) for f in self.levels]

    def low_size(self, req: ViewRequest) -> "tuple[int, int]":
        """``(width, height)`` of a request's low frame: what ``low_seconds`` buys, at most half the first
        level's width and height (a fast field's low frame stays a quick answer, smaller than any refinement)."""
        levels = self._levels(req)
        cap = max(1, max(levels[0]) // 2) if levels else self.max_size
        return size_for(req.aspect, self.cost.pixels(self.low_seconds), cap)

    def _emit(self, view: RenderedView, seconds: float, req: ViewRequest, level: int, levels: int) -> None:
        image = to_uint8(view.rgb) if self.mode == "rgb" else depth_image(view)
        self.show(Frame(image, view, seconds, time.perf_counter() - req.stamp, level, levels))

    def _low(self, req: ViewRequest) -> None:
        self._last = req
        w, h = self.low_size(req)
        view, seconds = self._timed(pinhole_camera(req.world_from_cam, req.fov, w, h))
        self.cost.observe(w * h, seconds)
        self._emit(view, seconds, req, 0, len(self._levels(req)))
        self._job = {"req": req, "level": 0, "parts": [], "row": 0, "seconds": 0.0, "levels": self._levels(req)}
        self._next_level()

    def _next_level(self) -> None:
        job = self._job
        if job is None:
            return
        job["level"] += 1
        if job["level"] > len(job["levels"]):
            self._job = None
            return
        req = job["req"]
        w, h = job["levels"][job["level"] - 1]
        job.update(cams=pinhole_camera(req.world_from_cam, req.fov, w, h), parts=[], row=0, seconds=0.0)
        job.pop("rate", None)

    def _strip(self) -> None:
        job = self._job
        cams = job["cams"]
        w, h = int(cams.width[0]), int(cams.height[0])
        # rows at the rate of the strip above (rows through the object cost more than rows of sky), the view's at first
        budget = max(self.strip_seconds - self.cost.overhead, 0.1 * self.strip_seconds)
        rows = max(1, min(h - job["row"], int(budget * job.get("rate", self.cost.rate)) // w))
        view, seconds = self._timed(strip_camera(cams, job["row"], rows))
        job["rate"] = w * rows / max(seconds - self.cost.overhead, 0.1 * seconds)
        self._rested = self.clock() + (seconds * (1.0 / self.refine_share - 1.0) if self.contended() else 0.0)
        job["parts"].append(view)
        job["row"] += rows
        job["seconds"] += seconds
        if job["row"] >= h:
            self.cost.observe(w * h, job["seconds"], len(job["parts"]))
            self._emit(join_strips(job["parts"]), job["seconds"], job["req"], job["level"], len(job["levels"]))
            self._next_level()


class RenderThread:
    """Drives renderers from a thread of its own (viewing a finished run): works while any has work,
    sleeps until the next has (a refinement waiting for its camera to settle) or until woken.

    Args:
        renderers: the renderers to drive (asked again before each round: clients come and go).
        threads: torch threads of the renders (None: leave torch's setting). torch's OpenMP threads of
            one process are shared, so this sets the process's count too, for threads that start later.
    """

    def __init__(self, renderers: "Callable[[], list[ProgressiveRenderer]]", threads: "int | None" = None) -> None:
        self._renderers, self._threads = renderers, threads
        self._wake = threading.Event()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="nerfpipe-view-render", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def stop(self) -> None:
        self._stop = True
        self._wake.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        if self._threads is not None:
            torch.set_num_threads(self._threads)
        while not self._stop:
            worked = False
            for r in self._renderers():
                worked = r.step() or worked
            if not worked:
                waits = [w for w in (r.wait_seconds() for r in self._renderers()) if w is not None]
                self._wake.wait(min(waits + [1.0]))
                self._wake.clear()


__all__ = ["Frame", "OtherLoad", "ProgressiveRenderer", "RenderCost", "RenderThread", "ViewRequest", "cpu_sample", "others_busy", "pinhole_camera", "same_camera", "strip_camera"]
