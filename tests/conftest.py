"""Shared fixtures: the real-data folder, devices, dtypes and tolerances (STYLE habit 11)."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # pytest -n 2 shares the cores: no spinning waits (nerfpipe/util/runtime.py)
import torch

REPO = Path(__file__).resolve().parents[1]
DATA_ENV = "NERFPIPE_DATA"


def _data_root() -> Path:
    return Path(os.environ.get(DATA_ENV, REPO.parent / "shared" / "data")).resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (or ``$NERFPIPE_DATA``). Missing data fails loudly under CI, skips locally."""
    root = _data_root()
    if not root.is_dir():
        msg = f"real test data not found at {root} (set {DATA_ENV})"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return root


@pytest.fixture(scope="session")
def scene_path(shared_data):
    """``scene_path("colmap_mouse")``: a scene folder under the shared data, failing loudly when absent."""

    def get(name: str) -> Path:
        p = shared_data / name
        if not p.exists():
            pytest.fail(f"shared data set {name} missing at {p}")
        return p

    return get


TINY_LEGO_SIZE = 40
"""Side of the tiny lego views (:func:`tiny_lego`) in pixels."""


@pytest.fixture(scope="session")
def tiny_lego_npz(scene_path, tmp_path_factory) -> Path:
    """Every 4th training view of lego_200x200 and 2 validation views, area-resized to 40x40: a CS180 npz in a
    temp folder (not the repo), a lego-like scene a fast model trains on in milliseconds per step."""
    import numpy as np
    import torch.nn.functional as F

    def shrink(images):
        t = torch.from_numpy(images).permute(0, 3, 1, 2).float()
        small = F.interpolate(t, size=(TINY_LEGO_SIZE, TINY_LEGO_SIZE), mode="area")
        return small.round().clamp(0, 255).byte().permute(0, 2, 3, 1).numpy()

    src = np.load(scene_path("lego_200x200") / "lego_200x200.npz")
    out = tmp_path_factory.mktemp("tiny_lego") / "tiny_lego.npz"
    np.savez(out, images_train=shrink(src["images_train"][::4]), c2ws_train=src["c2ws_train"][::4], images_val=shrink(src["images_val"][:2]),
             c2ws_val=src["c2ws_val"][:2], c2ws_test=src["c2ws_test"][::20], focal=np.float64(src["focal"]) * TINY_LEGO_SIZE / 200)
    return out


@pytest.fixture(scope="session")
def tiny_lego(tiny_lego_npz):
    """:func:`tiny_lego_npz`, loaded."""
    from nerfpipe.data_adapters import load

    return load(tiny_lego_npz)


# Tolerances by dtype, not magic numbers per test (kornia's _DTYPE_PRECISIONS idea).
TOLERANCES = {
    torch.float16: dict(rtol=1e-2, atol=1e-2),
    torch.bfloat16: dict(rtol=2e-2, atol=2e-2),
    torch.float32: dict(rtol=1e-4, atol=1e-5),
    torch.float64: dict(rtol=1e-9, atol=1e-10),
}


@pytest.fixture
def tol():
    return lambda dtype: TOLERANCES[dtype]


CUDA = torch.cuda.is_available() and torch.cuda.device_count() > 0


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=pytest.mark.requires_cuda)])
def device(request) -> torch.device:
    """Every device the numerical tests run on: the CPU, and CUDA where there is one (skipped elsewhere)."""
    return torch.device(request.param)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``requires_cuda`` (the one GPU marker) are skipped on machines without CUDA."""
    if CUDA:
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (none on this machine)")
    for item in items:
        if "requires_cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(params=[torch.float32, torch.float64])
def dtype(request) -> torch.dtype:
    return request.param


def pytest_configure(config):
    # Under pytest-xdist every worker gets one thread (2 workers on 2 cores); alone, use 2.
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))
