"""The process settings the CLI applies (OpenMP waiting, glibc's allocator), and a library import that applies none."""

import os
import platform
import subprocess
import sys

import pytest

from nerfpipe.util.runtime import busy_cpus, choose_omp_wait_policy, keep_freed_memory, sustained_busy_cpus


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_settings_take_effect_on_glibc():
    assert keep_freed_memory()


def test_environment_opt_out(monkeypatch):
    monkeypatch.setenv("NERFPIPE_KEEP_FREED_MEMORY", "0")
    assert not keep_freed_memory()


def test_big_tensors_still_allocate_and_free():
    """A 1.25 GiB block is above the raised mmap threshold and a 64 MiB one below it: both work."""
    code = "import nerfpipe.util.runtime as r; r.apply(); import torch; a = torch.ones(335544320); b = torch.ones(16777216); print(float(a[-1] + b[-1]))"
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


def test_a_busy_process_keeps_the_cpus_busy_in_every_reading_a_burst_in_one():
    """The decision reads the least of several windows: a hog is seen in all of them, a burst (a process exiting
    just as a run starts) in one only, and a burst must not cost an idle machine's run its spinning waits."""
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        import time

        time.sleep(0.3)
        assert sustained_busy_cpus() > 0.7
    finally:
        hog.kill()
    readings = iter([2.0, 1.9, 0.2, 2.0])
    assert sustained_busy_cpus(measure=lambda: next(readings)) == 0.2
    env: dict = {}
    assert choose_omp_wait_policy(env, busy=sustained_busy_cpus(measure=iter([2.0, 0.1, 2.0, 2.0]).__next__), cpus=2) == "spin"


def _without_openmp_settings() -> dict:
    return {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}


def test_the_cli_decides_before_torch_loads():
    """``nerfpipe.cli`` imports no torch, and its ``main`` makes the settings first (so OpenMP sees them)."""
    code = ("import io, sys, contextlib, nerfpipe.cli as cli, nerfpipe.util.runtime as r, os\n"
            "assert 'torch' not in sys.modules\n"
            "with contextlib.redirect_stdout(io.StringIO()): cli.main(['stages'])\n"
            "print(r.OMP_WAIT, os.environ.get('OMP_WAIT_POLICY'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=_without_openmp_settings())
    decision, policy = out.stdout.split()
    assert (decision, policy) in {("spin", "None"), ("passive", "PASSIVE")}


SPY = """
import ctypes, os, sys
calls = []
class Spy(ctypes.CDLL):  # records every C function looked up, mallopt included
    def __getattr__(self, name):
        calls.append(name)
        return super().__getattr__(name)
ctypes.CDLL = Spy
environ = dict(os.environ)
import nerfpipe, nerfpipe.util.runtime as r
from nerfpipe import Cameras, SceneData, volrend  # the lazy names load torch
print(r.OMP_WAIT, "mallopt" in calls, dict(os.environ) == environ, "torch" in sys.modules)
"""


def test_importing_nerfpipe_changes_nothing_in_the_process():
    """No /proc sampling decision, no OMP_WAIT_POLICY, no mallopt: a library import leaves the host alone."""
    out = subprocess.run([sys.executable, "-c", SPY], capture_output=True, text=True, check=True, env=_without_openmp_settings())
    assert out.stdout.split() == ["unset", "False", "True", "True"]


def test_apply_after_torch_leaves_the_environment_alone():
    code = "import torch, os, nerfpipe.util.runtime as r; print(r.apply(), r.apply(), os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=_without_openmp_settings())
    assert out.stdout.split() == ["late", "late", "None"]


TRAIN = """
import os, sys, torch
import torch._dynamo  # torch's optimisers import it, and it sets TORCHINDUCTOR_CACHE_DIR: torch's doing, in any host
environ, threads = dict(os.environ), torch.get_num_threads()
torch.manual_seed(1234)  # the host's own stream: a library must not move it
host_rng = torch.get_rng_state()
import nerfpipe.util.runtime as r
from nerfpipe.data_adapters import load
from nerfpipe.models.base import Callback
from nerfpipe.models.fast import FastConfig
from nerfpipe.training.trainer import Trainer, TrainerConfig
cfg = TrainerConfig(iters=6, rays_per_step=128, eval_every=3, final_eval_views=1, video_frames=0, checkpoint_every=3,
                    num_threads=1 if threads > 1 else 2, seed=5, write_outputs=False)
model = FastConfig(levels=(8, 16), occupancy=FastConfig().occupancy.__class__(warmup_steps=0, update_every=2))
trainer = Trainer(cfg, load(sys.argv[1]), "fast", model, sys.argv[2])
seen = []
trainer.hooks.setdefault(Callback.AFTER_TRAIN_ITERATION, []).append(lambda step: seen.append(torch.get_num_threads()))
trainer.train()
print(r.OMP_WAIT, dict(os.environ) == environ, torch.equal(torch.get_rng_state(), host_rng),
      torch.get_num_threads() == threads, set(seen) == {cfg.num_threads})
"""


def test_a_training_leaves_the_process_as_it_found_it(tmp_path):
    """Import, train (occupancy refreshes, jitter, validation, checkpoints): the environment, torch's global
    stream and thread count are as before; the run's own thread count held while it trained."""
    from nerfpipe.data.synthetic import SynthConfig, generate

    generate(tmp_path / "scene", SynthConfig(views=8, width=16, height=16, layout="blender"))
    out = subprocess.run([sys.executable, "-c", TRAIN, str(tmp_path / "scene"), str(tmp_path / "run")],
                         capture_output=True, text=True, env=_without_openmp_settings())
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-5:] == ["unset", "True", "True", "True", "True"]
