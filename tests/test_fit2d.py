"""nerfpipe fit2d: exact positional encoding, grid encoder vs references, training, outputs, bad input."""

import json
import math
from fractions import Fraction

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nerfpipe.cli import main
from nerfpipe.encoders import GridEncoderConfig, PositionalEncoderConfig
from nerfpipe.functional.encoding import nyquist_frequencies, positional_encoding, positional_encoding_dim
from nerfpipe.image_field import fit_image, pixel_grid
from nerfpipe.image_field.fit2d_run import configure


def _reference_pe(x: np.ndarray, num_frequencies: int) -> np.ndarray:
    """Exact rational phase reduction with fractions, then float64 sin/cos; course ordering."""
    out = [x]
    for k in range(num_frequencies):
        red = np.vectorize(lambda v: float((Fraction(float(v)) * 2**k) % 2))(x)
        out += [np.sin(math.pi * red), np.cos(math.pi * red)]
    return np.concatenate(out, axis=-1)


def _photo(h: int = 32, w: int = 40) -> np.ndarray:
    from PIL import Image
    from skimage import data

    return np.array(Image.fromarray(data.astronaut()).resize((w, h), Image.Resampling.BOX))


# --- positional encoding -------------------------------------------------------------------------


def test_positional_encoding_golden_values_and_ordering():
    x = torch.tensor([[0.25, 0.5]], dtype=torch.float64)
    s, c = math.sin, math.cos
    p = math.pi
    expected = [0.25, 0.5, s(p / 4), s(p / 2), c(p / 4), c(p / 2), s(p / 2), s(p), c(p / 2), c(p)]
    torch.testing.assert_close(positional_encoding(x, 2), torch.tensor([expected], dtype=torch.float64))
    torch.testing.assert_close(positional_encoding(x, 2, include_input=False), torch.tensor([expected[2:]]).double())


@pytest.mark.parametrize("batch", [(), (1,), (2, 3)])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_positional_encoding_shapes(batch, dim, dtype):
    x = torch.rand(*batch, dim, dtype=dtype)
    out = positional_encoding(x, 4)
    assert out.shape == (*batch, positional_encoding_dim(dim, 4)) == (*batch, dim * 9)
    assert out.dtype == dtype
    torch.testing.assert_close(out[..., :dim], x)


@pytest.mark.parametrize("num_frequencies", [10, 35, 40])
def test_positional_encoding_exact_at_high_frequencies(num_frequencies, dtype, tol):
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(64, 3, generator=gen, dtype=torch.float64).to(dtype) * 2 - 1
    out = positional_encoding(x, num_frequencies)
    assert torch.isfinite(out).all()
    ref = torch.from_numpy(_reference_pe(x.double().numpy(), num_frequencies)).to(dtype)
    torch.testing.assert_close(out, ref, **tol(dtype))


def test_naive_float32_phases_are_noise_at_high_frequencies():
    """The failure the exact reduction avoids: float32 sin(2^k·π·x) is far off for large k."""
    x = torch.rand(256, 2, generator=torch.Generator().manual_seed(1))
    k = 34
    naive = torch.sin((2.0**k) * math.pi * x)
    exact = positional_encoding(x, k + 1)[..., -4:-2]  # sin of the last frequency
    assert (naive - exact).abs().max() > 0.5


def test_positional_encoding_gradcheck():
    x = torch.rand(5, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: positional_encoding(v, 6), (x,))


def test_nyquist_frequencies():
    assert nyquist_frequencies(512) == 10 and nyquist_frequencies(511) == 9 and nyquist_frequencies(2) == 2


# --- grid encoder --------------------------------------------------------------------------------


def _grid(dim: int, **kw):
    cfg = GridEncoderConfig(num_levels=3, base_resolution=3, max_resolution=24, init_scale=1.0, **kw)
    torch.manual_seed(0)
    return cfg.setup(dim).double()


@pytest.mark.parametrize("dim", [2, 3])
def test_dense_grid_matches_grid_sample(dim):
    enc = _grid(dim, log2_hashmap_size=20)
    assert not enc.hashed.any()
    x = torch.rand(50, dim, dtype=torch.float64)
    out = enc(x).reshape(50, 3, -1)
    for lvl in range(3):
        res, off, n = int(enc.resolution[lvl]), int(enc.offset[lvl]), int(enc.size[lvl])
        vol = enc.table[off : off + n].reshape(*([res + 1] * dim), -1)  # [z][y]x, x fastest
        vol = vol.permute(dim, *range(dim))[None]  # [1, F, (z,) y, x]
        grid = (2 * x - 1).reshape(1, *([1] * (dim - 1)), 50, dim)
        ref = F.grid_sample(vol, grid, mode="bilinear", align_corners=True).reshape(-1, 50).T
        torch.testing.assert_close(out[:, lvl], ref)


@pytest.mark.parametrize("dim", [2, 3])
def test_hashed_grid_matches_reference_and_cached_corners(dim):
    enc = _grid(dim, log2_hashmap_size=6)
    assert enc.hashed.any() and not enc.hashed.all()
    x = torch.rand(40, dim, dtype=torch.float64)
    torch.testing.assert_close(enc(x), enc._reference_forward(x))
    idx, w = enc.corners(x)
    torch.testing.assert_close(enc.interpolate(idx, w), enc(x))
    assert enc(x.reshape(4, 10, dim)).shape == (4, 10, enc.out_dim)


@pytest.mark.parametrize("dim", [2, 3])
def test_grid_encoder_gradients_match_reference(dim):
    enc = _grid(dim, log2_hashmap_size=6)
    x = torch.rand(12, dim, dtype=torch.float64, requires_grad=True)

    table = enc.table.detach().clone().requires_grad_(True)
    fast = lambda t, xx: _with_table(enc, t, xx, reference=False)  # noqa: E731
    slow = lambda t, xx: _with_table(enc, t, xx, reference=True)  # noqa: E731
    assert torch.autograd.gradcheck(fast, (table, x), fast_mode=True)
    weights = torch.randn(12, enc.out_dim, dtype=torch.float64)
    g_fast = torch.autograd.grad((fast(table, x) * weights).sum(), (table, x))
    g_slow = torch.autograd.grad((slow(table, x) * weights).sum(), (table, x))
    for a, b in zip(g_fast, g_slow):
        torch.testing.assert_close(a, b)


def _with_table(enc, table, x, reference):
    """Evaluate the encoder with ``table`` as a differentiable input instead of its parameter."""
    saved = enc.table
    try:
        del enc.table
        enc.table = table
        return enc._reference_forward(x) if reference else enc(x)
    finally:
        del enc.table
        enc.table = saved


# --- training and the command --------------------------------------------------------------------


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny fits run faster on one thread (no OpenMP hand-offs on a busy machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("preset", ["course", "fast"])
def test_training_raises_psnr(preset):
    img = torch.from_numpy(_photo())
    cfg = configure(preset, {"iterations": 60, "num_evals": 3}, tuple(img.shape))
    if preset == "course":
        cfg.field.hidden_width, cfg.train.batch_size = 64, 512
    result = fit_image(img, cfg.field, cfg.train)
    assert result.iterations == 60 and math.isfinite(result.psnr)
    assert result.psnr > result.curve_psnr[0] + 6.0
    assert set(result.snapshots) <= set(result.curve_iterations) and 60 in result.snapshots


def test_pixel_grid_is_row_major_pixel_centres():
    g = pixel_grid(2, 4)
    torch.testing.assert_close(g[1], torch.tensor([0.375, 0.25]))
    torch.testing.assert_close(g[4], torch.tensor([0.125, 0.75]))


def test_fast_preset_has_fewer_parameters_than_image_values():
    for h, w in [(512, 512), (64, 48)]:
        cfg = configure("fast", {}, (h, w, 3))
        assert cfg.field.setup().num_parameters() < h * w * 3


def test_course_preset_is_the_course_recipe():
    cfg = configure("course", {}, (512, 512, 3))
    assert isinstance(cfg.field.encoder, PositionalEncoderConfig) and cfg.field.encoder.num_frequencies == 10
    assert (cfg.field.hidden_width, cfg.field.num_layers, cfg.train.lr, cfg.train.batch_size) == (256, 4, 1e-2, 10_000)
    model = cfg.field.setup()
    assert sum(isinstance(m, torch.nn.Linear) for m in model.modules()) == 4


def _write(path, img):
    import imageio.v3 as iio

    iio.imwrite(path, img)
    return str(path)


def test_cli_writes_outputs(tmp_path):
    img = _write(tmp_path / "in.png", _photo(24, 20))
    out = tmp_path / "out"
    assert main(["fit2d", img, "--out", str(out), "--preset", "fast", "--iterations", "6", "--num-evals", "2",
                 "--threads", "1"]) == 0
    for name in ("psnr.png", "progress.png", "final.png", "metrics.json"):
        assert (out / name).stat().st_size > 0
    m = json.loads((out / "metrics.json").read_text())
    assert {"psnr", "seconds", "iterations", "params"} <= set(m) and m["iterations"] == 6
    assert m["params"] < m["image_values"] == 24 * 20 * 3


def test_cli_sweep(tmp_path):
    img = _write(tmp_path / "in.png", _photo(12, 16))
    out = tmp_path / "sweep"
    args = ["fit2d", img, "--out", str(out), "--sweep", "--sweep-l", "2", "40", "--sweep-lr", "1e-2",
            "--iterations", "3", "--hidden-width", "16", "--batch-size", "64", "--threads", "1"]
    assert main(args) == 0
    rows = json.loads((out / "sweep.json").read_text())["rows"]
    assert [(r["L"], r["lr"]) for r in rows] == [(2, 1e-2), (40, 1e-2)]
    assert all(math.isfinite(r["psnr"]) for r in rows)
    assert (out / "sweep_psnr.png").stat().st_size > 0 and "| 40 |" in (out / "sweep.md").read_text()


def test_cli_rejects_flags_of_the_other_encoder(tmp_path, capsys):
    img = _write(tmp_path / "in.png", _photo(8, 8))
    assert main(["fit2d", img, "--out", str(tmp_path / "o"), "--grid-levels", "4", "--threads", "1"]) == 2
    assert "does not apply" in capsys.readouterr().err


def test_default_image_ships_with_scikit_image():
    from nerfpipe.image_field.images import load_target

    target = load_target(None)
    assert target.pixels.dtype == np.uint8 and target.pixels.shape[-1] == 3 and min(target.pixels.shape[:2]) >= 256
    assert target.source.startswith("skimage:") and target.pixels.flags.writeable


def test_public_names_resolve():
    import nerfpipe.encoders
    import nerfpipe.image_field

    for module in (nerfpipe.encoders, nerfpipe.image_field):
        assert all(hasattr(module, name) for name in module.__all__)


def _bad_inputs(tmp_path):
    (tmp_path / "notes.png").write_text("not an image")
    return {
        "non-image": str(tmp_path / "notes.png"),
        "missing": str(tmp_path / "nope.jpg"),
        "1x1": _write(tmp_path / "one.png", np.zeros((1, 1, 3), np.uint8)),
    }


@pytest.mark.parametrize("case", ["non-image", "missing", "1x1"])
def test_cli_bad_input_is_one_line(tmp_path, capsys, case):
    path = _bad_inputs(tmp_path)[case]
    assert main(["fit2d", path, "--out", str(tmp_path / "o"), "--iterations", "1", "--threads", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("nerfpipe: error:") and "\n" not in err and "Traceback" not in err


@pytest.mark.parametrize("case", ["rgba", "grey", "uint16", "large"])
def test_cli_handles_unusual_images(tmp_path, case):
    rgb = _photo(16, 20)
    img = {
        "rgba": np.concatenate([rgb, np.full((16, 20, 1), 128, np.uint8)], axis=-1),
        "grey": rgb[..., 0],
        "uint16": rgb[..., 1].astype(np.uint16) * 257,  # 16-bit grey PNG (Pillow writes no RGB48)
        "large": _photo(64, 80),
    }[case]
    path = _write(tmp_path / f"{case}.png", img)
    out = tmp_path / "o"
    args = ["fit2d", path, "--out", str(out), "--preset", "fast", "--iterations", "2", "--max-pixels", "400", "--threads", "1"]
    assert main(args) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["image"]["height"] * m["image"]["width"] <= 400
    assert bool(m["image"]["notes"]) == (case in ("rgba", "large"))
