"""Shared fixtures: the real-data folder, devices, dtypes and tolerances (STYLE habit 11)."""

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # pytest -n 2 shares the cores: no spinning waits (nerfpipe/runtime.py)
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


@pytest.fixture(params=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64])
def dtype(request) -> torch.dtype:
    return request.param


def pytest_configure(config):
    # Under pytest-xdist every worker gets one thread (2 workers on 2 cores); alone, use 2.
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))
