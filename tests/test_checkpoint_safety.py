"""Checkpoints are read without executing code: a crafted pickle in a shared run folder is refused
with one line naming the file, and nothing it asks for runs; real checkpoints round-trip exactly."""

import json
import math
import pickle
import struct

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from nerfpipe.cli import main
from nerfpipe.training.checkpoint import CHECKPOINT, LEGACY_CHECKPOINT, find_checkpoint, load_checkpoint, save_checkpoint
from nerfpipe.util.errors import NerfpipeError


class _Payload:
    """Unpickling this creates a marker file (stands in for ``os.system``)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _malicious(path, marker, writer):
    """A checkpoint-looking pickle whose loading would create ``marker``: raw ``pickle`` or ``torch.save``."""
    state = {"model": {"w": torch.zeros(2)}, "payload": _Payload(marker)}
    if writer == "pickle":
        with open(path, "wb") as f:
            pickle.dump(state, f)
    else:
        torch.save(state, path)


@pytest.mark.parametrize("writer", ["pickle", "torch.save"])
@pytest.mark.parametrize("name", [CHECKPOINT, LEGACY_CHECKPOINT])
def test_crafted_pickle_checkpoint_is_refused_and_runs_nothing(tmp_path, name, writer):
    ckpt, marker = tmp_path / name, tmp_path / "pwned"
    _malicious(ckpt, marker, writer)
    with pytest.raises(NerfpipeError, match="old pickle format") as err:
        load_checkpoint(ckpt)
    assert str(err.value).startswith(str(ckpt)) and "\n" not in str(err.value)
    assert not marker.exists()


def test_run_folder_with_only_a_pickle_checkpoint_is_refused_not_ignored(tmp_path):
    _malicious(tmp_path / LEGACY_CHECKPOINT, tmp_path / "pwned", "torch.save")
    with pytest.raises(NerfpipeError, match=f"{LEGACY_CHECKPOINT}: checkpoint is in the old pickle format"):
        find_checkpoint(tmp_path)  # resume and render ask this first
    assert not (tmp_path / "pwned").exists()
    save_checkpoint(tmp_path / CHECKPOINT, {"model": {}})
    assert find_checkpoint(tmp_path) == tmp_path / CHECKPOINT  # a retrained run has both: the new one wins
    assert find_checkpoint(tmp_path / "empty") is None


@pytest.mark.parametrize("name", [CHECKPOINT, LEGACY_CHECKPOINT])
def test_render_of_a_crafted_run_folder_exits_2_and_runs_nothing(tmp_path, scene_path, capsys, name):
    run, marker = tmp_path / "run", tmp_path / "pwned"
    run.mkdir()
    data = scene_path("lego_200x200") / "lego_200x200.npz"
    (run / "config.json").write_text(json.dumps({"data": str(data), "model": "fast", "model_config": {}, "trainer": {}}))
    _malicious(run / name, marker, "torch.save")
    assert main(["render", str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{run / name}: checkpoint is in the old pickle format" in err[0]
    assert not marker.exists()


def _with_state(path, state_json, version="1", tensors=None):
    save_file(tensors or {}, str(path), metadata={"format": "nerfpipe-checkpoint", "version": version, "state": state_json})


def test_not_a_checkpoint_is_one_clear_error(tmp_path):
    f = tmp_path / CHECKPOINT
    cases = [
        (lambda: f.write_bytes(b"this is not a checkpoint"), "not a nerfpipe checkpoint \\(unreadable\\)"),
        (lambda: f.write_bytes(b""), "unreadable"),
        (lambda: f.write_bytes(struct.pack("<Q", 10**12) + b"{"), "unreadable"),  # a header larger than the file
        (lambda: save_file({"w": torch.zeros(2)}, str(f)), "a safetensors file without its state"),  # safe, but not ours
        (lambda: _with_state(f, "{not json"), "malformed state"),
        (lambda: _with_state(f, json.dumps({"model": {"w": {"$tensor": "absent"}}})), "malformed state"),
        (lambda: _with_state(f, "[" * 100_000 + "]" * 100_000), "malformed state"),
        (lambda: _with_state(f, json.dumps({"model": {"$items": [[{"k": 1}, 2]]}})), "malformed state"),
        (lambda: _with_state(f, json.dumps({"step": 3})), "no model state"),
        (lambda: _with_state(f, json.dumps({"model": {}}), version="2"), "format version 2, newer"),
    ]
    for write, message in cases:
        write()
        with pytest.raises(NerfpipeError, match=message) as err:
            load_checkpoint(f)
        assert str(err.value).startswith(f"{f}: ") and "\n" not in str(err.value)
    with pytest.raises(NerfpipeError, match="checkpoint is missing"):
        load_checkpoint(tmp_path / "absent" / CHECKPOINT)


def _assert_same(a, b, where="state"):
    """Equal values of equal types, all the way down (tensors: dtype, shape and bits; dicts: order)."""
    assert type(a) is type(b) or isinstance(a, dict) and isinstance(b, dict), where
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        assert getattr(a, "_metadata", None) == getattr(b, "_metadata", None), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}/{i}")
    else:
        assert a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)), where


def _trained(fused: bool):
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4), torch.nn.Linear(4, 2))
    opt = torch.optim.Adam([{"params": model[0].parameters(), "lr": 1e-2, "initial_lr": 1e-2},
                            {"params": list(model[1].parameters()) + list(model[2].parameters()), "lr": 1e-3}], fused=fused)
    for _ in range(2):
        opt.zero_grad()
        model(torch.randn(5, 3)).square().sum().backward()
        opt.step()
    return model, opt


@pytest.mark.parametrize("fused", [False, True])
def test_round_trip_is_exact_and_the_optimizer_resumes(tmp_path, fused):
    model, opt = _trained(fused)
    state = {"step": 7, "train_seconds": 1.0 / 3.0, "model": model.state_dict(), "optimizer": opt.state_dict(),
             "torch_rng": torch.get_rng_state(), "sampler_rng": torch.Generator().manual_seed(5).get_state(),
             "history": {"train": [[1, 0.1, 20.0], [2, 0.2, float("nan")]], "val": [[2, 0.2, 21.5, 0.7, 3]]},
             "odd": {"$x": (1, "a", None, True), 3: torch.tensor(2.5, dtype=torch.float64), "3": torch.arange(4),
                     "more": [torch.zeros(0, 2), torch.tensor([True, False]), torch.ones(2, dtype=torch.bfloat16)]}}
    path = save_checkpoint(tmp_path / CHECKPOINT, state)
    assert sorted(p.name for p in tmp_path.iterdir()) == [CHECKPOINT]  # written atomically: no temporary left
    back = load_checkpoint(path)
    _assert_same(state, back)

    model2, opt2 = _trained(fused)
    for p in model2.parameters():
        p.data.zero_()
    model2.load_state_dict(back["model"])
    opt2.load_state_dict(back["optimizer"])
    batch = torch.randn(5, 3)
    for m, o in ((model, opt), (model2, opt2)):
        o.zero_grad()
        m(batch).square().sum().backward()
        o.step()
    for p, q in zip(model.parameters(), model2.parameters()):
        assert torch.equal(p, q)  # one more step from the checkpoint is bit-identical


def test_loaded_tensors_are_owned_and_writable(tmp_path):
    path = save_checkpoint(tmp_path / CHECKPOINT, {"model": {"w": torch.arange(6.0)}})
    w = load_checkpoint(path)["model"]["w"]
    save_checkpoint(path, {"model": {"w": torch.zeros(1)}})  # the file changes under a resumed optimiser
    w += 1
    assert w.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]


def test_tensors_that_share_memory_are_saved_apart(tmp_path):
    base = torch.arange(8.0)
    state = {"model": {"a": base, "a_view": base[2:5], "strided": base[::2], "same": base}}
    back = load_checkpoint(save_checkpoint(tmp_path / CHECKPOINT, state))["model"]
    for k, v in state["model"].items():
        assert torch.equal(back[k], v), k


def test_saving_anything_but_data_is_a_type_error_and_keeps_the_old_checkpoint(tmp_path):
    path = save_checkpoint(tmp_path / CHECKPOINT, {"model": {"w": torch.ones(2)}, "step": 1})
    for bad, where in ((np.float32(1.0), "history/0"), (_Payload(tmp_path / "x"), "history/0"), ({(1, 2): 3}, "history/0")):
        with pytest.raises(TypeError, match=where):
            save_checkpoint(path, {"model": {}, "history": [bad]})
    assert load_checkpoint(path)["step"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == [CHECKPOINT]
