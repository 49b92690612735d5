"""Geometry figures of a mesh against what a dataset offers as reference: a ground-truth mesh
(a synthetic scene's ``gt_mesh.ply``) and/or sparse points (COLMAP), all in the input frame.

Shared by ``nerfpipe eval-mesh`` (a dataset folder as REF) and the ``mesh`` stage.
"""

from dataclasses import dataclass

import numpy as np

from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.typing import Bool, Float


def points_figures(
    mesh: TriangleMesh,
    points: Float[np.ndarray, "num_points 3"],
    threshold: "float | None" = None,
    crop: bool = True,
    on_object: "Bool[np.ndarray, 'num_points'] | None" = None,
    above_support: "Bool[np.ndarray, 'num_points'] | None" = None,
) -> dict:
    """How well ``mesh`` and sparse ``points`` agree, at a threshold (default: 1% of the mesh's diagonal).

    * ``points_within_threshold``: fraction of the points *on the object* within the threshold of the
      mesh (completeness). Which points are on the object is stated in ``points_object_rule``: those of
      ``on_object`` (e.g. inside the box that was meshed), else with ``crop`` those inside the mesh's
      box grown by the threshold, else all; of them, with ``above_support``, only those above the plane the object
      stands on (the table is not the object: :func:`nerfpipe.training.trainer.above_support`); ``points_excluded``
      counts the others.
    * ``points_all_within_threshold``: the same fraction over all points.
    * ``mesh_area_near_points``: fraction of the mesh's area within the threshold of some point
      (accuracy; a fog mesh has most of its area far from every point). Sparse points are sparse,
      so a good mesh scores well below 1 on texture-less parts; compare meshes by it, not with 1.
    """
    from nerfpipe.mesh.metrics import default_threshold, point_fraction

    tau = default_threshold(mesh) if threshold is None else float(threshold)
    points = np.asarray(points, dtype=np.float64)
    rule, keep = _object_points(mesh, points, tau, crop, on_object)
    if above_support is not None:
        rule, keep = f"{rule}, above the support plane", keep & np.asarray(above_support, dtype=bool)
    if not keep.any():
        raise NerfpipeError("no sparse point lies near the mesh: is the mesh in the dataset's frame?")
    fig, every = point_fraction(points[keep], mesh, tau), point_fraction(points, mesh, tau)
    return {"points_total": len(points), "points_used": fig["num_points"], "points_excluded": int((~keep).sum()),
            "points_object_rule": rule, "points_within_threshold": fig["fraction_within"],
            "points_all_within_threshold": every["fraction_within"], "points_median_distance": fig["median_distance"],
            "mesh_area_near_points": area_near_points(mesh, points, tau), "points_threshold": tau}  # fmt: skip


def _object_points(mesh: TriangleMesh, points: np.ndarray, tau: float, crop: bool, on_object) -> "tuple[str, np.ndarray]":
    if on_object is not None:
        return "inside the meshed box", np.asarray(on_object, dtype=bool)
    if crop:
        lo, hi = mesh.bounds()
        return "inside the mesh's bounds grown by the threshold", np.all((points >= lo - tau) & (points <= hi + tau), axis=1)
    return "all", np.ones(len(points), dtype=bool)


def area_near_points(mesh: TriangleMesh, points: Float[np.ndarray, "num_points 3"], threshold: float, samples: int = 100_000) -> float:
    """Fraction of the mesh's area within ``threshold`` of some point (area-uniform surface samples)."""
    from scipy.spatial import cKDTree

    from nerfpipe.mesh.metrics import sample_surface

    surface, _ = sample_surface(mesh, samples)
    d, _ = cKDTree(np.asarray(points, dtype=np.float64)).query(surface, distance_upper_bound=threshold)
    return float(np.mean(d < threshold))


def reference_figures(
    mesh: TriangleMesh,
    gt_mesh: "TriangleMesh | None" = None,
    points: "Float[np.ndarray, 'num_points 3'] | None" = None,
    threshold: "float | None" = None,
    samples: int = 100_000,
    crop: bool = True,
    gt_prefix: str = "",
    on_object: "Bool[np.ndarray, 'num_points'] | None" = None,
    sight_lines: "SightLines | None" = None,
    above_support: "Bool[np.ndarray, 'num_points'] | None" = None,
) -> dict:
    """F-score, Chamfer... against ``gt_mesh`` (keys prefixed by ``gt_prefix``), the points figures and,
    with ``sight_lines``, the free-space violation (:func:`nerfpipe.mesh.metrics.free_space_violation`).

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
        out.update(points_figures(mesh, np.asarray(points, dtype=np.float64), threshold, crop, on_object, above_support))
        if sight_lines is not None:
            from nerfpipe.mesh.metrics import free_space_violation

            out.update(free_space_violation(mesh, sight_lines.points, sight_lines.centers, sight_lines.point_idx, sight_lines.cam_idx))
    return out


@dataclass
class SightLines:
    """Track observations of the sparse points: camera ``cam_idx[i]`` sees point ``point_idx[i]``."""

    points: Float[np.ndarray, "num_points 3"]
    """The sparse points."""
    centers: Float[np.ndarray, "num_cameras 3"]
    """Camera centres, in the frame of the points."""
    point_idx: "np.ndarray"
    cam_idx: "np.ndarray"

    def segments(self) -> "tuple[np.ndarray, np.ndarray]":
        """``(camera centres, points)`` of every observation."""
        return self.centers[np.asarray(self.cam_idx, dtype=np.int64)], self.points[np.asarray(self.point_idx, dtype=np.int64)]


def sight_lines(scene, frame: str = "input") -> "SightLines | None":
    """The dataset's track observations (:class:`nerfpipe.data.scene.Points3D` ``track_*``), in its ``input``
    frame or nerfpipe's ``world`` frame (None without tracks)."""
    pts = scene.points
    if pts is None or not pts.has_tracks:
        return None
    points, centers = pts.xyz.double(), scene.cameras.centers.double().reshape(-1, 3)
    if frame == "input":
        back = scene.world_from_input.inverse()
        points, centers = back.apply_points(points), back.apply_points(centers)
    return SightLines(points=points.numpy(), centers=centers.numpy(), point_idx=pts.track_point.numpy(), cam_idx=pts.track_camera.numpy())


def dataset_references(scene, folder) -> "tuple[TriangleMesh | None, np.ndarray | None]":
    """The references a dataset offers, in its input frame: ``folder/gt_mesh.ply`` and the sparse points.

    Args:
        scene: the loaded ``SceneData`` (its points are in the world frame).
        folder: the dataset path (a file's folder is used), or None for an in-memory input.
    """
    from pathlib import Path

    from nerfpipe.data.synthetic import MESH_FILE
    from nerfpipe.mesh.export import read_mesh

    gt = None
    if folder is not None:
        folder = Path(folder)
        folder = folder if folder.is_dir() else folder.parent
        gt = read_mesh(folder / MESH_FILE) if (folder / MESH_FILE).is_file() else None
    points = None
    if scene.points is not None and len(scene.points.xyz) > 0:
        points = scene.world_from_input.inverse().apply_points(scene.points.xyz.double()).numpy()
    return gt, points
