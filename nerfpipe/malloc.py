"""Keep large freed blocks in the process instead of returning them to the system (glibc only).

Training allocates and frees the same large tensors every step: the gradient of a 128^3 grid of four
channels alone is 32 MiB. glibc serves blocks above its mmap threshold (at most 32 MiB by default)
with fresh ``mmap`` pages and unmaps them when freed, so every step pays a page fault on each 4 KiB
page it touches again. Measured on this 2-core machine: ``torch.zeros(2097152, 4)`` 39 ms with the
default, 14 ms with these settings (``python -m benchmarks.alloc_speed`` prints both).

:func:`keep_freed_memory` raises the mmap threshold to 1 GiB and the trim threshold to 2 GiB
(``mallopt``), the same as starting Python with ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``
set. The process then keeps its peak heap after a step instead of giving it back. Set
``NERFPIPE_KEEP_FREED_MEMORY=0`` to leave the allocator alone; other C libraries are left alone.
"""

import ctypes
import ctypes.util
import os

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
