"""Geometry metrics of a mesh against a reference mesh or reference points.

Points are sampled uniformly (by area) on each mesh and their exact distance to the other
surface is computed with Open3D's ``RaycastingScene`` (closest point on the triangles, not
nearest sampled point, so the figures carry no sampling bias):

* accuracy      mean distance of predicted-surface samples to the reference (lower is better)
* completeness  mean distance of reference samples to the predicted surface
* chamfer_l1    mean of the two
* precision / recall   fraction of predicted / reference samples within ``threshold``
* fscore        harmonic mean of precision and recall at ``threshold``
* normal_consistency   mean ``|n_pred · n_ref|`` at closest points, both directions (1 is best)

The default threshold is 1% of the reference bounding-box diagonal.
"""

from dataclasses import asdict, dataclass

import numpy as np

from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.errors import require
from nerfpipe.util.typing import Bool, Float, Int

DEFAULT_THRESHOLD_FRACTION = 0.01


@dataclass
class MeshMetrics:
    """Figures from :func:`compare_meshes`, in the meshes' units."""

    accuracy: float
    completeness: float
    chamfer_l1: float
    precision: float
    recall: float
    fscore: float
    normal_consistency: float
    threshold: float
    num_samples: int

    def to_dict(self) -> dict:
        return asdict(self)


def sample_surface(mesh: TriangleMesh, count: int, seed: int = 0):
    """``count`` points uniformly distributed by area, with the unit normals of their faces."""
    rng = np.random.default_rng(seed)
    v = mesh.vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    face = rng.choice(mesh.num_faces, size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    f = v[face]
    pts = f[:, 0] + r1[:, None] * (f[:, 1] - f[:, 0]) + r2[:, None] * (f[:, 2] - f[:, 0])
    return pts, mesh.face_normals()[face]


class SurfaceQuery:
    """Exact closest-point queries against one mesh (Open3D ray-casting scene)."""

    def __init__(self, mesh: TriangleMesh) -> None:
        o3d = require("open3d", "mesh")
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(mesh.to_open3d_tensor())
        self._normals = mesh.face_normals()

    def closest(self, points: Float[np.ndarray, "num_points 3"]):
        """Distances to the surface and the unit normal of the closest triangle."""
        q = self._o3d.core.Tensor(np.asarray(points, dtype=np.float32))
        ans = self._scene.compute_closest_points(q)
        cp = ans["points"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        return np.linalg.norm(cp - points, axis=1), self._normals[prim]


def default_threshold(ref: TriangleMesh) -> float:
    return DEFAULT_THRESHOLD_FRACTION * ref.diagonal()


def compare_meshes(pred: TriangleMesh, ref: TriangleMesh, threshold: "float | None" = None, num_samples: int = 100_000, seed: int = 0) -> MeshMetrics:
    """Accuracy, completeness, Chamfer-L1, F-score at ``threshold`` and normal consistency."""
    tau = default_threshold(ref) if threshold is None else float(threshold)
    p_pts, p_n = sample_surface(pred, num_samples, seed)
    r_pts, r_n = sample_surface(ref, num_samples, seed + 1)
    d_pr, n_at_ref = SurfaceQuery(ref).closest(p_pts)
    d_rp, n_at_pred = SurfaceQuery(pred).closest(r_pts)
    precision, recall = float(np.mean(d_pr < tau)), float(np.mean(d_rp < tau))
    fscore = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    nc = 0.5 * (np.abs(np.sum(p_n * n_at_ref, axis=1)).mean() + np.abs(np.sum(r_n * n_at_pred, axis=1)).mean())
    acc, comp = float(d_pr.mean()), float(d_rp.mean())
    return MeshMetrics(acc, comp, 0.5 * (acc + comp), precision, recall, fscore, float(nc), tau, num_samples)


def point_fraction(points: Float[np.ndarray, "num_points 3"], mesh: TriangleMesh, threshold: float) -> "dict[str, float]":
    """Fraction of ``points`` (e.g. COLMAP's sparse points) within ``threshold`` of the surface."""
    d, _ = SurfaceQuery(mesh).closest(np.asarray(points, dtype=np.float64))
    return {"fraction_within": float(np.mean(d < threshold)), "median_distance": float(np.median(d)), "num_points": int(len(d)), "threshold": float(threshold)}


def robust_diagonal(points: Float[np.ndarray, "num_points 3"]) -> float:
    """Diagonal of the points' 2-98 % quantile box (an extent that ignores stray points)."""
    lo, hi = np.quantile(np.asarray(points, dtype=np.float64), [0.02, 0.98], axis=0)
    return float(np.linalg.norm(hi - lo))


def early_hits(
    mesh: TriangleMesh,
    origins: Float[np.ndarray, "num_lines 3"],
    targets: Float[np.ndarray, "num_lines 3"],
    tau: float,
    shift: "Float[np.ndarray, '3'] | None" = None,
) -> "tuple[Bool[np.ndarray, 'num_cast'], Int[np.ndarray, 'num_cast']]":
    """Cast the segments ``origins -> targets`` longer than ``tau`` against ``mesh`` (Open3D): whether the
    first hit lies more than ``tau`` before the target, and the face hit (-1: none).

    Open3D casts in float32, so everything is first moved by ``shift`` (default: the targets' median): a
    capture far from its origin (geo-registered) keeps its precision.
    """
    o3d = require("open3d", "mesh")
    origins, targets = np.asarray(origins, dtype=np.float64), np.asarray(targets, dtype=np.float64)
    shift = np.median(targets, axis=0) if shift is None else np.asarray(shift, dtype=np.float64)
    offset = targets - origins
    length = np.linalg.norm(offset, axis=1)
    ok = length > tau
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(TriangleMesh(mesh.vertices - shift, mesh.faces).to_open3d_tensor())
    rays = np.concatenate([origins[ok] - shift, offset[ok] / length[ok, None]], axis=1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    blocked = ans["t_hit"].numpy() < length[ok] - tau
    return blocked, np.where(np.isfinite(ans["t_hit"].numpy()), prim, -1)


def free_space_violation(
    mesh: TriangleMesh,
    points: Float[np.ndarray, "num_points 3"],
    centers: Float[np.ndarray, "num_cameras 3"],
    point_idx: Int[np.ndarray, "num_obs"],
    cam_idx: Int[np.ndarray, "num_obs"],
    tau: "float | None" = None,
) -> "dict[str, float]":
    """Share of sight lines that the mesh blocks: for every track observation (a point and a camera that
    sees it), the segment from the camera centre to the point must not hit the mesh more than ``tau``
    before the point. A fog box blocks most of them, a correct surface almost none.

    Args:
        mesh: the surface, in the frame of ``points`` and ``centers``.
        points: sparse 3D points.
        centers: camera centres.
        point_idx, cam_idx: one row per observation, indices into ``points`` and ``centers``.
        tau: slack before the point (default: 1 % of the points' 2-98 % extent diagonal).

    Returns:
        ``free_space_violation`` (the share), ``sight_lines`` (observations cast: those longer than
        ``tau``) and ``free_space_tau``.

    Note:
        Open3D casts in float32, so everything is first moved to the points' median: a capture far
        from its origin (geo-registered) keeps its precision.
    """
    points, centers = np.asarray(points, dtype=np.float64), np.asarray(centers, dtype=np.float64)
    tau = 0.01 * robust_diagonal(points) if tau is None else float(tau)
    origins = centers[np.asarray(cam_idx, dtype=np.int64)]
    targets = points[np.asarray(point_idx, dtype=np.int64)]
    blocked, _ = early_hits(mesh, origins, targets, tau, shift=np.median(points, axis=0))
    share = float(blocked.mean()) if len(blocked) else 0.0
    return {"free_space_violation": share, "sight_lines": int(len(blocked)), "free_space_tau": tau}
