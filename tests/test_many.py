"""``Pipeline.run_many`` on a local Ray: two synthetic captures, both reports and one index; the worker of
one capture killed (SIGKILL) in the middle of training, and Ray's retry resumes its run folder (finished
stages skipped, training continued from its checkpoint) instead of starting it again.

Ray starts locally with 2 CPUs, no dashboard and no usage report; nothing is downloaded. Starting Ray
and its workers takes most of this test's time (~40 s on 2 busy cores), hence ``slow``.
"""

import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from nerfpipe.pipeline.many import ManyConfig, plan
from nerfpipe.pipeline.stages import Pipeline
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.runlock import holder

ITERS, EVERY = 80, 5
CONFIGS = {
    "train": {"model_options": {"levels": [16, 32], "tighten_step": 0, "occupancy": {"resolution": 16}},
              "trainer": {"iters": ITERS, "rays_per_step": 256, "eval_every": 0, "final_eval_views": 1,
                          "checkpoint_every": EVERY, "write_outputs": False, "num_threads": 1}},
}  # fmt: skip


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> "list[Path]":
    from nerfpipe.data.synthetic import SynthConfig, generate

    root = tmp_path_factory.mktemp("captures")
    for name, seed in (("turntable_a", 0), ("turntable_b", 1)):
        generate(root / name, SynthConfig(views=8, width=24, height=24, layout="blender", seed=seed))
    return [root / "turntable_a", root / "turntable_b"]


def kill_when_training(run_dir: Path, killed: list, stop: threading.Event) -> None:
    """SIGKILL the process that holds ``run_dir`` once its training wrote a checkpoint (a Ray worker)."""
    checkpoint = run_dir / "train" / "checkpoint.safetensors"
    while not stop.is_set():
        record = holder(run_dir)
        if checkpoint.exists() and record is not None:
            os.kill(record["pid"], signal.SIGKILL)
            killed.append(record["pid"])
            return
        time.sleep(0.01)


def test_plan_refuses_a_missing_capture_and_two_with_one_name(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "a").mkdir()
    with pytest.raises(NerfpipeError, match="no such file"):
        plan([tmp_path / "a", tmp_path / "missing"], tmp_path / "out")
    with pytest.raises(NerfpipeError, match="two captures are named 'a'"):
        plan([tmp_path / "a", tmp_path / "b" / "a"], tmp_path / "out")
    assert [o.name for o in plan([tmp_path / "a", tmp_path / "b"], tmp_path / "out")] == ["a", "b"]


@pytest.mark.slow
def test_two_captures_on_local_ray_and_a_killed_worker_resumes(captures, tmp_path):
    pytest.importorskip("ray")
    out = tmp_path / "many"
    killed, stop = [], threading.Event()
    watcher = threading.Thread(target=kill_when_training, args=(out / "turntable_a", killed, stop), daemon=True)
    watcher.start()
    updates = []
    try:
        outcomes = Pipeline(["load", "train", "report"], CONFIGS).run_many(
            captures, out, ManyConfig(num_cpus=2, cpus_per_run=1.0, max_retries=2, poll_seconds=0.2), on_update=updates.append)
    finally:
        stop.set()
        watcher.join()

    assert len(killed) == 1 and updates  # the live table had something to show
    a, b = outcomes
    assert [o.status for o in outcomes] == ["done", "done"], [o.error for o in outcomes]
    for o in outcomes:
        assert (Path(o.run_dir) / "report.html").is_file() and o.figures["iterations"] == ITERS
    # the killed capture ran twice and its second attempt resumed: load skipped, training from a checkpoint
    assert a.attempts == 2 and a.stages == {"load": "skipped", "train": "ran", "report": "ran"}
    resumed = a.figures["resumed_at"]
    assert len(resumed) == 1 and EVERY <= resumed[0] < ITERS and resumed[0] % EVERY == 0
    assert b.attempts == 1 and b.figures["resumed_at"] == [] and b.stages["load"] == "ran"

    index = (out / "index.html").read_text()
    assert 'href="turntable_a/report.html"' in index and 'href="turntable_b/report.html"' in index
    summary = json.loads((out / "run_many.json").read_text())
    assert [s["status"] for s in summary] == ["done", "done"] and summary[0]["attempts"] == 2


def test_the_command_refuses_a_missing_capture_in_one_line(tmp_path, capsys):
    from nerfpipe.cli import main

    assert main(["run-many", str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such file or folder" in err[0] and not (tmp_path / "out").exists()
