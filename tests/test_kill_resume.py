"""kill -9 at any point of a pipeline run, then the same command again: it resumes, finishes, and scores
as an uninterrupted run; nothing written before the kill is lost or left half-written.

Each killed run is a child process that pauses at a named point (a function of the pipeline wrapped by
the child script, not a hook in nerfpipe), writes a marker file and sleeps; the test kills it with
SIGKILL once the marker appears, checks what is on disk, and runs the pipeline again in-process.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nerfpipe.pipeline.stages import Pipeline
from nerfpipe.training.checkpoint import load_checkpoint
from nerfpipe.util.runlock import LOCK_FILE

REPO = Path(__file__).resolve().parents[1]
CHAIN = ["load", "train", "render", "mesh"]
ITERS, EVERY = 20, 5
CONFIGS = {
    "train": {"model": "fast", "model_options": {"levels": [16, 32], "tighten_step": 0, "occupancy": {"resolution": 32}},
              "trainer": {"iters": ITERS, "rays_per_step": 256, "eval_every": 0, "final_eval_views": 2,
                          "checkpoint_every": EVERY, "write_outputs": False, "num_threads": 1}},
    "render": {"frames": 3},
    "mesh": {"mesh": {"method": "mc", "resolution": 32, "support_plane": False, "free_space_passes": 0, "remove_unseen": False},
             "evaluate": False},
}  # fmt: skip

KILLED = """
import json, sys, time
from pathlib import Path
import nerfpipe.outputs.artifacts, nerfpipe.training.checkpoint, nerfpipe.mesh.pipeline, nerfpipe.training.trainer
from nerfpipe.pipeline.stages import Pipeline

point, data, run_dir, marker, configs = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], json.loads(sys.argv[5])

def pause_after(owner, name, nth):
    original, calls = getattr(owner, name), []
    def wrapper(*args, **kwargs):
        out = original(*args, **kwargs)
        calls.append(1)
        if len(calls) == nth:
            Path(marker).write_text("")
            time.sleep(120)
        return out
    setattr(owner, name, wrapper)

owner, name, nth = {
    "training": (nerfpipe.training.trainer.Trainer, "train_step", %(mid)d),  # between the checkpoints at steps %(every)d and %(next)d
    "checkpoint": (nerfpipe.training.checkpoint, "save_file", 2),  # the second checkpoint in its temporary, not yet in place
    "render": (nerfpipe.outputs.artifacts, "write_sequence", 1),  # frames written into render/'s temporary folder
    "mesh": (nerfpipe.mesh.pipeline, "write_meshes", 1),  # mesh.ply written into mesh/'s temporary folder
}[point]
pause_after(owner, name, nth)
Pipeline(%(chain)r, configs).run(data, run_dir)
""" % {"mid": EVERY + 3, "every": EVERY, "next": 2 * EVERY, "chain": CHAIN}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from nerfpipe.data.synthetic import SynthConfig, generate

    out = tmp_path_factory.mktemp("killed") / "scene"
    generate(out, SynthConfig(views=10, width=24, height=24, layout="blender"))
    return out


@pytest.fixture(scope="module")
def uninterrupted(scene, tmp_path_factory) -> dict:
    return Pipeline(CHAIN, CONFIGS).run(scene, tmp_path_factory.mktemp("straight"))["metrics"]


def kill_at(point: str, scene: Path, run_dir: Path, tmp_path: Path) -> None:
    marker = tmp_path / f"paused-{point}"
    cmd = [sys.executable, "-c", KILLED, point, str(scene), str(run_dir), str(marker), json.dumps(CONFIGS)]
    log = tmp_path / f"child-{point}.log"  # a file, not a pipe: a child never blocks on a full pipe
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}, stdout=out, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 120
    while not marker.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            proc.wait()
            pytest.fail(f"the child ended before reaching {point}: {log.read_text(errors='replace')[-2000:]}")
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()


def stage_done(run_dir: Path, name: str) -> bool:
    return (run_dir / "stages" / f"{name}.done.json").is_file()


def temporaries(run_dir: Path) -> "list[str]":
    return sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob(".tmp-*"))


@pytest.mark.parametrize(
    "point, rerun",
    [
        ("training", ["skipped", "ran", "ran", "ran"]),
        ("checkpoint", ["skipped", "ran", "ran", "ran"]),
        ("render", ["skipped", "skipped", "ran", "ran"]),
        ("mesh", ["skipped", "skipped", "skipped", "ran"]),
    ],
)
def test_killed_run_resumes_and_scores_as_an_uninterrupted_one(point, rerun, scene, uninterrupted, tmp_path):
    import imageio.v3 as iio
    import trimesh

    run_dir = tmp_path / "run"
    kill_at(point, scene, run_dir, tmp_path)

    # what the kill left: finished stages and the last checkpoint whole, the interrupted artifact absent
    checkpoint = run_dir / "train" / "checkpoint.safetensors"
    if point in ("training", "checkpoint"):
        assert not stage_done(run_dir, "train") and load_checkpoint(checkpoint)["step"] == EVERY
        first_steps = load_checkpoint(checkpoint)["history"]["train"]
        left = temporaries(run_dir)  # the second checkpoint's temporary, when killed while writing it
        assert left == [] if point == "training" else len(left) == 1 and left[0].startswith("train/.tmp-")
    else:
        assert stage_done(run_dir, "train") and load_checkpoint(checkpoint)["step"] == ITERS
        assert not (run_dir / point).exists() and len(temporaries(run_dir)) == 1  # the stage's folder, never in place
    assert (run_dir / LOCK_FILE).is_file()  # left by the killed holder; the kernel released its lock

    result = Pipeline(CHAIN, CONFIGS).run(scene, run_dir)
    assert [r.status for r in result.records] == rerun
    metrics = json.loads((run_dir / "train" / "metrics.json").read_text())
    assert metrics["iterations"] == ITERS and abs(metrics["val_psnr"] - uninterrupted["val_psnr"]) <= 0.3
    history = load_checkpoint(checkpoint)["history"]["train"]
    assert [row[0] for row in history] == list(range(1, ITERS + 1))
    if point in ("training", "checkpoint"):  # continued from the checkpoint: its steps (and their timings) kept
        assert history[:EVERY] == first_steps
    assert iio.imread(run_dir / "render" / "orbit.gif", index=None).shape[-1] == 3
    assert len(trimesh.load(run_dir / "mesh" / "mesh.ply").faces) > 0
    assert temporaries(run_dir) == [] and list(run_dir.rglob(LOCK_FILE)) == []  # the run's and the training's


def test_a_folder_moved_aside_by_a_killed_replace_is_put_back(tmp_path):
    """Killed between the two renames of a folder replace: the target is missing, its old content is
    aside and the new one still in its temporary. The next run's sweep puts the old one back."""
    from nerfpipe.util.atomic import sweep_temporaries

    (tmp_path / ".tmp-old-0123abcd-render").mkdir()
    (tmp_path / ".tmp-old-0123abcd-render" / "orbit.gif").write_text("the finished render")
    (tmp_path / ".tmp-89abcdef-render").mkdir()
    (tmp_path / ".tmp-89abcdef-render" / "orbit.gif").write_text("the new one")
    (tmp_path / "mesh").mkdir()
    (tmp_path / ".tmp-old-4567cdef-mesh").mkdir()  # its replacement arrived: the aside copy is garbage
    sweep_temporaries(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh", "render"]
    assert (tmp_path / "render" / "orbit.gif").read_text() == "the finished render"


def test_what_is_written_reaches_the_disk_before_and_after_its_rename(tmp_path, monkeypatch):
    """fsync of every file written (a file, and each file of a folder), then of the folder holding the renamed entry."""
    import os

    from nerfpipe.util import atomic

    synced = []
    real = os.fsync
    monkeypatch.setattr(atomic.os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real(fd)))
    atomic.write_text(tmp_path / "a.json", "{}")
    assert Path(synced[0]).name.startswith(".tmp-") and synced[0].endswith("-a.json")  # the data, in its temporary, first
    assert synced[-1] == str(tmp_path)  # then the folder, after the rename
    synced.clear()
    with atomic.atomic_path(tmp_path / "render") as tmp:
        (tmp / "sub").mkdir(parents=True)
        (tmp / "sub" / "f.png").write_bytes(b"x")
    assert any(s.endswith("/sub/f.png") for s in synced) and synced[-1] == str(tmp_path)
    assert (tmp_path / "render" / "sub" / "f.png").read_bytes() == b"x"
