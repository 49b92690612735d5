"""Seconds to allocate a grid-sized gradient, with and without :func:`nerfpipe.util.runtime.keep_freed_memory`.

Run: ``python -m benchmarks.alloc_speed`` (each setting in a fresh interpreter, since the allocator
settings are process-wide).
"""

import os
import subprocess
import sys

CODE = """
from nerfpipe.util import runtime
runtime.keep_freed_memory()  # follows NERFPIPE_KEEP_FREED_MEMORY
import time, torch
torch.zeros(2097152, 4)
t = time.perf_counter()
for _ in range(20):
    torch.zeros(2097152, 4)
print(f"{(time.perf_counter() - t) / 20 * 1000:.1f} ms (load {os.getloadavg()[0]:.1f})")
"""


def main() -> None:
    for flag in ("0", "1"):
        env = dict(os.environ, NERFPIPE_KEEP_FREED_MEMORY=flag)
        out = subprocess.run([sys.executable, "-c", "import os" + CODE], env=env, capture_output=True, text=True, check=True)
        print(f"torch.zeros(2097152, 4) with NERFPIPE_KEEP_FREED_MEMORY={flag}: {out.stdout.strip()}")


if __name__ == "__main__":
    main()
