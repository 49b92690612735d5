"""Geometry figures of a mesh against what a dataset offers as reference: a ground-truth mesh
(a synthetic scene's ``gt_mesh.ply``) and/or sparse points (COLMAP), all in the input frame.

Shared by ``nerfpipe eval-mesh`` (a dataset folder as REF) and the ``mesh`` stage.
"""

import numpy as np

from nerfpipe.errors import NerfpipeError
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.typing import Float


def points_figures(mesh: TriangleMesh, points: Float[np.ndarray, "num_points 3"], threshold: "float | None" = None, crop: bool = True) -> dict:
    """Fraction of ``points`` within the threshold of ``mesh`` (default: 1% of the mesh's diagonal).

    With ``crop``, only the points inside the mesh's box grown by the threshold count (the points
    on the object, not the background).
    """
    from nerfpipe.mesh.metrics import default_threshold, point_fraction

    tau = default_threshold(mesh) if threshold is None else float(threshold)
    total = len(points)
    if crop:
        lo, hi = mesh.bounds()
        points = points[np.all((points >= lo - tau) & (points <= hi + tau), axis=1)]
    if len(points) == 0:
        raise NerfpipeError("no sparse point lies near the mesh: is the mesh in the dataset's frame?")
    fig = point_fraction(points, mesh, tau)
    return {"points_total": total, "points_used": fig["num_points"], "points_within_threshold": fig["fraction_within"],
            "points_median_distance": fig["median_distance"], "points_threshold": tau}  # fmt: skip


def reference_figures(
    mesh: TriangleMesh,
    gt_mesh: "TriangleMesh | None" = None,
    points: "Float[np.ndarray, 'num_points 3'] | None" = None,
    threshold: "float | None" = None,
    samples: int = 100_000,
    crop: bool = True,
    gt_prefix: str = "",
) -> dict:
    """F-score, Chamfer... against ``gt_mesh`` (keys prefixed by ``gt_prefix``) and the points figures.

    Raises:
        NerfpipeError: when there is neither a ground-truth mesh nor a sparse point.
    """
    from nerfpipe.mesh.metrics import compare_meshes

    has_points = points is not None and len(points) > 0
    if gt_mesh is None and not has_points:
        raise NerfpipeError("the dataset has no ground-truth mesh and no sparse points to compare with")
    out = {}
    if gt_mesh is not None:
        out.update({f"{gt_prefix}{k}": v for k, v in compare_meshes(mesh, gt_mesh, threshold, num_samples=samples).to_dict().items()})
    if has_points:
        out.update(points_figures(mesh, np.asarray(points, dtype=np.float64), threshold, crop))
    return out


def dataset_references(scene, folder) -> "tuple[TriangleMesh | None, np.ndarray | None]":
    """The references a dataset offers, in its input frame: ``folder/gt_mesh.ply`` and the sparse points.

    Args:
        scene: the loaded ``SceneData`` (its points are in the world frame).
        folder: the dataset path (a file's folder is used), or None for an in-memory input.
    """
    from pathlib import Path

    from nerfpipe.mesh.export import read_mesh
    from nerfpipe.synthetic import MESH_FILE

    gt = None
    if folder is not None:
        folder = Path(folder)
        folder = folder if folder.is_dir() else folder.parent
        gt = read_mesh(folder / MESH_FILE) if (folder / MESH_FILE).is_file() else None
    points = None
    if scene.points is not None and len(scene.points.xyz) > 0:
        points = scene.world_from_input.inverse().apply_points(scene.points.xyz.double()).numpy()
    return gt, points
