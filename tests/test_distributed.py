"""Data-parallel training (torchrun, gloo on the CPU): one step of two processes is one step on the union
of their ray batches; the ranks stay identical through occupancy refreshes and box tightening; a
checkpoint of two processes resumes in one; kill -9 of one rank, and torchrun's restart resumes.

The groups are real: ``python -m torch.distributed.run --standalone --nproc-per-node 2`` runs
:data:`CHILD`, which trains and then saves each rank's model tensors (the child writes them, not
nerfpipe: ranks other than 0 write nothing). The reference of the one-step test is computed here,
in one process, from the same streams: each rank's batch drawn as that rank draws it, the
share-weighted sum of the two gradients (the gradient of the mean loss over the union of the
batches), one Adam step.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from nerfpipe.models.base import Callback
from nerfpipe.models.fast import FastConfig
from nerfpipe.training import distributed
from nerfpipe.training.checkpoint import load_checkpoint
from nerfpipe.training.trainer import Trainer, TrainerConfig

REPO = Path(__file__).resolve().parents[1]
MODEL = {"levels": [16, 32], "tighten_step": 6, "coarse_to_fine_every": 0,
         "occupancy": {"resolution": 16, "warmup_steps": 2, "update_every": 2}}  # fmt: skip
TRAINER = {"rays_per_step": 256, "track_rays": 64, "eval_every": 0, "final_eval_views": 1, "video_frames": 0,
           "write_outputs": False, "num_threads": 1}  # fmt: skip

CHILD = """
import json, os, sys, time
from pathlib import Path
import torch
from safetensors.torch import save_file
from nerfpipe.data_adapters import load
from nerfpipe.models.fast import FastConfig
from nerfpipe.training.runs import from_dict
from nerfpipe.training.trainer import Trainer, TrainerConfig

data, out, model, trainer, pause = sys.argv[1], Path(sys.argv[2]), json.loads(sys.argv[3]), json.loads(sys.argv[4]), float(sys.argv[5])
rank, attempt = os.environ["RANK"], os.environ.get("TORCHELASTIC_RESTART_COUNT", "0")
(out.parent / f"pid-{rank}-{attempt}").write_text(str(os.getpid()))
t = Trainer(from_dict(TrainerConfig, trainer), load(data), "fast", from_dict(FastConfig, model), out)
save = lambda name: save_file({k: v.contiguous() for k, v in t.model.state_dict().items()}, str(out.parent / name))
step = t.train_step
def train_step():
    time.sleep(pause)  # slow steps, so that the test can kill a rank mid-training
    mse = step()
    if t.step == 1:
        save(f"rank{rank}-{attempt}-step1.safetensors")
    return mse
t.train_step = train_step
t.train()
save(f"rank{rank}-{attempt}.safetensors")
from nerfpipe.training import distributed
distributed.end_process(0)
"""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from nerfpipe.data.synthetic import SynthConfig, generate

    out = tmp_path_factory.mktemp("dp") / "scene"
    generate(out, SynthConfig(views=8, width=24, height=24, num_points=400))  # COLMAP layout: track rays too
    return out


def torchrun(scene: Path, out: Path, iters: int, pause: float = 0.0, restarts: int = 0, **trainer) -> subprocess.Popen:
    script = out.parent / "child.py"
    script.write_text(CHILD)
    cfg = {**TRAINER, "iters": iters, **trainer}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", f"--max-restarts={restarts}",
           str(script), str(scene), str(out), json.dumps(MODEL), json.dumps(cfg), str(pause)]
    log = open(out.parent / "torchrun.log", "wb")  # a file, not a pipe: a child never blocks on a full pipe
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])), "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)


def finish(proc: subprocess.Popen, out: Path) -> None:
    assert proc.wait(timeout=300) == 0, (out.parent / "torchrun.log").read_text(errors="replace")[-3000:]


ITERS = 10
"""Steps of the two-process run: occupancy refreshes at steps 2, 4, ..., the box tightened at step 6."""


@pytest.fixture(scope="module")
def two_ranks(scene, tmp_path_factory) -> Path:
    """The run folder of a two-process training (the ranks' tensors after step 1 and at the end beside it)."""
    out = tmp_path_factory.mktemp("two") / "run"
    finish(torchrun(scene, out, iters=ITERS, checkpoint_every=5), out)
    return out


def test_one_step_of_two_processes_is_one_step_on_the_union_of_their_rays(scene, two_ranks, tmp_path, monkeypatch):
    from nerfpipe.data_adapters import load
    from nerfpipe.training.runs import from_dict

    got = load_file(str(two_ranks.parent / "rank0-0-step1.safetensors"))

    # the reference: both ranks' batches, drawn from their streams, in this one process
    cfg, model_cfg, data = from_dict(TrainerConfig, {**TRAINER, "iters": 1}), from_dict(FastConfig, MODEL), load(scene)
    ranks = []
    for rank in (0, 1):
        monkeypatch.setattr(distributed, "world", lambda device, r=rank: distributed.World(rank=r, size=2))
        ranks.append(Trainer(cfg, data, "fast", model_cfg, tmp_path / f"ref{rank}"))
    grads, batches = [], []
    for t in ranks:
        t.model.load_state_dict(ranks[0].model.state_dict())  # every rank starts from rank 0's tensors
        t.model.train()
        t.fire(Callback.BEFORE_TRAIN_ITERATION)
        t.model.load_state_dict(ranks[0].model.state_dict())  # and marches rank 0's occupancy grid
        batch = t.sampler.sample(t.rays, t.generator)
        batches.append(batch.rays.directions)
        losses = t.model.get_losses(t.model.get_outputs(batch.rays, batch.background), batch.rgb, batch.depth)
        sum(losses.values()).backward()
        grads.append({n: (p.grad, t.rays / cfg.rays_per_step) for n, p in t.model.named_parameters()})
    assert not torch.equal(batches[0], batches[1])  # each rank draws its own rays
    one = ranks[0]
    for name, p in one.model.named_parameters():
        parts = [(g, w) for g, w in (r[name] for r in grads) if g is not None]
        p.grad = sum(w * g for g, w in parts) if parts else None
    before = {name: p.detach().clone() for name, p in one.model.named_parameters()}
    one.apply_lr()
    one.optimizer.step()

    params = dict(one.model.named_parameters())
    assert params and set(params) <= set(got)
    for name, p in params.items():
        torch.testing.assert_close(got[name], p.detach(), rtol=1e-5, atol=1e-6, msg=name)
    moved = [name for name in params if not torch.equal(got[name], before[name])]
    assert len(moved) >= 3  # grids and MLP took a step: not a comparison of two untouched models


def test_ranks_stay_identical_through_refreshes_and_tightening_and_resume_in_one_process(scene, two_ranks, tmp_path):
    from nerfpipe.data_adapters import load
    from nerfpipe.training.runs import from_dict

    out, iters = two_ranks, ITERS
    r0, r1 = (load_file(str(out.parent / f"rank{r}-0.safetensors")) for r in (0, 1))
    assert set(r0) == set(r1) and "grid.density" in r0
    assert all(torch.equal(r0[k], r1[k]) for k in r0), [k for k in r0 if not torch.equal(r0[k], r1[k])]
    assert float(r0["grid.density"].abs().sum()) > 0  # refreshed, not an untouched grid
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.safetensors", "config.json", "history.json", "metrics.json", "progress"]

    state = load_checkpoint(out / "checkpoint.safetensors")
    assert state["step"] == iters and state["ranks"]["sampler_rng"].shape[0] == 2
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["processes"] == 2 and metrics["iterations"] == iters

    # the checkpoint of two processes goes on in one (rank 0's streams, the whole batch on this rank)
    cfg = from_dict(TrainerConfig, {**TRAINER, "iters": iters + 2, "resume": True})
    t = Trainer(cfg, load(scene), "fast", from_dict(FastConfig, MODEL), shutil.copytree(out, tmp_path / "resumed"))
    assert t.train()["iterations"] == iters + 2 and t.history["resumed_at"] == [iters] and t.rays == cfg.rays_per_step


@pytest.mark.slow
def test_kill_one_rank_and_torchrun_restarts_the_group_from_the_checkpoint(scene, tmp_path):
    out = tmp_path / "run"
    iters, every = 16, 4
    proc = torchrun(scene, out, iters=iters, pause=0.15, restarts=1, checkpoint_every=every)
    checkpoint, deadline = out / "checkpoint.safetensors", time.monotonic() + 120
    while not checkpoint.exists() or not (tmp_path / "pid-1-0").exists():
        assert proc.poll() is None and time.monotonic() < deadline, (tmp_path / "torchrun.log").read_text(errors="replace")[-3000:]
        time.sleep(0.05)
    os.kill(int((tmp_path / "pid-1-0").read_text()), signal.SIGKILL)  # rank 1, mid-training
    finish(proc, out)

    assert (tmp_path / "pid-1-1").exists()  # torchrun started the group again
    metrics = json.loads((out / "metrics.json").read_text())
    resumed = metrics["resumed_at"]
    assert metrics["iterations"] == iters and len(resumed) == 1 and every <= resumed[0] < iters and resumed[0] % every == 0
    history = load_checkpoint(checkpoint)["history"]["train"]
    assert [row[0] for row in history] == list(range(1, iters + 1))
    r0, r1 = (load_file(str(tmp_path / f"rank{r}-1.safetensors")) for r in (0, 1))
    assert all(torch.equal(r0[k], r1[k]) for k in r0)


def test_the_pipeline_under_torchrun_trains_on_every_rank_and_rank_0_alone_writes(scene, tmp_path):
    toml = tmp_path / "pipe.toml"
    trainer = {**TRAINER, "iters": 4, "final_eval_views": 1}
    toml.write_text('stages = ["load", "train"]\n[train]\nmodel_options = ' + _toml_table(MODEL) + "\n[train.trainer]\n"
                    + "\n".join(f"{k} = {json.dumps(v)}" for k, v in trainer.items()) + "\n")
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m", "nerfpipe", "run",
           str(scene), "--pipeline", str(toml), "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert proc.stdout.count("nerfpipe run:") == 1  # one summary table: rank 0's
    metrics = json.loads((out / "train" / "metrics.json").read_text())
    assert metrics["processes"] == 2 and metrics["iterations"] == 4
    assert sorted(p.name for p in (out / "stages").iterdir()) == ["load.done.json", "train.done.json"]


def _toml_table(d: dict) -> str:
    """An inline TOML table of a JSON-like dict."""
    items = (f"{k} = {_toml_table(v) if isinstance(v, dict) else json.dumps(v)}" for k, v in d.items())
    return "{ " + ", ".join(items) + " }"
