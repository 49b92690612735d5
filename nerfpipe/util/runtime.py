"""Process-wide runtime settings for the ``nerfpipe`` command: OpenMP waiting and glibc's allocator.

Both change the whole process, so they are the program's choice, never a side effect of ``import
nerfpipe``: the CLI (:func:`nerfpipe.cli.main`, ``python -m nerfpipe``, the ``nerfpipe`` console
script) and the benchmark programs call :func:`apply` first thing, before torch is imported. A
program that embeds nerfpipe and wants the same calls ``nerfpipe.util.runtime.apply()`` before its first
``import torch``; a library user who does not call it gets torch's and glibc's defaults.

**OpenMP waiting** (:func:`choose_omp_wait_policy`). torch's CPU kernels run in GNU OpenMP parallel
regions; between two regions the worker threads either spin for a while (GOMP's default) or sleep at
once (``OMP_WAIT_POLICY=PASSIVE``). A training step runs hundreds of short regions, so on an idle
machine spinning is much faster; when other processes want the cores, spinning threads take their
time. Measured on this 2-core machine, 100 steps of ``fast-small`` on lego with 2 threads:

==========================  ==========================  ==================================
waiting                     idle machine (load 1)       two busy processes beside (load 3)
==========================  ==========================  ==================================
GOMP default (spin)         15.4 s                      14.2 s for 20 steps
``GOMP_SPINCOUNT=10000``    18.5 s                      11.4 s for 20 steps
``PASSIVE``                 27.2 s                      9.5 s for 20 steps
==========================  ==========================  ==================================

(and with several multi-threaded torch processes spinning against each other, a training step took
4.7 s instead of 0.21 s). So the CLI keeps GOMP's default when the machine is idle at start and asks
for ``PASSIVE`` when other processes keep half of the CPUs or more busy (:func:`sustained_busy_cpus`: the least of
four readings of 50 ms of ``/proc/stat``, so that a burst, such as a previous process's exit, does not count; the
1-minute load average lags by a minute after a heavy process ends). An explicit
``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` wins. The setting is read once, when torch loads OpenMP:
:func:`apply` after torch is loaded leaves the environment alone (it would only reach child processes).

**Allocator** (:func:`keep_freed_memory`). Training allocates and frees the same large tensors every
step: the gradient of a 128^3 grid of four channels alone is 32 MiB. glibc serves blocks above its
mmap threshold (at most 32 MiB by default) with fresh ``mmap`` pages and unmaps them when freed, so
every step pays a page fault on each 4 KiB page it touches again. Measured here: ``torch.zeros(2097152, 4)``
39 ms with the default, 14 ms with these settings (``python -m benchmarks.alloc_speed`` prints both).
:func:`keep_freed_memory` raises the mmap threshold to 1 GiB and the trim threshold to 2 GiB
(``mallopt``), the same as starting Python with ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``
set; the process then keeps its peak heap instead of giving it back. ``NERFPIPE_KEEP_FREED_MEMORY=0``
leaves the allocator alone; other C libraries are left alone.
"""

import ctypes
import ctypes.util
import os
import sys

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3


def keep_freed_memory(mmap_threshold: int = 1 << 30, trim_threshold: int = (1 << 31) - 1) -> bool:
    """Tune glibc's allocator as described above; returns whether both settings took effect."""
    if os.environ.get("NERFPIPE_KEEP_FREED_MEMORY", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, Windows, musl without mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(M_TRIM_THRESHOLD, trim_threshold))


OMP_WAIT = "unset"
"""What :func:`apply` decided: ``unset`` (never called: a library import), ``spin`` (GOMP's default),
``passive``, ``user`` (an explicit setting was kept) or ``late`` (torch was loaded already)."""


def apply() -> str:
    """Both settings for this process (the CLI's opt-in; see the module docstring); returns :data:`OMP_WAIT`.

    Call it before ``import torch``. Once per process: later calls change nothing.
    """
    global OMP_WAIT
    if OMP_WAIT == "unset":
        OMP_WAIT = "late" if "torch" in sys.modules else choose_omp_wait_policy()
        keep_freed_memory()
    return OMP_WAIT


def choose_omp_wait_policy(environ: "dict | None" = None, busy: "float | None" = None, cpus: "int | None" = None) -> str:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` when other processes keep at least half of the CPUs busy (see
    the module docstring); returns ``user`` (an explicit setting was kept), ``passive`` or ``spin``.

    Args:
        environ: the environment to read and change (default: ``os.environ``).
        busy: CPUs in use by others (default: measured by :func:`sustained_busy_cpus`).
        cpus: CPUs of the machine (default: ``os.cpu_count()``).
    """
    env = os.environ if environ is None else environ
    if "OMP_WAIT_POLICY" in env or "GOMP_SPINCOUNT" in env:
        return "user"
    cpus = cpus or os.cpu_count() or 1
    busy = sustained_busy_cpus() if busy is None else busy
    if busy >= cpus / 2:
        env["OMP_WAIT_POLICY"] = "PASSIVE"
        return "passive"
    return "spin"


def cpu_ticks() -> "tuple[int, int] | None":
    """``(ticks of all CPUs, their idle and iowait ticks)`` since boot, from ``/proc/stat`` (Linux), or None.

    The total is user through steal: the guest fields are already counted in user."""
    try:
        with open("/proc/stat") as f:
            fields = [int(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return sum(fields), idle


def sustained_busy_cpus(windows: int = 4, measure=None) -> float:
    """CPUs in use through ``windows`` consecutive readings of :func:`busy_cpus` (``measure``: another reading, for
    tests): the least of them. Passive waits cost a run on an idle machine 1.8x its step time, and one 50 ms reading
    counts a short burst (a process exiting, a shell command) as load; other processes that keep the CPUs busy do so
    in every reading.

    Example:
        >>> readings = iter([1.9, 0.1, 2.0, 1.8])
        >>> sustained_busy_cpus(measure=lambda: next(readings))
        0.1
    """
    measure = busy_cpus if measure is None else measure
    return min(measure() for _ in range(max(1, windows)))


def busy_cpus(seconds: float = 0.05) -> float:
    """CPUs in use over the next ``seconds`` (from ``/proc/stat``; elsewhere the 1-minute load average)."""
    import time

    def load_average() -> float:
        return os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0

    first = cpu_ticks()
    if first is None:
        return load_average()
    time.sleep(seconds)
    second = cpu_ticks()
    total, idle = (second[0] - first[0], second[1] - first[1]) if second is not None else (0, 0)
    if total <= 0:  # no tick counted in the window (a container's /proc/stat can lag under load): no measurement
        return load_average()
    return (os.cpu_count() or 1) * (total - idle) / total
