"""Count what a piece of torch code asks of the device: ATen operations and host synchronisations.

On a GPU every ATen operation is (at least) one kernel launch, and a *host sync* stalls the Python
thread until the device has caught up: reading a value back (``.item()``, ``float(t)``, ``bool(t)``,
``.tolist()``, ``.numpy()``) or an operation whose output *shape* depends on the data (``nonzero``,
boolean-mask indexing, ``unique``, ``masked_select``, ``repeat_interleave`` without ``output_size``),
which must read a count back before it can allocate. Both are counted here with a
:class:`~torch.utils._python_dispatch.TorchDispatchMode` (and a ``TorchFunctionMode`` for the reads
that never reach ATen on CPU), so the count is the same on CPU as on CUDA and can be a test on a
machine without a GPU.

Glossary:
    op      one ATen operator call below autograd (forward and backward), e.g. ``aten.mul.Tensor``
    sync    an op (or tensor method) that makes the host wait for the device
    upload  a tensor built from Python values (``torch.tensor([...])``): a blocking host-to-device copy on
            CUDA (the stream is synchronised before the host memory is released), counted as a sync too
    transfer  a copy between devices (``.to(device)``, ``.cpu()``): a sync unless ``non_blocking`` from the host, or
            ``non_blocking`` into pinned host memory (``copy_``, read once an event says it landed);
            seen only where there are two devices (on CUDA), not on a CPU-only run

Example:
    >>> x = torch.arange(4.0)
    >>> with DispatchCounter() as c:
    ...     y = (x * 2)[x > 1].sum().item()
    >>> c.syncs, dict(c.sync_ops)
    (2, {'aten.index.Tensor(bool)': 1, 'aten._local_scalar_dense': 1})
"""

import time
from collections import Counter
from dataclasses import dataclass, field

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

SYNC_OPS = frozenset({
    "aten._local_scalar_dense",  # .item(), float(t), int(t), bool(t)
    "aten.nonzero", "aten.masked_select", "aten.argwhere",
    "aten._unique", "aten._unique2", "aten.unique_dim", "aten.unique_consecutive", "aten.unique_dim_consecutive",
    "aten.bincount", "aten.equal", "aten.is_nonzero", "aten._assert_scalar",
})  # fmt: skip
"""ATen operators that read device memory back on the host (their result or its shape depends on the data)."""

UPLOAD_OPS = frozenset({"aten.lift_fresh", "aten.lift_fresh_copy"})
"""ATen operators of ``torch.tensor(python values)``: a host-to-device copy on CUDA (counted for lists, not
for the 0-dim tensors Python scalars become)."""

_HOST_METHODS = frozenset({"tolist", "numpy", "__array__"})
"""Tensor methods that read every value back (no ATen operator on CPU)."""


def _name(func) -> str:
    return f"{func.namespace}.{func._opname}" if hasattr(func, "_opname") else str(func)


def _has_bool_index(args) -> bool:
    """Whether an ``index``/``index_put`` call's index list holds a boolean mask (a data-dependent shape)."""
    indices = args[1] if len(args) > 1 else ()
    return any(isinstance(t, torch.Tensor) and t.dtype in (torch.bool, torch.uint8) for t in indices or ())


def _transfer(name: str, args, kwargs) -> "str | None":
    """``device-to-host`` or ``host-to-device`` for a copy between devices that makes the host wait (a copy to the
    host always does; one from pageable host memory does unless ``non_blocking``), else None. Never on a CPU-only run."""
    if name == "aten._to_copy" and args and kwargs.get("device") is not None:
        src, dst, non_blocking = args[0].device, torch.device(kwargs["device"]), kwargs.get("non_blocking", False)
    elif name == "aten.copy_" and len(args) > 1 and isinstance(args[1], torch.Tensor):
        src, dst, non_blocking = args[1].device, args[0].device, bool(args[2]) if len(args) > 2 else kwargs.get("non_blocking", False)
    else:
        return None
    if src == dst:
        return None
    if dst.type == "cpu":  # into pinned memory without blocking (a copy_ only): the host does not wait
        return None if name == "aten.copy_" and non_blocking and args[0].is_pinned() else "device-to-host"
    return None if non_blocking and src.type == "cpu" else "host-to-device"


def _repeat_without_size(args, kwargs) -> bool:
    return kwargs.get("output_size") is None and not (len(args) > 2 and args[2] is not None)


@dataclass
class _Tally:
    ops: Counter = field(default_factory=Counter)
    sync_ops: Counter = field(default_factory=Counter)
    uploads: int = 0

    def op(self, func, args, kwargs) -> None:
        name = _name(func)
        self.ops[name] += 1
        if name in SYNC_OPS:
            self.sync_ops[name] += 1
        elif name in ("aten.index", "aten.index_put", "aten.index_put_", "aten._index_put_impl_") and _has_bool_index(args):
            self.sync_ops[f"{func}(bool)"] += 1
        elif name == "aten.repeat_interleave" and _repeat_without_size(args, kwargs):
            self.sync_ops[name] += 1
        elif name in ("aten._to_copy", "aten.copy_") and (kind := _transfer(name, args, kwargs)) is not None:
            self.sync_ops[f"{name}({kind})"] += 1
        elif name in UPLOAD_OPS and args and args[0].ndim > 0:  # (0-dim: a Python scalar made a tensor, e.g. ``x[m] = 0``)
            # a blocking copy from pageable host memory on CUDA: the stream is synchronised
            self.sync_ops[name] += 1
            self.uploads += 1


class _Ops(TorchDispatchMode):
    def __init__(self, tally: _Tally) -> None:
        super().__init__()
        self.tally = tally

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.tally.op(func, args, kwargs)
        return func(*args, **kwargs)


class _Reads(TorchFunctionMode):
    def __init__(self, tally: _Tally) -> None:
        super().__init__()
        self.tally = tally

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in _HOST_METHODS:
            self.tally.sync_ops[f"Tensor.{name}"] += 1
        return func(*args, **(kwargs or {}))


class DispatchCounter:
    """Context manager counting ATen ops, host syncs and constant uploads (see the module docstring).

    Counts accumulate over every ``with`` block the same counter is entered in; :meth:`reset` clears them.
    Ops that autograd runs in ``backward()`` are counted when ``backward()`` is called inside the block.
    """

    def __init__(self) -> None:
        self.tally = _Tally()
        self._modes: "list" = []

    def __enter__(self) -> "DispatchCounter":
        self._modes = [_Reads(self.tally), _Ops(self.tally)]
        for mode in self._modes:
            mode.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        for mode in reversed(self._modes):
            mode.__exit__(*exc)
        self._modes = []

    def reset(self) -> None:
        self.tally = _Tally()

    @property
    def ops(self) -> int:
        """ATen operator calls."""
        return sum(self.tally.ops.values())

    @property
    def syncs(self) -> int:
        """Host synchronisations (reads back and data-dependent shapes)."""
        return sum(self.tally.sync_ops.values())

    @property
    def sync_ops(self) -> Counter:
        """Host synchronisations by operator."""
        return self.tally.sync_ops

    @property
    def op_counts(self) -> Counter:
        """ATen operator calls by operator."""
        return self.tally.ops

    @property
    def uploads(self) -> int:
        """Tensors built from Python values (host-to-device copies on CUDA)."""
        return self.tally.uploads


@dataclass
class StepCounts:
    """ATen ops, host syncs and uploads per step, averaged over ``steps`` steps, with the worst step."""

    steps: int
    ops: float
    syncs: float
    uploads: float
    max_ops: int
    max_syncs: int
    sync_ops: "dict[str, int]"
    """Host synchronisations over all the steps, by operator."""
    per_step: "list[tuple[int, int]]" = field(default_factory=list)
    """(ATen ops, host syncs) of each step, in order."""

    def row(self) -> "dict[str, float]":
        """The figures of a benchmark row."""
        return {"aten_ops_per_step": round(self.ops, 1), "host_syncs_per_step": round(self.syncs, 2), "uploads_per_step": round(self.uploads, 2)}


def count_steps(step, steps: int) -> StepCounts:
    """Call ``step()`` ``steps`` times under a :class:`DispatchCounter`; per-step figures."""
    per, total = [], Counter()
    for _ in range(steps):
        counter = DispatchCounter()
        with counter:
            step()
        per.append((counter.ops, counter.syncs, counter.uploads))
        total.update(counter.sync_ops)
    n = max(steps, 1)
    return StepCounts(
        steps=steps, ops=sum(p[0] for p in per) / n, syncs=sum(p[1] for p in per) / n, uploads=sum(p[2] for p in per) / n,
        max_ops=max((p[0] for p in per), default=0), max_syncs=max((p[1] for p in per), default=0), sync_ops=dict(total),
        per_step=[(p[0], p[1]) for p in per],
    )


def gpu_profile(step, steps: int, device: str, tables: bool = False) -> "dict[str, float]":
    """GPU time, kernel launches and wall time per call of ``step`` over ``steps`` calls under torch's profiler, on a
    CUDA ``device``. The busy time sums the kernels' own device time (user annotations such as the optimiser's step
    range left out, as the profiler's ``Self CUDA time total`` does); the profiler lengthens the host's time, so the
    busy share is a lower bound. ``tables``: print the profiler's tables of the top kernels and host ops."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize(device)
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        torch.cuda.synchronize(device)
        wall = time.perf_counter() - t0
    events = prof.key_averages()
    kernels = [e for e in events if e.device_type == DeviceType.CUDA and not getattr(e, "is_user_annotation", False)]
    busy_ms = sum(e.self_device_time_total for e in kernels) / 1000 / steps
    launches = sum(e.count for e in events if e.key in ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel")) / steps
    if tables:
        print(events.table(sort_by="self_device_time_total", row_limit=12))
        print(events.table(sort_by="self_cpu_time_total", row_limit=12))
    wall_ms = 1000 * wall / steps
    return {"profiled_ms_per_step": wall_ms, "gpu_busy_ms_per_step": busy_ms, "gpu_busy_share": busy_ms / wall_ms,
            "kernel_launches_per_step": launches}
