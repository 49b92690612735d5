"""Example third-party stage ``pointcloud``: the scene's sparse points as ``pointcloud.ply``.

The points are written in the input frame (nerfpipe's normalisation undone), with their colours,
so they overlay the original COLMAP model or the exported cameras. It uses only nerfpipe's public
stage API: :class:`~nerfpipe.pipeline.stages.StageSpec`, :class:`~nerfpipe.pipeline.stages.StageContext` (the
``scene`` artifact) and :func:`~nerfpipe.pipeline.stages.atomic_path`.
"""

from dataclasses import dataclass

import numpy as np

from nerfpipe.pipeline.stages import StageContext, StageSpec, atomic_path
from nerfpipe.util.errors import NerfpipeError

POINTCLOUD = "pointcloud.ply"


@dataclass
class PointCloudConfig:
    """Options of the ``pointcloud`` stage."""

    max_error_px: float = 0.0
    """Drop points whose reprojection error is above this many pixels (0 keeps all)."""


def input_frame_points(scene, max_error_px: float = 0.0) -> "tuple[np.ndarray, np.ndarray]":
    """``(xyz [N, 3] float64 in the input frame, rgb [N, 3] uint8)`` of the scene's sparse points."""
    if scene.points is None:
        raise NerfpipeError(f"the scene has no sparse points ({scene.format} input)", scene.source)
    keep = np.ones(len(scene.points.xyz), dtype=bool)
    if max_error_px > 0 and scene.points.error is not None:
        keep = scene.points.error.numpy() <= max_error_px
    xyz = scene.world_from_input.inverse().apply_points(scene.points.xyz.double()).numpy()
    return xyz[keep], scene.points.rgb.numpy()[keep]


def run(config: PointCloudConfig, ctx: StageContext) -> "dict[str, object]":
    import trimesh

    xyz, rgb = input_frame_points(ctx.get("scene"), config.max_error_px)
    cloud = trimesh.PointCloud(xyz, colors=np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1))
    with atomic_path(ctx.path(POINTCLOUD)) as tmp:
        cloud.export(tmp, file_type="ply")
    ctx.log.info("pointcloud: %d points -> %s", len(xyz), POINTCLOUD)
    return {"pointcloud": cloud}


STAGE = StageSpec(
    name="pointcloud",
    description="example plugin: the scene's sparse points as a PLY point cloud in the input frame",
    config=PointCloudConfig,
    run=run,
    requires=("scene",),
    produces=(POINTCLOUD,),
    provides=("pointcloud",),
)
