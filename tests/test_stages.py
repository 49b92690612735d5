"""Stages and pipelines: discovery, chaining, TOML, resume after failures and kills, the built-in
stages on real data (load, check, export read back), and the example third-party stage."""

import importlib.metadata
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfpipe.cli import main
from nerfpipe.pipeline.stages import Pipeline, StageContext, StageSpec, atomic_path, config_hash, marker_path, stages
from nerfpipe.training.checkpoint import load_checkpoint
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.registry import PluginWarning, STAGE_GROUP

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "plugins" / "example_pointcloud"
BUILTIN = {"sfm", "load", "check", "export", "train", "render", "mesh", "report"}


# ---------------------------------------------------------------- toy stages


@dataclass
class ToyConfig:
    value: int = 1
    """Written into the artifact."""
    fail: bool = False
    """Raise half-way, after part of the artifact is written."""


def toy_stage(name: str, requires=(), calls: "list | None" = None) -> StageSpec:
    def run(config: ToyConfig, ctx: StageContext) -> dict:
        if calls is not None:
            calls.append(name)
        upstream = [int(ctx.path(f"{r}.txt").read_text()) for r in requires]
        with atomic_path(ctx.path(f"{name}.txt")) as tmp:
            tmp.write_text("partial")
            if config.fail:
                raise RuntimeError(f"{name} failed half-way")
            tmp.write_text(str(config.value + sum(upstream)))
        return {name: config.value + sum(upstream)}

    return StageSpec(name, f"toy {name}", ToyConfig, run, tuple(f"{r}.txt" for r in requires), (f"{name}.txt",), (name,))


def toy_registry(calls: "list | None" = None) -> "dict[str, StageSpec]":
    return {"a": toy_stage("a", calls=calls), "b": toy_stage("b", ("a",), calls), "c": toy_stage("c", ("b",), calls)}


def leftovers(run_dir: Path) -> "list[str]":
    return [p.name for p in run_dir.rglob(".tmp-*")]


# ---------------------------------------------------------------- discovery


def test_builtin_stages_register_through_entry_points():
    names = {ep.name for ep in importlib.metadata.entry_points(group=STAGE_GROUP)}
    assert BUILTIN <= names
    found = stages()
    assert BUILTIN <= set(found)
    for name in BUILTIN:
        assert found[name].name == name and found[name].config().__class__ is found[name].config


@pytest.fixture
def plugin_entry_points(monkeypatch):
    """The built-in stages, the example package (from its source folder), a broken and a mistyped plugin."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    real = [ep for ep in importlib.metadata.entry_points(group=STAGE_GROUP) if ep.name in BUILTIN]
    fake = [
        importlib.metadata.EntryPoint("pointcloud", "nerfpipe_example_pointcloud:STAGE", STAGE_GROUP),
        importlib.metadata.EntryPoint("broken", "nerfpipe_no_such_plugin:STAGE", STAGE_GROUP),
        importlib.metadata.EntryPoint("mistyped", "nerfpipe.pipeline.stages:DEFAULT_CHAIN", STAGE_GROUP),
    ]
    original = importlib.metadata.entry_points

    def entry_points(group=None):
        return real + fake if group == STAGE_GROUP else original(group=group)

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)


def test_broken_plugins_are_warned_and_skipped(plugin_entry_points):
    with pytest.warns(PluginWarning) as record:
        found = stages()
    assert set(found) == BUILTIN | {"pointcloud"}
    text = " ".join(str(w.message) for w in record)
    assert "'broken'" in text and "failed to load" in text and "'mistyped'" in text


def test_cli_lists_stages_and_names_broken_plugin(plugin_entry_points, capsys):
    assert main(["stages"]) == 0
    out = capsys.readouterr().out
    assert "warning:" in out and "'broken'" in out and "'mistyped'" in out
    for name in BUILTIN | {"pointcloud"}:
        assert name in out


# ---------------------------------------------------------------- chaining, resume, TOML


def test_chain_runs_in_order_and_resumes(tmp_path):
    calls = []
    pipe = Pipeline(["a", "b", "c"], {"a": {"value": 2}}, registry=toy_registry(calls))
    result = pipe.run(None, tmp_path)
    assert calls == ["a", "b", "c"]
    assert (result["a"], result["b"], result["c"]) == (2, 3, 4)  # each adds its upstream's value
    assert [r.status for r in result.records] == ["ran"] * 3
    done = json.loads(marker_path(result.context, "a").read_text())
    assert done["config_hash"] == config_hash(ToyConfig(value=2)) and done["config"] == {"value": 2, "fail": False}

    calls.clear()
    again = pipe.run(None, tmp_path)
    assert calls == [] and [r.status for r in again.records] == ["skipped"] * 3
    assert again["c.txt"] == tmp_path / "c.txt"

    calls.clear()  # a changed option re-runs that stage and everything after it
    Pipeline(["a", "b", "c"], {"a": {"value": 2}, "b": {"value": 5}}, registry=toy_registry(calls)).run(None, tmp_path)
    assert calls == ["b", "c"] and (tmp_path / "c.txt").read_text() == "8"


def test_each_stage_sees_whether_only_light_stages_follow(tmp_path):
    """The render stage spends most of the time left only where nothing but light stages (export, report) follows."""
    seen = {}

    def probe(name: str, light: bool = False) -> StageSpec:
        def run(config: ToyConfig, ctx: StageContext) -> dict:
            seen[name] = ctx.rest_is_light()
            return {}

        return StageSpec(name, f"probe {name}", ToyConfig, run, light=light)

    registry = {"a": probe("a"), "b": probe("b"), "w": probe("w", light=True), "z": probe("z", light=True)}
    Pipeline(["a", "b", "w", "z"], registry=registry).run(None, tmp_path / "1")
    assert seen == {"a": False, "b": True, "w": True, "z": True}
    Pipeline(["b", "w", "a"], registry=registry).run(None, tmp_path / "2")
    assert seen["b"] is False and seen["w"] is False and seen["a"] is True
    assert stages()["export"].light and stages()["report"].light and not stages()["mesh"].light


def test_each_stage_plans_on_the_time_left_less_what_the_later_stages_need(tmp_path):
    """Under a budget a stage plans on the time left less the ``min_seconds`` of the stages after it (the orbit's few
    seconds, which the mesh stage used to take), keeping at least half; without a budget there is nothing to plan on."""
    seen = {}

    def probe(name: str, min_seconds: float = 0.0) -> StageSpec:
        def run(config: ToyConfig, ctx: StageContext) -> dict:
            seen[name] = (ctx.time_left(), ctx.time_for_stage())
            return {}

        return StageSpec(name, f"probe {name}", ToyConfig, run, min_seconds=min_seconds)

    registry = {"a": probe("a"), "b": probe("b", 3.0), "c": probe("c", 2.0)}
    Pipeline(["a", "b", "c"], registry=registry).run(None, tmp_path / "1", time_budget=100.0)
    for name, floors in (("a", 5.0), ("b", 2.0), ("c", 0.0)):
        left, planned = seen[name]
        assert 99.0 < left <= 100.0 and planned == pytest.approx(left - floors, abs=1e-3), (name, seen[name])
    Pipeline(["a", "b", "c"], registry=registry).run(None, tmp_path / "2", time_budget=6.0)
    left, planned = seen["a"]
    assert planned == pytest.approx(0.5 * left, abs=1e-3)  # 5 s of floors, but half of 6 s stays the stage's
    Pipeline(["a", "b", "c"], registry=registry).run(None, tmp_path / "3")
    assert seen["a"] == (None, None)
    assert stages()["render"].min_seconds > 0 and stages()["mesh"].min_seconds == 0


def test_failed_stage_leaves_no_marker_and_no_artifact(tmp_path):
    calls = []
    with pytest.raises(RuntimeError, match="b failed half-way"):
        Pipeline(["a", "b", "c"], {"b": {"fail": True}}, registry=toy_registry(calls)).run(None, tmp_path)
    assert calls == ["a", "b"]
    assert (tmp_path / "a.txt").is_file() and marker_path(StageContext(tmp_path), "a").is_file()
    assert not (tmp_path / "b.txt").exists() and not marker_path(StageContext(tmp_path), "b").exists()
    assert leftovers(tmp_path) == []

    calls.clear()
    result = Pipeline(["a", "b", "c"], registry=toy_registry(calls)).run(None, tmp_path)
    assert calls == ["b", "c"] and [r.status for r in result.records] == ["skipped", "ran", "ran"]


KILLED_RUN = """
import sys, time
from pathlib import Path
sys.path.insert(0, {tests!r})
from test_stages import toy_registry, toy_stage
from nerfpipe.pipeline.stages import Pipeline, atomic_path

def slow(config, ctx):
    with atomic_path(ctx.path("b.txt")) as tmp:
        tmp.write_text("partial")
        ctx.path("b.started").write_text("")
        time.sleep(60)
    return {{}}

reg = toy_registry()
reg["b"] = reg["b"].__class__("b", "slow", reg["b"].config, slow, ("a.txt",), ("b.txt",))
Pipeline(["a", "b", "c"], registry=reg).run(None, {run_dir!r})
"""


def test_killed_run_resumes_from_last_finished_stage(tmp_path):
    script = KILLED_RUN.format(tests=str(Path(__file__).parent), run_dir=str(tmp_path))
    proc = subprocess.Popen([sys.executable, "-c", script], env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))})
    deadline = time.monotonic() + 120
    while not (tmp_path / "b.started").exists():
        assert proc.poll() is None and time.monotonic() < deadline, "the child died before stage b started"
        time.sleep(0.1)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    ctx = StageContext(tmp_path)
    assert marker_path(ctx, "a").is_file() and not marker_path(ctx, "b").exists()
    assert not (tmp_path / "b.txt").exists() and len(leftovers(tmp_path)) == 1  # the temp of b, never in place

    calls = []
    result = Pipeline(["a", "b", "c"], registry=toy_registry(calls)).run(None, tmp_path)
    assert calls == ["b", "c"] and result["c"] == 3
    assert leftovers(tmp_path) == []  # stale temporaries are swept on the next run


def test_a_folder_nerfpipe_did_not_make_keeps_its_tmp_files(tmp_path):
    (tmp_path / ".tmp-notes.txt").write_text("the user's")
    Pipeline(["a", "b", "c"], registry=toy_registry()).run(None, tmp_path)
    assert (tmp_path / ".tmp-notes.txt").read_text() == "the user's"


def test_not_needed_stage_is_recorded_and_skipped(tmp_path):
    calls = []
    reg = toy_registry(calls)
    reg["a"] = StageSpec("a", "never needed", ToyConfig, reg["a"].run, produces=("a.txt",), applies=lambda ctx: False)
    reg["b"] = toy_stage("b", calls=calls)
    first = Pipeline(["a", "b"], registry=reg).run(None, tmp_path)
    assert [r.status for r in first.records] == ["not needed", "ran"] and calls == ["b"]
    again = Pipeline(["a", "b"], registry=reg).run(None, tmp_path)
    assert [r.status for r in again.records] == ["not needed", "skipped"] and calls == ["b"]


def test_chain_is_validated_before_anything_runs(tmp_path):
    calls = []
    with pytest.raises(NerfpipeError, match="stage 'c' needs 'b.txt'.*produced by: b"):
        Pipeline(["a", "c"], registry=toy_registry(calls)).run(None, tmp_path)
    assert calls == [] and not (tmp_path / "stages").exists()
    with pytest.raises(NerfpipeError, match="unknown stage 'nope'"):
        Pipeline(["a", "nope"], registry=toy_registry())


def test_pipeline_from_toml(tmp_path):
    toml = tmp_path / "pipe.toml"
    toml.write_text('stages = ["a", "b"]\n[a]\nvalue = 7\n[b]\nvalue = 1\n')
    pipe = Pipeline.from_toml(toml, registry=toy_registry())
    assert pipe.names == ["a", "b"] and pipe.configs["a"] == ToyConfig(value=7)
    assert pipe.run(None, tmp_path / "run")["b"] == 8
    bad = {
        'stages = ["a"]\n[a]\nvalu = 7\n': "stage 'a' has no option 'valu'",
        'stages = ["a"]\n[b]\nvalue = 7\n': "options for stage 'b', which is not in 'stages'",
        "[a]\nvalue = 7\n": "needs 'stages",
        'stages = ["a"\n': "cannot read pipeline file",
    }
    for text, message in bad.items():
        toml.write_text(text)
        with pytest.raises(NerfpipeError, match=message):
            Pipeline.from_toml(toml, registry=toy_registry())


def test_pipeline_file_values_the_command_line_overrides_are_not_read(tmp_path):
    from nerfpipe.commands.run import given_stage_options

    toml = tmp_path / "pipe.toml"
    toml.write_text('stages = ["a", "b"]\n[a]\nvalue = "seven"\n[b]\nvalue = 3\n')
    with pytest.raises(NerfpipeError, match="value"):
        Pipeline.from_toml(toml, registry=toy_registry())
    given = given_stage_options(["DATA", "--a.value", "5", "--b.other-thing=2", "--out", "x", "--pipeline", str(toml)])
    assert given == ("a.value", "b.other_thing")
    pipe = Pipeline.from_toml(toml, registry=toy_registry(), overridden=given)
    assert pipe.configs["a"] == ToyConfig() and pipe.configs["b"] == ToyConfig(value=3)  # the file's other values stay


def test_run_folder_of_another_input_is_refused(tmp_path):
    Pipeline(["a"], registry=toy_registry()).run(tmp_path / "x", tmp_path / "run")
    with pytest.raises(NerfpipeError, match="made from"):
        Pipeline(["a"], registry=toy_registry()).run(tmp_path / "y", tmp_path / "run")


# ---------------------------------------------------------------- built-in stages on real data


def input_frame(scene):
    from nerfpipe.plugins.export import input_frame_cameras

    return input_frame_cameras(scene)


@pytest.fixture(scope="module")
def mouse_run(scene_path, tmp_path_factory):
    """``load, check, export`` on the real COLMAP mouse (56 registered photos)."""
    run_dir = tmp_path_factory.mktemp("mouse")
    return Pipeline(["sfm", "load", "check", "export"]).run(scene_path("colmap_mouse"), run_dir)


def test_builtin_chain_on_colmap(mouse_run, scene_path):
    import pycolmap

    assert [r.status for r in mouse_run.records] == ["not needed", "ran", "ran", "ran"]
    scene = mouse_run["scene"]
    summary = json.loads(mouse_run["scene.json"].read_text())
    rec = pycolmap.Reconstruction(str(scene_path("colmap_mouse") / "sparse" / "0"))
    assert summary["num_cameras"] == len(scene.cameras) == rec.num_reg_images()
    assert summary["format"] is None and summary["adapter"] == "colmap"
    assert mouse_run["check"]["failures"] == []
    # camera centres in the input frame are COLMAP's, independently of nerfpipe's conversion
    names = [p.name for p in scene.images.paths]
    by_name = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    colmap_centres = np.stack([by_name[n].projection_center() for n in names])
    assert np.allclose(input_frame(scene).centers.numpy(), colmap_centres, atol=1e-4 * np.abs(colmap_centres).max())


def test_export_reads_back_as_the_same_cameras(mouse_run):
    import open3d as o3d

    from nerfpipe import data_adapters

    scene = mouse_run["scene"]
    again = data_adapters.load(mouse_run["export/transforms.json"])
    assert again.format == "nerfstudio" and len(again.cameras) == len(scene.cameras)
    a, b = input_frame(scene), input_frame(again)
    for key in ("fx", "fy", "cx", "cy", "width", "height", "distortion", "dist_params"):
        assert torch.equal(getattr(a, key), getattr(b, key)), key
    assert torch.allclose(a.world_from_cam, b.world_from_cam, atol=1e-6 * float(a.centers.abs().max()))

    traj = o3d.io.read_pinhole_camera_trajectory(str(mouse_run["export/trajectory.json"]))
    assert len(traj.parameters) == len(scene.cameras)
    extrinsic = np.stack([p.extrinsic for p in traj.parameters])
    k = np.stack([p.intrinsic.intrinsic_matrix for p in traj.parameters])
    assert np.allclose(extrinsic, a.cam_from_world.numpy(), atol=1e-9)
    assert np.allclose(k[:, 0, 2], a.cx.numpy() - 0.5) and np.allclose(k[:, 1, 1], a.fy.numpy())  # Open3D: integer pixel centres


def test_check_stage_stops_a_broken_scene(mouse_run, tmp_path):
    from dataclasses import replace

    scene = mouse_run["scene"]
    flipped = replace(scene.cameras)
    flipped.world_from_cam = scene.cameras.world_from_cam @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))  # OpenGL axes
    broken = replace(scene, cameras=flipped)
    with pytest.raises(NerfpipeError, match="camera conventions are broken"):
        Pipeline(["check", "export"]).run(None, tmp_path, cache={"scene": broken})
    assert not (tmp_path / "check.json").exists() and not (tmp_path / "export").exists()
    assert (tmp_path / "check.failed.json").is_file()


def test_in_memory_reconstruction_through_the_python_api(scene_path, tmp_path):
    """A reconstruction and an image folder in memory: no file written by the caller."""
    import pycolmap

    root = scene_path("colmap_mouse")
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    run = tmp_path / "run"
    result = Pipeline(["load", "check"]).run(None, run, reconstruction=rec, images=root / "images")
    scene = result["scene"]
    assert len(scene.cameras) == rec.num_reg_images() and result["check"]["failures"] == []
    assert json.loads((run / "scene.json").read_text())["input"] == "input"  # inside the run: recorded relative to it
    # the run folder alone is enough to restore the scene (resume / ``nerfpipe stage``), moved elsewhere too
    moved = tmp_path / "elsewhere" / "run"
    shutil.move(run, moved)
    fresh = Pipeline(["load", "check"]).run(None, moved)
    assert [r.status for r in fresh.records] == ["skipped", "skipped"]
    assert torch.equal(fresh["scene"].cameras.world_from_cam, scene.cameras.world_from_cam)


def test_cli_run_and_stage(scene_path, tmp_path, capsys):
    toml = tmp_path / "pipe.toml"
    toml.write_text('stages = ["load", "check"]\n[check]\nsamples = 4\n')
    run_dir = tmp_path / "run"
    assert main(["run", str(scene_path("colmap_mouse")), "--pipeline", str(toml), "--out", str(run_dir)]) == 0
    out = capsys.readouterr().out
    assert "load" in out and "check" in out and "ran" in out
    assert json.loads((run_dir / "stages" / "check.done.json").read_text())["config"]["samples"] == 4
    first = (run_dir / "stages" / "check.done.json").stat().st_mtime_ns
    assert main(["stage", "check", str(run_dir)]) == 0  # re-run alone, with the options it ran with
    done = json.loads((run_dir / "stages" / "check.done.json").read_text())
    assert done["config"]["samples"] == 4 and (run_dir / "stages" / "check.done.json").stat().st_mtime_ns > first
    assert main(["run", str(scene_path("colmap_mouse")), "--stages", "load,nope", "--out", str(run_dir)]) == 2


TINY_TRAIN = {
    "train": {
        "model": "vanilla",
        "model_options": {"num_samples": 8, "field": {"width": 16, "depth": 2, "skip": 1, "head_width": 16,
                                                      "pos_frequencies": 2, "dir_frequencies": 1}},
        "trainer": {"iters": 2, "rays_per_step": 32, "eval_every": 0, "final_eval_views": 1, "eval_scale": 0.1,
                    "checkpoint_every": 1, "write_outputs": False},
    },
    "render": {"frames": 3, "scale": 0.2},
}  # fmt: skip


def test_train_and_render_resume_from_the_checkpoint(scene_path, tmp_path):
    import imageio.v3 as iio

    npz = scene_path("lego_200x200") / "lego_200x200.npz"
    first = Pipeline(["load", "train", "render"], TINY_TRAIN).run(npz, tmp_path)
    assert [r.status for r in first.records] == ["ran", "ran", "ran"]
    assert first["metrics"]["iterations"] == 2 and len(first["views"]) == 3
    assert first["views"][0].rgb.shape == (40, 40, 3)  # 200 px cameras at scale 0.2
    for gif in ("orbit.gif", "depth_orbit.gif"):  # GIF writers merge identical frames: count not fixed
        assert iio.imread(tmp_path / "render" / gif, index=None).shape[1:] == (40, 40, 3)

    more = {**TINY_TRAIN, "train": {**TINY_TRAIN["train"], "trainer": {**TINY_TRAIN["train"]["trainer"], "iters": 4}}}
    again = Pipeline(["load", "train", "render"], more).run(npz, tmp_path)
    assert [r.status for r in again.records] == ["skipped", "ran", "ran"]
    history = load_checkpoint(tmp_path / "train" / "checkpoint.safetensors")["history"]["train"]
    assert [row[0] for row in history] == [1, 2, 3, 4]  # steps 1-2 come from the first run's checkpoint
    assert again["metrics"]["iterations"] == 4


# ---------------------------------------------------------------- the example third-party stage


def test_example_stage_is_discovered_and_chained(plugin_entry_points, mouse_run, scene_path, tmp_path):
    import pycolmap
    import trimesh

    with pytest.warns(PluginWarning):
        pipe = Pipeline(["load", "pointcloud"], {"pointcloud": {"max_error_px": 0.0}})
    result = pipe.run(scene_path("colmap_mouse"), tmp_path)
    cloud = trimesh.load(result["pointcloud.ply"], process=False)
    rec = pycolmap.Reconstruction(str(scene_path("colmap_mouse") / "sparse" / "0"))
    xyz = np.array([rec.points3D[i].xyz for i in sorted(rec.points3D)])
    assert len(cloud.vertices) == len(xyz)
    assert np.allclose(np.asarray(cloud.vertices), xyz, atol=1e-5 * np.abs(xyz).max())  # input frame = COLMAP's


@pytest.mark.slow
def test_example_package_installs_with_pip(monkeypatch, scene_path, tmp_path):
    """Really pip-install the example package into this environment; its entry point is then found."""
    try:
        importlib.metadata.distribution("nerfpipe-example-pointcloud")
        installed_before = True
    except importlib.metadata.PackageNotFoundError:
        installed_before = False
    pip = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]
    if not installed_before:
        subprocess.run(pip + ["install", "--no-deps", "--no-build-isolation", "-e", str(EXAMPLE)], check=True)
    try:
        listing = subprocess.run([sys.executable, "-m", "nerfpipe", "stages"], capture_output=True, text=True, check=True)
        assert "pointcloud" in listing.stdout and "warning" not in listing.stdout
        # in this process the editable install's import hook is not active: put the source on the path
        monkeypatch.syspath_prepend(str(EXAMPLE))
        result = Pipeline(["load", "pointcloud"]).run(scene_path("colmap_mouse"), tmp_path)
        assert result["pointcloud.ply"].is_file() and (tmp_path / "stages" / "pointcloud.done.json").is_file()
    finally:
        if not installed_before:
            subprocess.run(pip + ["uninstall", "-y", "nerfpipe-example-pointcloud"], check=True)
