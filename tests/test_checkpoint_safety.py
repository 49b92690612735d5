"""Checkpoints are read without executing code: a crafted pickle in a shared run folder is refused
with one line naming the file, and nothing it asks for runs; real checkpoints round-trip exactly."""

import json
import pickle

import pytest
import torch

from nerfpipe.cli import main
from nerfpipe.errors import NerfpipeError
from nerfpipe.runs import load_checkpoint, save_checkpoint


class _Payload:
    """Unpickling this creates a marker file (stands in for ``os.system``)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _malicious(path, marker):
    with open(path, "wb") as f:
        pickle.dump({"model": {}, "payload": _Payload(marker)}, f)


def test_crafted_checkpoint_is_refused_and_runs_nothing(tmp_path):
    ckpt, marker = tmp_path / "checkpoint.pt", tmp_path / "pwned"
    _malicious(ckpt, marker)
    with pytest.raises(NerfpipeError, match="checkpoint"):
        load_checkpoint(ckpt)
    assert not marker.exists()


def test_render_of_a_crafted_run_folder_exits_2_and_runs_nothing(tmp_path, scene_path, capsys):
    run, marker = tmp_path / "run", tmp_path / "pwned"
    run.mkdir()
    data = scene_path("lego_200x200") / "lego_200x200.npz"
    (run / "config.json").write_text(json.dumps({"data": str(data), "model": "fast", "model_config": {}, "trainer": {}}))
    _malicious(run / "checkpoint.pt", marker)
    assert main(["render", str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "checkpoint.pt" in err[0]
    assert not marker.exists()


def test_not_a_checkpoint_is_one_clear_error(tmp_path):
    junk = tmp_path / "checkpoint.pt"
    junk.write_bytes(b"this is not a checkpoint")
    with pytest.raises(NerfpipeError, match="not a nerfpipe checkpoint"):
        load_checkpoint(junk)
    torch.save({"weights": torch.zeros(2)}, junk)  # safe, but not ours
    with pytest.raises(NerfpipeError, match="no model state"):
        load_checkpoint(junk)


def test_round_trip_is_exact(tmp_path):
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model(torch.ones(4, 3)).sum().backward()
    opt.step()
    state = {"step": 7, "train_seconds": 1.5, "model": model.state_dict(), "optimizer": opt.state_dict(),
             "torch_rng": torch.get_rng_state(), "history": {"train": [[1, 0.1, 20.0]], "val": []}}
    save_checkpoint(tmp_path / "c.pt", state)
    back = load_checkpoint(tmp_path / "c.pt")
    assert back["step"] == 7 and back["history"] == state["history"]
    torch.testing.assert_close(back["model"]["weight"], model.weight.detach())
    opt2 = torch.optim.Adam(torch.nn.Linear(3, 2).parameters(), lr=1e-3)
    opt2.load_state_dict(back["optimizer"])
    torch.testing.assert_close(opt2.state_dict()["state"][0]["exp_avg"], opt.state_dict()["state"][0]["exp_avg"])
