"""``nerfpipe bench``: the table and plot writers, and a two-budget run of one tiny preset."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nerfpipe.training.bench import BenchConfig, write_table


def row(preset, budget, psnr, mb):
    return {"preset": preset, "budget_s": budget, "clock": "wall", "clock_s": budget * 1.01, "train_s": budget * 1.01,
            "train_cpu_s": budget * 2, "iterations": int(budget * 3), "val_psnr": psnr, "val_ssim": 0.5,
            "model_params": 1000, "model_mb": mb, "occupied_fraction": None if preset == "vanilla" else 0.1,
            "samples_per_ray": 12.0, "eval_s": 1.0, "loadavg": 0.5}


def test_write_table_outputs(tmp_path):
    rows = [row("vanilla", 20, 12.0, 2.0), row("vanilla", 60, 14.0, 2.0), row("fast-small", 20, 22.0, 45.0), row("fast-small", 60, 26.5, 45.0)]
    write_table(rows, tmp_path, "lego", BenchConfig(budgets=(20.0, 60.0)))
    table = json.loads((tmp_path / "table.json").read_text())
    assert [r["val_psnr"] for r in table["rows"]] == [12.0, 14.0, 22.0, 26.5]
    md = (tmp_path / "table.md").read_text().splitlines()
    assert len([line for line in md if line.startswith("| fast-small")]) == 2
    assert "26.50" in md[-1]
    header = [c.strip() for c in md[2].split("|")]
    assert {"kernel launches/step", "GPU busy", "peak GPU MB"} <= set(header)
    assert [c.strip() for c in md[-1].split("|")][header.index("GPU busy")] == "-"  # a CPU row: no GPU figures
    gpu = dict(rows[-1], kernel_launches_per_step=412.0, gpu_busy_share=0.334, peak_gpu_mb=973.4)
    write_table([gpu], tmp_path, "lego", BenchConfig(budgets=(20.0, 60.0)))
    cells = [c.strip() for c in (tmp_path / "table.md").read_text().splitlines()[-1].split("|")]
    assert [cells[header.index(k)] for k in ("kernel launches/step", "GPU busy", "peak GPU MB")] == ["412", "33%", "973"]
    assert (tmp_path / "psnr_vs_seconds.png").read_bytes()[:4] == b"\x89PNG"


def tiny_lego(scene_path, tmp_path):
    """Every 20th lego training view and one val view at 16x16."""
    src = np.load(scene_path("lego_200x200") / "lego_200x200.npz")
    shrink = lambda im: F.interpolate(torch.from_numpy(im).permute(0, 3, 1, 2).float(), size=(16, 16), mode="area").round().byte().permute(0, 2, 3, 1).numpy()  # noqa: E731
    npz = tmp_path / "tiny.npz"
    np.savez(npz, images_train=shrink(src["images_train"][::20]), c2ws_train=src["c2ws_train"][::20],
             images_val=shrink(src["images_val"][:1]), c2ws_val=src["c2ws_val"][:1], c2ws_test=src["c2ws_test"][:1],
             focal=np.float64(src["focal"]) * 16 / 200)
    return npz


def test_bench_run_scores_each_budget(scene_path, tmp_path, device):
    """On CUDA each row also carries the GPU's figures (peak memory, busy share, kernel launches per step)."""
    from nerfpipe.training.bench import run

    npz = tiny_lego(scene_path, tmp_path)
    rows = run(npz, tmp_path / "out", BenchConfig(budgets=(0.2, 0.5), presets=("fast-small",), rays_per_step=64, threads=torch.get_num_threads(),
                                                  device=str(device)))
    if torch.device(device).type == "cuda":
        assert all(r["peak_gpu_mb"] > 0 and 0 < r["gpu_busy_share"] <= 1 and r["kernel_launches_per_step"] >= 1 for r in rows)
    assert [r["budget_s"] for r in rows] == [0.2, 0.5]
    assert rows[0]["clock_s"] >= 0.2 and rows[1]["clock_s"] >= 0.5 and rows[1]["iterations"] >= rows[0]["iterations"] >= 1
    assert (tmp_path / "out" / "table.md").is_file()
    assert all(r["aten_ops_per_step"] > 0 and r["host_syncs_per_step"] >= 0 for r in rows)  # counted after each budget
    assert "syncs/step" in (tmp_path / "out" / "table.md").read_text()


def test_preset_overrides_reach_the_model_config():
    import pytest

    from nerfpipe.training.bench import resolve_preset
    from nerfpipe.util.errors import NerfpipeError

    name, cfg, over = resolve_preset("fast-small:distortion_weight=0.001,tv_weight=1e-5,tighten_step=128")
    assert name == "fast" and cfg.preset == "small" and over["rays_per_step"] is None  # by the device
    assert (cfg.distortion_weight, cfg.tv_weight, cfg.tighten_step) == (0.001, 1e-5, 128)
    assert resolve_preset("fast")[1].preset == "auto"
    with pytest.raises(NerfpipeError, match="no option 'nope'"):
        resolve_preset("fast-small:nope=1")
    with pytest.raises(NerfpipeError, match="unknown bench preset"):
        resolve_preset("fast-tiny")


def test_steps_ab_tool_parses_options_and_validates_at_each_mark(scene_path, tmp_path):
    import pytest

    from benchmarks.steps import StepsConfig, main, model_config
    from nerfpipe.util.errors import NerfpipeError

    cfg = model_config("small", ("step_ratio=1.0", "occupancy.update_every=32", "levels=(8, 16)"))
    assert (cfg.step_ratio, cfg.occupancy.update_every, cfg.levels, cfg.preset) == (1.0, 32, (8, 16), "small")
    assert model_config("auto", ("behind.levels=(4,)", "behind.grid_lr=0.5")).behind.levels == (4,)  # any nested config
    with pytest.raises(NerfpipeError, match="nonexistent"):
        model_config("auto", ("behind.nonexistent=1",))
    log = tmp_path / "steps.jsonl"
    rows = main(StepsConfig(tiny_lego(scene_path, tmp_path), options=("levels=(8, 16)",), marks=(2, 4), eval_views=1,
                            rays_per_step=64, threads=torch.get_num_threads(), log=log))
    assert [r["step"] for r in rows] == [2, 4] and rows[1]["wall"] >= rows[0]["wall"] > 0
    assert all(r["psnr"] > 5 and r["samples_per_ray"] > 0 for r in rows)
    assert [json.loads(line)["psnr"] for line in log.read_text().splitlines()] == [r["psnr"] for r in rows]


def test_side_by_side_interleaves_variants_and_reports_size(scene_path, tmp_path):
    from benchmarks.side_by_side import SideBySideConfig, main, parse_variant

    assert parse_variant("dense:preset='small' levels=(8,16)") == ("dense", "small", ("levels=(8,16)",), {})
    assert parse_variant("compact:") == ("compact", "auto", (), {})
    assert parse_variant("s:train.train_max_size=480 tv_weight=0.1") == ("s", "auto", ("tv_weight=0.1",), {"train_max_size": 480})
    rows = main(SideBySideConfig(tiny_lego(scene_path, tmp_path), variants=("dense:preset='small' levels=(8,16)", "compact:preset='compact' log2_hashmap_size=9"),
                                 marks=(3,), chunk=2, eval_views=1, rays_per_step=64, threads=torch.get_num_threads(),
                                 eval_max_size=24, pictures=tmp_path / "orbits.png"))
    assert [r["name"] for r in rows] == ["dense", "compact"] and all(r["step"] == 3 and r["s_per_step"] > 0 for r in rows)
    assert rows[1]["model_mb"] < rows[0]["model_mb"]  # hashed into 512-row tables
    import imageio.v3 as iio

    picture = iio.imread(tmp_path / "orbits.png")  # colour and depth rows of four orbit views per variant
    h = picture.shape[0] // 4  # the tiny scene's square views
    assert picture.shape[0] == 4 * h and picture.shape[1] == 4 * h and h <= 24
    colour, depth = picture[:h], picture[h : 2 * h]
    assert not np.array_equal(colour, depth)


def test_step_profile_times_each_mode_and_batch(scene_path, tmp_path, device):
    """The step profiler trains a fresh model per marching mode and batch and times its steady steps; on CUDA the
    profiler's figures come with each row (GPU busy no more than the wall time, at least one kernel per step)."""
    from benchmarks.step_profile import StepProfileConfig, main

    log = tmp_path / "profile.jsonl"
    rows = main(StepProfileConfig(tiny_lego(scene_path, tmp_path), options=("levels=(8, 16)",), rays=(32, 64), modes=("fixed", "rounds"),
                                  warm=3, steps=2, profiled_steps=2, device=str(device), threads=torch.get_num_threads(), log=log))
    assert [(r["mode"], r["rays"]) for r in rows] == [("fixed", 32), ("fixed", 64), ("rounds", 32), ("rounds", 64)]
    assert all(r["ms_per_step"] > 0 and r["samples_per_ray"] > 0 for r in rows)
    assert len(log.read_text().splitlines()) == 4
    if torch.device(device).type == "cuda":
        assert all(0 < r["gpu_busy_ms_per_step"] <= r["profiled_ms_per_step"] and r["kernel_launches_per_step"] >= 1 for r in rows)
    else:
        assert not any("gpu_busy_ms_per_step" in r for r in rows)


def test_ray_regions_match_points_sampled_along_the_rays():
    """A ray is in ``box`` where a point sampled along it (in front of its origin) lies in the box, else in ``plane``
    where it crosses the plane downwards from above it; every ray is in exactly one region."""
    from benchmarks.held_out_regions import REGIONS, ray_regions

    g = torch.Generator().manual_seed(0)
    origins = torch.randn(600, 3, generator=g) * 3.0
    directions = torch.nn.functional.normalize(torch.randn(600, 3, generator=g), dim=-1)
    box, plane = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), torch.tensor([0.0, 0.0, 1.0, 1.5])  # z = -1.5
    masks = ray_regions(origins, directions, box, plane)
    assert torch.equal(sum(masks[k].long() for k in REGIONS), torch.ones(600, dtype=torch.long))
    t = torch.cat([torch.linspace(0.0, 20.0, 4001), torch.logspace(1.31, 6.0, 400)])  # far enough for shallow rays to cross the plane
    pts = origins[:, None] + t[None, :, None] * directions[:, None]
    in_box = ((pts >= -1.0) & (pts <= 1.0)).all(-1).any(-1)
    crosses = (origins[:, 2] > -1.5) & (pts[..., 2] < -1.5).any(-1)
    assert torch.equal(masks["box"], in_box)
    assert torch.equal(masks["plane"], crosses & ~in_box)
    assert 0 < int(masks["box"].sum()) < 600 and 0 < int(masks["plane"].sum()) < 600 and int(masks["rest"].sum()) > 0


def test_held_out_regions_split_a_runs_error_and_bound_it_by_an_affine_oracle(tiny_lego_npz, tmp_path):
    from benchmarks.held_out_regions import REGIONS, RegionsConfig, main, oracle_affine_mse
    from nerfpipe.pipeline.stages import Pipeline

    train = {"model": "fast", "model_options": {"preset": "small", "levels": [8, 16]},
             "trainer": {"iters": 20, "rays_per_step": 256, "eval_every": 0, "final_eval_views": 1, "video_frames": 0}}  # fmt: skip
    Pipeline(["load", "train"], {"train": train}).run(tiny_lego_npz, tmp_path)
    out = main(RegionsConfig(tmp_path, max_size=None, pictures=tmp_path / "pictures", threads=torch.get_num_threads()))
    s = out["summary"]
    assert s["views"] == len(out["views"]) == 2 and len(list((tmp_path / "pictures").glob("view_*.png"))) == 2
    assert sum(s[f"{k}_pixel_share"] for k in REGIONS) == pytest.approx(1.0)
    assert sum(s[f"{k}_error_share"] for k in REGIONS) == pytest.approx(1.0)
    assert s["plane_pixel_share"] == 0.0  # a synthetic object: no support plane
    assert all(v["psnr_oracle_affine"] >= v["psnr"] - 1e-6 for v in out["views"]) and 5.0 < s["psnr"] < 40.0
    pred = torch.rand(500, 3, generator=torch.Generator().manual_seed(1))
    assert oracle_affine_mse(pred, 0.5 * pred + 0.2) < 1e-12  # an exposure change is explained away
    assert oracle_affine_mse(pred, pred.flip(0)) > 0.05  # a different picture is not
