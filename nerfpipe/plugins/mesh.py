"""Stage ``mesh``: a mesh of the trained model, as ``nerfpipe mesh`` makes it, plus geometry metrics.

Uses :func:`nerfpipe.mesh.trained.mesh_model` and :func:`nerfpipe.mesh.pipeline.write_meshes`, the
same functions as ``nerfpipe mesh``, and writes the folder ``mesh/`` atomically: ``mesh.ply``,
``mesh_simplified.ply``, ``mesh_views.png``, ``mesh.json`` (in the input dataset's frame).

When the input offers a reference (a synthetic scene's ``gt_mesh.ply``, COLMAP sparse points),
``mesh/mesh_metrics.json`` holds the figures of :func:`nerfpipe.mesh.reference.reference_figures`
for ``mesh.ply``: F-score at 1% of the reference's diagonal, Chamfer-L1, accuracy, completeness
(against the mesh) and the fraction of sparse points within the threshold.

Under a time budget (``ctx.time_for_stage()``: the time left less the orbit render's few seconds) the marching-cubes
resolution is lowered (256 -> 192 -> 128) when the estimated cost does not fit half the time left; TSDF fusion (the
default) renders the views that fit and fuses coarser voxels where its faces would not fit the stage's reserve
(:meth:`RenderedViews.max_faces`). mesh.json records ``resolution`` and ``resolution_requested``.
"""

import dataclasses
import json
from dataclasses import dataclass, field

from nerfpipe.mesh.pipeline import MESH_DEPENDENCIES, MeshConfig
from nerfpipe.mesh.trained import RenderedViews
from nerfpipe.pipeline.report_items import Shown
from nerfpipe.pipeline.stages import StageContext, StageSpec, atomic_path

MESH_DIR = "mesh"
MESH_PLY = f"{MESH_DIR}/mesh.ply"
MESH_JSON = f"{MESH_DIR}/mesh.json"
METRICS_FILE = "mesh_metrics.json"


@dataclass
class MeshStageConfig:
    """Options of the ``mesh`` stage (the defaults of ``nerfpipe mesh``)."""

    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Extraction, cleaning and simplification."""
    views: RenderedViews = field(default_factory=RenderedViews)
    """Training views rendered for the depth level and TSDF fusion."""
    evaluate: bool = True
    """Compare with the input's ground-truth mesh / sparse points when it has them."""
    threshold: "float | None" = None
    """Distance threshold of the F-score (default: 1% of the reference mesh's diagonal, or of the mesh's)."""
    samples: int = 100_000
    """Points sampled on each surface for the metrics."""


def evaluate(config: MeshStageConfig, ctx: StageContext, scene, mesh_input_frame, box_world) -> "dict | None":
    """The geometry figures against the input's references; None when it has none.

    The sparse points "on the object" are those inside the box that was meshed (world frame) and, where the scene's
    sparse points give the plane the object stands on, not on or under it (:func:`nerfpipe.training.trainer.above_support`:
    the mesh stage removes the table, and counted, colmap_mouse's 424 of 4,411 boxed points on or under it held a mesh of
    the object alone under 95 %; ``points_box_within_threshold`` keeps the box rule's figure).
    """
    from nerfpipe.mesh.reference import dataset_references, reference_figures, sight_lines

    gt, points = dataset_references(scene, ctx.source)
    if gt is None and points is None:
        return None
    in_box = above = None
    if points is not None:
        from nerfpipe.training.trainer import above_support

        in_box, above = meshed_box_points(scene, box_world), above_support(scene)
    reference = "gt_mesh.ply" if gt is not None else "sparse points"
    figures = reference_figures(mesh_input_frame, gt, points, config.threshold, config.samples, on_object=in_box, sight_lines=sight_lines(scene),
                                above_support=above)
    if in_box is not None and "points_threshold" in figures:  # the box rule's figure beside it
        from nerfpipe.mesh.metrics import point_fraction

        figures["points_box_within_threshold"] = point_fraction(points[in_box], mesh_input_frame, figures["points_threshold"])["fraction_within"]
    return {"reference": reference, **figures}


def meshed_box_points(scene, box_world) -> "np.ndarray":
    """Which of the scene's sparse points lie inside the meshed box ``box_world`` (world frame)."""
    import numpy as np

    lo, hi = np.asarray(box_world, dtype=np.float64)
    xyz = scene.points.xyz.double().cpu().numpy()
    return np.all((xyz >= lo) & (xyz <= hi), axis=1)


def budgeted(cfg: MeshConfig, seconds_left: "float | None") -> MeshConfig:
    """``cfg`` with the marching-cubes resolution lowered when the time left is short (see resolution_for_budget)."""
    from nerfpipe.mesh.pipeline import resolution_for_budget

    if cfg.method != "mc":
        return cfg
    return dataclasses.replace(cfg, resolution=resolution_for_budget(cfg.resolution, seconds_left))


def run(config: MeshStageConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe.mesh.export import to_input_frame
    from nerfpipe.mesh.pipeline import write_meshes
    from nerfpipe.mesh.trained import mesh_model

    scene, model = ctx.get("scene"), ctx.get("model")
    seconds_left = ctx.time_for_stage()  # the orbit render after it keeps its few seconds
    cfg = budgeted(config.mesh, seconds_left)
    result = mesh_model(cfg, model, scene, config.views, ctx.device, seconds_left)
    result.figures.update(resolution_requested=config.mesh.resolution, seconds_left_at_start=seconds_left)
    full = to_input_frame(result.full, scene.world_from_input)
    figures = evaluate(config, ctx, scene, full, result.figures["box_world"]) if config.evaluate else None
    with atomic_path(ctx.path(MESH_DIR)) as tmp:
        write_meshes(result, tmp, scene.world_from_input, seen_from=scene.split_cameras("train").centers.reshape(-1, 3).double().numpy())
        if figures is not None:
            (tmp / METRICS_FILE).write_text(json.dumps(figures, indent=2) + "\n")
    ctx.log.info("mesh: %d faces%s", result.full.num_faces, "" if figures is None else ", " + _headline(figures))
    return {MESH_PLY: ctx.path(MESH_PLY), MESH_JSON: ctx.path(MESH_JSON)}


def _headline(figures: dict) -> str:
    """The reference figures in a few words: the F-score against a mesh; against sparse points, the share near the
    mesh and the sight lines the mesh blocks."""
    if "fscore" in figures:
        return f"F-score {figures['fscore']:.3f} against {figures['reference']}"
    line = f"{figures['points_within_threshold']:.1%} of {figures['reference']} within {figures['points_threshold']:.3g}"
    return line + (f", free-space violation {figures['free_space_violation']:.3f}" if "free_space_violation" in figures else "")


STAGE = StageSpec(
    name="mesh",
    description="mesh of the trained model (marching cubes or TSDF), cleaned and simplified, with geometry metrics",
    config=MeshStageConfig,
    run=run,
    requires=("scene", "model"),
    produces=(MESH_PLY, MESH_JSON),
    shows=(Shown("mesh", "table", (MESH_JSON,), "mesh figures"), Shown("mesh_views", "image", (f"{MESH_DIR}/mesh_views.png",), "mesh from four views"),
           Shown("mesh_evaluation", "table", (f"{MESH_DIR}/{METRICS_FILE}",), "mesh against the reference")),
    dependencies=MESH_DEPENDENCIES,
)
