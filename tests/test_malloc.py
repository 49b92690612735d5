"""The allocator setting nerfpipe applies at import (glibc's mallopt)."""

import platform
import subprocess
import sys

import pytest

from nerfpipe.malloc import keep_freed_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_settings_take_effect_on_glibc():
    assert keep_freed_memory()


def test_environment_opt_out(monkeypatch):
    monkeypatch.setenv("NERFPIPE_KEEP_FREED_MEMORY", "0")
    assert not keep_freed_memory()


def test_big_tensors_still_allocate_and_free():
    """A 1.25 GiB block is above the raised mmap threshold and a 64 MiB one below it: both work."""
    code = "import nerfpipe, torch; a = torch.ones(335544320); b = torch.ones(16777216); print(float(a[-1] + b[-1]))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "2.0"
