"""Progressive live rendering of a browser camera: a small frame at once, sharper ones while it stays still.

A :class:`ProgressiveRenderer` holds the latest camera a client asked for and does its work in small
units (:meth:`ProgressiveRenderer.step`), so whoever drives it decides when the CPU is spent: a
thread while a finished run is viewed, or the training loop between its steps (within a share of
its time) while training is watched. Each camera is rendered as

1. one **low** frame, whose pixel count is set from the measured rays per second so that it takes
   about ``low_seconds`` (the first answer to a move; the time the image was requested to the time
   it is shown is its latency);
2. then each finer level (``levels``, as fractions of ``max_size`` on the longer side) in **strips**
   of rows that take about ``strip_seconds`` each, each strip one unit of work, so a new camera
   interrupts a refinement within one strip.

A strip is the same camera with its principal point moved up by the strip's first row and its
height cut to the strip (:func:`strip_camera`), rendered by the one renderer
(:func:`nerfpipe.render.render_cameras`): a refined frame is the frame ``nerfpipe render`` makes of
that camera, strip by strip.
"""

import logging
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from nerfpipe.cameras import Cameras
from nerfpipe.render import RenderedView, to_uint8


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
    """The depth of a view colour-mapped over its own range (:mod:`nerfpipe.colormap`)."""
    from nerfpipe.colormap import colorize_depth, depth_range

    lo, hi = depth_range([view.depth], [view.acc])
    return colorize_depth(view.depth, view.acc, lo, hi)


class ProgressiveRenderer:
    """Renders the latest requested camera, coarse first (see the module docstring).

    Args:
        render: renders a ``[1]`` batch of cameras (the run's model through
            :func:`nerfpipe.render.render_cameras`).
        show: called with each finished :class:`Frame`.
        max_size: longer side of the finest level, in pixels.
        levels: finer levels after the low frame, as fractions of ``max_size``.
        low_seconds: the time the low frame should take.
        strip_seconds: the time one unit of refinement work (a strip) should take: a move waits at most this long.
    """

    def __init__(
        self,
        render: "Callable[[Cameras], RenderedView]",
        show: "Callable[[Frame], None]",
        max_size: int = 512,
        levels: "tuple[float, ...]" = (0.5, 1.0),
        low_seconds: float = 0.1,
        strip_seconds: float = 0.05,
    ) -> None:
        self.render, self.show = render, show
        self.max_size, self.levels, self.low_seconds, self.strip_seconds = max_size, levels, low_seconds, strip_seconds
        self.mode = "rgb"
        """``rgb`` or ``depth``: what :attr:`Frame.image` shows."""
        self.rays_per_second = 20_000.0
        """Measured speed (moving average), sets the low frame's size."""
        self._lock = threading.Lock()
        self._pending: "ViewRequest | None" = None
        self._last: "ViewRequest | None" = None
        self._job: "dict | None" = None

    def request(self, req: ViewRequest) -> None:
        """Ask for a camera; replaces whatever was asked before (thread-safe)."""
        with self._lock:
            self._pending = req

    def refresh(self, again: bool = False) -> None:
        """Render the last camera again: from its low frame (the mode or size changed), or with ``again``
        only at its sharpest level, strip by strip (the field changed while training: no flash of a blurred frame)."""
        with self._lock:
            if self._pending is None and self._last is not None:
                self._pending = replace(self._last, stamp=time.perf_counter(), again=again)

    @property
    def busy(self) -> bool:
        return self._pending is not None or self._job is not None

    def step(self) -> bool:
        """Do one unit of work (a low frame or a strip); False when there was none.

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
        if self._job is None:
            return False
        self._strip()
        return True

    def _timed(self, cams: Cameras) -> "tuple[RenderedView, float]":
        start = time.perf_counter()
        with torch.no_grad():
            view = self.render(cams)
        seconds = time.perf_counter() - start
        rays = int(cams.width[0]) * int(cams.height[0])
        if seconds > 0:
            self.rays_per_second = 0.7 * self.rays_per_second + 0.3 * rays / seconds
        return view, seconds

    def _levels(self, req: ViewRequest) -> "list[tuple[int, int]]":
        """``(width, height)`` of each refinement of a request."""
        if req.size is not None:
            return [req.size]
        return [level_size(req.aspect, f, self.max_size) for f in self.levels]

    def _emit(self, view: RenderedView, seconds: float, req: ViewRequest, level: int, levels: int) -> None:
        image = to_uint8(view.rgb) if self.mode == "rgb" else depth_image(view)
        self.show(Frame(image, view, seconds, time.perf_counter() - req.stamp, level, levels))

    def _low(self, req: ViewRequest) -> None:
        self._last = req
        w, h = size_for(req.aspect, self.low_seconds * self.rays_per_second, self.max_size)
        view, seconds = self._timed(pinhole_camera(req.world_from_cam, req.fov, w, h))
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

    def _strip(self) -> None:
        job = self._job
        cams = job["cams"]
        w, h = int(cams.width[0]), int(cams.height[0])
        rows = max(1, min(h - job["row"], int(self.strip_seconds * self.rays_per_second) // w))
        view, seconds = self._timed(strip_camera(cams, job["row"], rows))
        job["parts"].append(view)
        job["row"] += rows
        job["seconds"] += seconds
        if job["row"] >= h:
            self._emit(join_strips(job["parts"]), job["seconds"], job["req"], job["level"], len(job["levels"]))
            self._next_level()


class RenderThread:
    """Drives renderers from a thread of its own (viewing a finished run): works while any has work."""

    def __init__(self, renderers: "Callable[[], list[ProgressiveRenderer]]") -> None:
        self._renderers = renderers
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
        while not self._stop:
            worked = False
            for r in self._renderers():
                worked = r.step() or worked
            if not worked:
                self._wake.wait(0.05)
                self._wake.clear()


__all__ = ["Frame", "ProgressiveRenderer", "RenderThread", "ViewRequest", "pinhole_camera", "strip_camera"]
