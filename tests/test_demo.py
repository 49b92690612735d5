"""The default chain end to end (sfm, load, check, train, mesh, render, export, report) on a tiny
synthetic scene with the demo's options, shrunk: every artifact exists and the mesh is compared
with the scene's ground-truth mesh and sparse points."""

import json

import pytest
import torch

from nerfpipe.commands.demo import demo_configs
from nerfpipe.data.synthetic import MESH_FILE, SynthConfig, generate
from nerfpipe.pipeline.stages import DEFAULT_CHAIN, Pipeline, stages


def _tiny_configs() -> dict:
    """The demo's options with a few training steps, two small frames and a coarse mesh."""
    cfg = demo_configs(train_seconds=30.0, mesh_resolution=40, frames=2)
    cfg["train"]["trainer"].update(iters=12, rays_per_step=1024, eval_every=0, final_eval_views=1, checkpoint_every=0, num_threads=2)
    cfg["train"]["model_options"] = {"levels": (16, 32, 48), "feature_channels": 2, "hidden": 16}
    cfg["render"].update(scale=0.5)
    cfg["mesh"].update(samples=5000, views={"chunk": 4096})
    return cfg


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("demo")
    scene = generate(root / "scene", SynthConfig(views=16, width=48, height=48, num_points=800))
    torch.set_num_threads(2)
    result = Pipeline(list(DEFAULT_CHAIN), _tiny_configs()).run(scene.path, root / "run", resume=False)
    return scene, result


def test_default_chain_is_the_whole_pipeline():
    assert DEFAULT_CHAIN == ("sfm", "load", "check", "train", "mesh", "render", "export", "report")
    assert set(DEFAULT_CHAIN) <= set(stages())
    assert stages()["train"].config().model == "fast"


def test_default_chain_on_a_tiny_synthetic_scene(tiny_run):
    scene, result = tiny_run
    status = {r.name: r.status for r in result.records}
    assert status == {"sfm": "not needed", **{s: "ran" for s in DEFAULT_CHAIN if s != "sfm"}}
    for spec in (stages()[s] for s in DEFAULT_CHAIN if status[s] == "ran"):
        for artifact in spec.produces:
            assert (result.run_dir / artifact).exists(), artifact
    for name in ("mesh.ply", "mesh_simplified.ply", "mesh_views.png", "mesh.json", "mesh_metrics.json"):
        assert (result.run_dir / "mesh" / name).is_file(), name
    metrics = json.loads((result.run_dir / "train" / "metrics.json").read_text())
    assert metrics["model"] == "fast" and metrics["iterations"] >= 1
    assert json.loads((result.run_dir / "train" / "config.json").read_text())["trainer"]["background"] == "white"
    assert not list(result.run_dir.rglob(".tmp-*"))


def test_mesh_metrics_against_the_ground_truth(tiny_run):
    scene, result = tiny_run
    m = json.loads((result.run_dir / "mesh" / "mesh_metrics.json").read_text())
    assert m["reference"] == MESH_FILE
    assert 0.0 <= m["fscore"] <= 1.0 and 0.0 <= m["precision"] <= 1.0 and 0.0 <= m["recall"] <= 1.0
    assert m["chamfer_l1"] == pytest.approx(0.5 * (m["accuracy"] + m["completeness"]))
    assert m["chamfer_l1"] > 0.0
    assert 0.0 <= m["points_within_threshold"] <= 1.0 and 0 < m["points_used"] <= m["points_total"]
    page = (result.run_dir / "report.html").read_text()
    from nerfpipe.pipeline.report import fmt

    assert "Against the reference" in page and f"<td>{fmt(m['fscore'])}</td>" in page


def test_train_stage_takes_its_share_of_the_pipeline_budget(tmp_path):
    from dataclasses import replace

    from nerfpipe.pipeline.stages import StageContext
    from nerfpipe.plugins.train import TrainStageConfig, _trainer_config

    from nerfpipe.training.evaluation import FINAL_SHARE

    stage = TrainStageConfig()
    cfg = _trainer_config(stage, StageContext(run_dir=tmp_path, time_budget=100.0))
    share = cfg.train_budget
    assert 0.6 * 99.0 < share <= 0.6 * 100.0  # budget_share of what is left
    # end to end, the final evaluation included: training (and the validations' share) first, then the final phase
    assert share < (1 - FINAL_SHARE) * cfg.time_budget < 1.15 * share and cfg.time_budget < 99.0
    assert _trainer_config(stage, StageContext(run_dir=tmp_path)).time_budget is None
    capped = replace(stage, trainer=replace(stage.trainer, train_budget=30.0))
    assert _trainer_config(capped, StageContext(run_dir=tmp_path, time_budget=100.0)).train_budget == 30.0
    assert _trainer_config(stage, StageContext(run_dir=tmp_path)).train_budget is None
    spent = StageContext(run_dir=tmp_path, time_budget=10.0, started=0.0)  # started long ago: nothing left
    assert _trainer_config(stage, spent).train_budget == 0.0

