"""The runtime settings nerfpipe applies at import: OpenMP waiting and glibc's allocator."""

import platform
import subprocess
import sys

import pytest

from nerfpipe.runtime import busy_cpus, choose_omp_wait_policy, keep_freed_memory


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


def test_an_explicit_openmp_setting_wins():
    for key in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT"):
        env = {key: "1000"}
        assert choose_omp_wait_policy(env, busy=2.0, cpus=2) == "user" and env == {key: "1000"}


def test_passive_waits_only_on_a_busy_machine():
    busy, idle = {}, {}
    assert choose_omp_wait_policy(busy, busy=1.0, cpus=2) == "passive" and busy == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert choose_omp_wait_policy(idle, busy=0.3, cpus=2) == "spin" and idle == {}


def test_busy_cpus_sees_a_busy_process():
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        import time

        time.sleep(0.3)
        assert busy_cpus(0.3) > 0.7
    finally:
        hog.kill()


def test_the_import_decision_is_recorded():
    code = "import nerfpipe.runtime as r, nerfpipe, os; print(r.OMP_WAIT, os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={k: v for k, v in __import__("os").environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")})
    decision, policy = out.stdout.split()
    assert (decision, policy) in {("spin", "None"), ("passive", "PASSIVE")}
