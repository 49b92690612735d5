"""One nerfpipe process at a time in a run folder: a second run, stage or training refuses with one
line while the first lives (another process or another thread); a lock left by kill -9 is taken over."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from nerfpipe.data_adapters import load
from nerfpipe.models.vanilla import VanillaConfig
from nerfpipe.pipeline.stages import Pipeline, StageContext, StageSpec, atomic_path
from nerfpipe.training.trainer import Trainer, TrainerConfig
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.runlock import LOCK_FILE, holder, run_lock

REPO = Path(__file__).resolve().parents[1]
HOLD = """
import sys, time
from pathlib import Path
from nerfpipe.util.runlock import run_lock
with run_lock(sys.argv[1]):
    Path(sys.argv[2]).write_text("")
    time.sleep(120)
"""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from nerfpipe.data.synthetic import SynthConfig, generate

    out = tmp_path_factory.mktemp("lock") / "scene"
    generate(out, SynthConfig(views=8, width=16, height=16, layout="blender"))
    return out


def one_stage(calls: list) -> "dict[str, StageSpec]":
    def run(config, ctx: StageContext) -> dict:
        calls.append(ctx.run_dir)
        with atomic_path(ctx.path("a.txt")) as tmp:
            tmp.write_text("a")
        return {}

    return {"a": StageSpec("a", "toy", TrainerConfig, run, (), ("a.txt",))}


def holding(run_dir: Path, tmp_path: Path) -> subprocess.Popen:
    """A process that holds the folder's lock until killed (returns once it holds it)."""
    marker = tmp_path / f"holding-{time.monotonic_ns()}"
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(run_dir), str(marker)], env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))})
    deadline = time.monotonic() + 60
    while not marker.exists():
        assert proc.poll() is None and time.monotonic() < deadline, "the holder died before taking the lock"
        time.sleep(0.05)
    return proc


def test_a_second_process_is_refused_and_a_killed_holder_leaves_no_stale_lock(tiny, tmp_path):
    run_dir, calls = tmp_path / "run", []
    proc = holding(run_dir, tmp_path)
    try:
        with pytest.raises(NerfpipeError, match=f"in use by nerfpipe process {proc.pid} on "):
            Pipeline(["a"], registry=one_stage(calls)).run(None, run_dir)
        cli = subprocess.run([sys.executable, "-m", "nerfpipe", "run", str(tiny), "--stages", "load", "--out", str(run_dir)],
                             capture_output=True, text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))})
        assert cli.returncode == 2 and len(cli.stderr.strip().splitlines()) == 1, cli.stderr
        assert "in use by nerfpipe process" in cli.stderr and "Traceback" not in cli.stderr
        assert calls == [] and sorted(p.name for p in run_dir.iterdir()) == [LOCK_FILE]  # nothing written
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert holder(run_dir)["pid"] == proc.pid  # the file stays after kill -9, but the kernel dropped the lock
    Pipeline(["a"], registry=one_stage(calls)).run(None, run_dir)
    assert calls == [run_dir] and not (run_dir / LOCK_FILE).exists()


def test_a_lock_file_of_a_dead_process_is_taken_over(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    tmp_path.joinpath(LOCK_FILE).write_text(json.dumps({"pid": dead.pid, "host": os.uname().nodename, "started": "", "command": "nerfpipe run"}))
    calls = []
    Pipeline(["a"], registry=one_stage(calls)).run(None, tmp_path)
    assert calls == [tmp_path] and (tmp_path / "a.txt").read_text() == "a"


def test_another_thread_is_refused_too(tiny, tmp_path):
    """flock belongs to an open file: a second lock in the same process (a thread, a second Trainer) is refused."""
    taken, release = threading.Event(), threading.Event()

    def hold() -> None:
        with run_lock(tmp_path):
            taken.set()
            release.wait(60)

    thread = threading.Thread(target=hold)
    thread.start()
    try:
        assert taken.wait(60)
        cfg = TrainerConfig(iters=1, rays_per_step=16, eval_every=0, video_frames=0, write_outputs=False)
        with pytest.raises(NerfpipeError, match=f"in use by nerfpipe process {os.getpid()}"):
            Trainer(cfg, load(tiny), "vanilla", VanillaConfig(num_samples=4), tmp_path).train()
        with pytest.raises(NerfpipeError, match="in use"):
            Pipeline(["a"], registry=one_stage([])).run(None, tmp_path)
    finally:
        release.set()
        thread.join()
    assert not (tmp_path / LOCK_FILE).exists() and not (tmp_path / "config.json").exists()


def test_the_stage_command_takes_the_lock(tmp_path, capsys):
    from nerfpipe.cli import main

    Pipeline(["a"], registry=one_stage([])).run(None, tmp_path)  # a run folder (run.json)
    with run_lock(tmp_path):
        assert main(["stage", "load", str(tmp_path)]) == 2
    assert "in use" in capsys.readouterr().err


def test_a_run_folder_under_a_file_is_one_line(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(NerfpipeError, match="cannot create the run folder"):
        with run_lock(tmp_path / "file" / "run"):
            pass
