"""A training step's forward, losses and backward captured once as a CUDA graph and replayed (issue 13).

On a GPU the fast model's training step is ~400 small kernels; launched one by one from Python the host needs
9.0 ms for 2.3 ms of GPU work (an H200, lego_200 fast-small, 4,096 rays, session 23). Replaying a captured graph
launches them in one call, so the step costs about what the GPU does: 4.0 ms there (35 launches from the host per
step instead of 411, the GPU busy 85 % of the time instead of 16 %).

What a graph holds and what stays eager around its replay:

- eager before: the model's hooks (occupancy refreshes, box tightening, coarse-to-fine), the learning rate, the
  pixel sampler (its stream is on the host); the batch is then copied into the graph's static inputs;
- the graph: :meth:`~nerfpipe.models.base.Model.get_outputs`, :meth:`~nerfpipe.models.base.Model.get_losses`,
  the backward pass (into each parameter's ``.grad``, which the graph owns) and the per-ray squared error;
- eager after: the optimiser's step (fused Adam: a few launches), the parameter average, the loss log.

A captured step stays valid while the model's :meth:`~nerfpipe.models.base.Model.graph_key` is unchanged (the
Python-level state its code branches on and the memory it reads); when the key changes the step runs eagerly once
on a side stream (the warm-up that capturing needs, and the measure of the samples it packs) and is captured anew.
Random draws inside the graph come from the model's generator, registered with the graph, so each replay draws
new numbers and a checkpoint's generator state goes on from there.

What varies in size from step to step is packed into a fixed number of slots, the model's ``sample_capacity``
(:func:`~nerfpipe.functional.packed.pack_static`; for the fast model the occupied intervals whose density is evaluated,
and the samples kept): :data:`HEADROOM` times the most a step has needed, in multiples of :data:`QUANTUM`. The graph
keeps the largest counts of its replays on the device; after each replay that is copied to pinned host memory without waiting, and
read once the copy has landed (an event; waited for at the end of each window of :data:`WINDOW` replays). A step that
needed more than the slots lost its last rays' samples (they rendered as their background), and the next step is
captured with more slots; where a window needed much less than the slots, the step is captured with fewer.
"""

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import fields, is_dataclass

import torch

from nerfpipe.util.typing import Float, Tensor

HEADROOM = 1.15
"""Slots for samples over the most a step has needed. Every slot costs a sample's work in the field and its backward,
used or not (an H200, lego_200 fast-small, 4,096 rays, ~17,000 samples a step: 49,152 slots with a headroom of 1.25
in multiples of 16,384 made the GPU busy 6.5 ms per step, 26,624 with these values 3.6 ms; eagerly 2.3 ms)."""

QUANTUM = 1 << 11
"""Sample slots are a multiple of this."""

WINDOW = 64
"""Replays between checks whether the slots could shrink."""

SHRINK_BELOW = 0.8
"""Capture with fewer slots when a window's largest count is below this share of them."""


def capacity_for(count: int) -> int:
    """Sample slots for steps that needed up to ``count`` samples.

    Example:
        >>> capacity_for(100_000)
        116736
    """
    return max(QUANTUM, math.ceil(HEADROOM * count / QUANTUM) * QUANTUM)


def _tensors(obj) -> "list[Tensor]":
    """The tensors of a (nested) dataclass, in field order."""
    out = []
    for f in fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, Tensor):
            out.append(v)
        elif is_dataclass(v):
            out += _tensors(v)
    return out


def _layout(obj) -> tuple:
    """The fields of a (nested) dataclass with the shape and dtype of each tensor (None for a field without one):
    two batches with the same layout fit the same static inputs."""
    out = [type(obj)]
    for f in fields(obj):
        v = getattr(obj, f.name)
        out.append((v.shape, v.dtype) if isinstance(v, Tensor) else _layout(v) if is_dataclass(v) else None)
    return tuple(out)


class GraphedStep:
    """The forward, losses and backward of a trainer's steps as a replayed CUDA graph (see the module).

    Args:
        model: the model being trained (on a CUDA device).
        optimizer: its optimiser (its gradients are set to None before each capture: the graph allocates them).
        forward_backward: the eager step, ``forward_backward(batch) -> squared error per ray``, its gradients
            written into ``.grad`` (None before).
    """

    def __init__(self, model, optimizer: torch.optim.Optimizer, forward_backward) -> None:
        self.model, self.optimizer, self.forward_backward = model, optimizer, forward_backward
        self.device = next(model.parameters()).device
        self.stream = self._new_stream()
        self.graph: "torch.cuda.CUDAGraph | None" = None
        self.key: "tuple | None" = None
        self.warmed: "tuple | None" = None
        """The key the latest eager warm-up ran with: the next step with that key is captured."""
        self.capacity: "tuple[int, ...]" = ()
        self.static = None
        self.layout: "tuple | None" = None
        """:func:`_layout` of the static inputs."""
        self.sq: "Float[Tensor, 'num_rays'] | None" = None
        count = model.sample_count()
        n = 0 if count is None else count.numel()
        self.peak = torch.zeros(n, dtype=torch.long, device=self.device)
        self.pinned = self._host_buffer(n)
        self._pinned_view = self.pinned.numpy()  # read on the host without an ATen op (nothing waits for the device)
        self.event: "torch.cuda.Event | None" = None
        self.most: "tuple[int, ...]" = (0,) * n
        """The largest count of each slot kind read back since the last capture or window."""
        self.window = 0
        self.captures, self.replays, self.eager_steps, self.overflows = 0, 0, 0, 0
        self.capture_seconds = 0.0
        self.window_most: "tuple[int, ...]" = (0,) * n
        """The largest counts of the latest whole window (a figure for the run's metrics)."""
        self.grads: "list[tuple[Tensor, Tensor]]" = []
        """Each parameter with the gradient tensor the graph writes."""
        self.failed: "str | None" = None
        """Why capturing failed (the trainer then steps eagerly for the rest of the run)."""

    def __call__(self, batch) -> "Float[Tensor, 'num_rays'] | None":
        """Run one step's forward, losses and backward for ``batch``; its squared error per ray (a tensor the next
        call overwrites: use it before). None where the model cannot be captured now: the caller steps eagerly."""
        if self.failed is not None:
            return None
        key = self.model.graph_key()
        if key is None:
            self._drop()
            return None
        if self.graph is not None and (key != self.key or _layout(batch) != self.layout):
            self._drop()  # the step's code or the memory it reads changed: warm up and capture again
        if self.graph is None:
            if self.warmed != key:
                return self._warm_up(batch, key)
            if not self._capture(batch, self._slots(), key):
                return None
        elif self._read_count(wait=self.window >= WINDOW):  # a step needed more slots than there are
            self.overflows += 1
            if not self._capture(batch, self._slots(), key):
                return None
        elif self.event is None and self.window >= WINDOW:  # a window's largest counts have landed: fewer slots?
            if any(n < SHRINK_BELOW * c for n, c in zip(self._slots(), self.capacity)) and not self._capture(batch, self._slots(), key):
                return None
            self.peak.zero_()
            self.window_most, self.most, self.window = self.most, (0,) * len(self.most), 0
        for dst, src in zip(_tensors(self.static), _tensors(batch)):
            dst.copy_(src, non_blocking=True)
        for param, grad in self.grads:  # the graph writes these: a caller that set .grad to None must not lose them
            if param.grad is not grad:
                param.grad = grad
        self.graph.replay()
        self.replays += 1
        self.window += 1
        self.pinned.copy_(self.peak, non_blocking=True)
        self.event = self._record_event()
        return self.sq

    def _read_count(self, wait: bool = False) -> bool:
        """Read the latest count copied back if it has landed (``wait``: once it has; at the end of each window, so a
        step short of slots is seen within :data:`WINDOW` steps even where the host runs ahead of the GPU); whether it
        exceeded the slots."""
        if self.event is None or not (wait or self.event.query()):
            return False
        self.event.synchronize()
        self.event = None
        self.most = tuple(max(a, int(b)) for a, b in zip(self.most, self._pinned_view))
        return any(n > c for n, c in zip(self.most, self.capacity))

    def _slots(self) -> "tuple[int, ...]":
        """Slots for the counts seen (:func:`capacity_for` each)."""
        return tuple(capacity_for(n) for n in self.most)

    def _drop(self) -> None:
        self.graph, self.key, self.static, self.sq, self.event, self.grads = None, None, None, None, None, []
        self.model.sample_capacity = None

    def _warm_up(self, batch, key: tuple) -> "Float[Tensor, 'num_rays']":
        """One eager step on the side stream (a capture needs one there first), which measures the samples a
        step packs (one read back per capture)."""
        self.optimizer.zero_grad(set_to_none=True)
        with self._side_stream():
            sq = self.forward_backward(batch)
        count = self.model.sample_count()
        self.most = () if count is None else tuple(int(n) for n in count.tolist())  # the read back of a warm-up
        self.warmed = key
        self.eager_steps += 1
        return sq

    def _capture(self, batch, capacity: "tuple[int, ...]", key: tuple) -> bool:
        """Capture the step with ``capacity`` slots (``batch`` fills its static inputs; nothing runs until
        the replay). False where capturing failed: :attr:`failed` says why, and the run goes on eagerly."""
        self._drop()
        self.model.sample_capacity = capacity
        self.static, self.layout = _clone(batch), _layout(batch)
        self.optimizer.zero_grad(set_to_none=True)  # the graph allocates the gradients it writes
        start = time.perf_counter()
        try:
            graph, sq = self._record(self._body)
        except Exception as exc:  # an op that cannot be captured: the run goes on eagerly
            self.failed = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
            self._drop()
            self.optimizer.zero_grad(set_to_none=True)
            return False
        self.graph, self.sq, self.key, self.capacity = graph, sq, key, capacity
        self.grads = [(p, p.grad) for group in self.optimizer.param_groups for p in group["params"] if p.grad is not None]
        self.peak.zero_()
        self.most, self.window = (0,) * len(self.most), 0
        self.captures += 1
        self.capture_seconds += time.perf_counter() - start
        return True

    def _body(self) -> "Float[Tensor, 'num_rays']":
        """What the graph holds: the step on the static batch, and the largest counts kept on the device."""
        sq = self.forward_backward(self.static)
        count = self.model.sample_count()
        if count is not None:
            torch.maximum(self.peak, count, out=self.peak)
        return sq

    # the CUDA calls, one method each (tests/test_cuda_graph.py runs the rest on the CPU with stand-ins for them)
    def _new_stream(self):
        return torch.cuda.Stream(self.device)

    def _host_buffer(self, n: int) -> Tensor:
        return torch.zeros(n, dtype=torch.long).pin_memory()

    def _record_event(self):
        event = torch.cuda.Event()
        event.record()
        return event

    @contextmanager
    def _side_stream(self) -> "Iterator[None]":
        """Work on the side stream, ordered after what was queued before and before what comes after."""
        self.stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(self.stream):
            yield
        torch.cuda.current_stream(self.device).wait_stream(self.stream)

    def _record(self, body) -> "tuple[torch.cuda.CUDAGraph, Tensor]":
        """``body()`` captured as a CUDA graph (nothing runs until :meth:`replay`), with its output."""
        graph = torch.cuda.CUDAGraph()
        generator = getattr(self.model, "generator", None)
        if generator is not None and generator.device.type == "cuda":
            graph.register_generator_state(generator)
        with torch.cuda.graph(graph, stream=self.stream, capture_error_mode="thread_local"):
            out = body()
        return graph, out

    def stats(self) -> "dict[str, int | float | list[int]]":
        """Counts for the run's metrics: captures, replays, eager steps, overflows, slots, capture seconds."""
        return {"graph_captures": self.captures, "graph_replays": self.replays, "graph_eager_steps": self.eager_steps,
                "graph_overflows": self.overflows, "graph_slots": list(self.capacity), "graph_capture_s": round(self.capture_seconds, 3),
                "graph_window_most": list(self.window_most)}


def _clone(obj):
    """A copy of a (nested) dataclass of tensors with every tensor in new memory."""
    values = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        values[f.name] = v.clone() if isinstance(v, Tensor) else _clone(v) if is_dataclass(v) else v
    return type(obj)(**values)
