"""Cleaning and simplification of extracted meshes (pymeshlab, scipy), and face visibility (Open3D).

* :func:`remove_small_components` drops floaters: connected pieces (:func:`component_labels`) whose
  bounding-box diagonal is a small fraction of the whole mesh's (:func:`edge_pieces` for flaps hanging on a
  vertex), or that lie far from the main piece;
* :func:`faces_near_box_sides` marks the faces along the sides of the meshed box (fog walls);
* :func:`visible_faces` marks the faces some training camera sees (a z-buffer test against
  a ray-cast depth map per camera), so faces no camera sees (inner blobs) can be dropped;
* :func:`faces_blocking_sight_lines` marks the faces that camera-to-point sight lines of the sparse
  points' tracks cross before reaching their point (fog the cameras see through);
* :func:`support_plane` finds the plane an object stands on (a RANSAC plane under the sparse points,
  cameras on one side) and :func:`faces_on_or_below_plane` marks the mesh of that support;
* :func:`close_holes` fills holes up to a number of boundary edges;
* :func:`simplify` runs quadric edge collapse to a target face count;
* :func:`hausdorff_distance` measures what simplification changed.
"""

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import camera_rays
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.util.typing import Bool, Float, Int


def _meshset(mesh: TriangleMesh):
    pymeshlab = require("pymeshlab", "mesh")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(mesh.to_pymeshlab())
    return ms


def _result(ms, mesh: TriangleMesh, **info) -> TriangleMesh:
    out = TriangleMesh.from_pymeshlab(ms.current_mesh(), with_colors=mesh.vertex_colors is not None, info=mesh.info)
    out.info.update(info)
    return out


def component_labels(mesh: TriangleMesh) -> "tuple[int, Int[np.ndarray, 'num_verts']]":
    """Connected components (faces that share a vertex): how many labels there are and each vertex's label
    (a face's is its first vertex's; an unreferenced vertex is a label of its own)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f, n = mesh.faces, mesh.num_vertices
    edges = coo_matrix((np.ones(2 * len(f)), (np.concatenate([f[:, 0], f[:, 1]]), np.concatenate([f[:, 1], f[:, 2]]))), shape=(n, n))
    count, label = connected_components(edges, directed=False)
    return int(count), label


def edge_pieces(mesh: TriangleMesh) -> "tuple[int, Int[np.ndarray, 'num_faces']]":
    """Pieces of faces joined through shared edges (a piece that touches the rest at a vertex only is its own, unlike
    :func:`component_labels`): how many there are and each face's."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = mesh.faces.astype(np.int64)
    edges = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2), axis=1)
    key = edges[:, 0] * max(mesh.num_vertices, 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    face, key = np.repeat(np.arange(len(f)), 3)[order], key[order]
    same = key[1:] == key[:-1]
    a, b = face[:-1][same], face[1:][same]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(f), len(f)))
    count, label = connected_components(graph, directed=False)
    return int(count), label


def _label_diagonals(points: Float[np.ndarray, "num_points 3"], label: Int[np.ndarray, "num_points"], count: int) -> Float[np.ndarray, "count"]:
    """Bounding-box diagonal of the points of each of ``count`` labels."""
    lo, hi = np.full((count, 3), np.inf), np.full((count, 3), -np.inf)
    np.minimum.at(lo, label, points)
    np.maximum.at(hi, label, points)
    return np.linalg.norm(hi - lo, axis=1)


def _small_edge_pieces(mesh: TriangleMesh, min_diameter: float) -> Bool[np.ndarray, "num_faces"]:
    """Faces of the :func:`edge_pieces` whose bounding-box diagonal is below ``min_diameter``."""
    count, label = edge_pieces(mesh)
    return (_label_diagonals(mesh.vertices[mesh.faces].reshape(-1, 3), np.repeat(label, 3), count) < min_diameter)[label]


def remove_small_components(
    mesh: TriangleMesh, min_diameter_fraction: float = 0.05, max_gap: "float | None" = None,
    anchors: "Float[np.ndarray, 'num_anchors 3'] | None" = None, unsupported: "tuple[float, float, float] | None" = None,
    far_min_anchors: float = 0.0,
) -> TriangleMesh:
    """Drop floaters: connected components whose bounding-box diagonal is below ``min_diameter_fraction`` of
    the mesh's and, with ``max_gap``, those farther than ``max_gap`` from the main component.

    The main component is the one nearest to the most ``anchors`` (e.g. the object's sparse points: the
    object, not the largest sheet of fog), or the largest by area without anchors. With ``anchors`` and
    ``unsupported = (distance, density_share, area_share)``, pieces beside the main one that hold at least
    ``area_share`` of its area but fewer than ``density_share`` of its anchors per area (anchors within
    ``distance`` of a vertex) go too: a sheet of fog beside the object, which no SfM point lies on. With both and
    ``far_min_anchors`` > 0, a piece farther than ``max_gap`` stays where it holds that share of the anchors or more
    (and is not unsupported): a part of the object that the mesh does not join to the rest (a dome above a facade
    whose drum no photograph resolved), not a floater. A small piece that touches a kept one at a vertex only (a
    flap of the fused surface) goes by the size rule too (:func:`edge_pieces`).
    """
    from scipy.spatial import cKDTree

    if mesh.num_faces == 0:
        return mesh
    count, label = component_labels(mesh)
    keep = _label_diagonals(mesh.vertices, label, count) >= min_diameter_fraction * mesh.diagonal()
    has_anchors = anchors is not None and len(anchors) > 0
    if max_gap is not None or (unsupported is not None and has_anchors):
        main = _main_component(mesh, label, count, anchors)
    if max_gap is not None:
        others = np.flatnonzero((label != main) & keep[label])
        gap, _ = cKDTree(mesh.vertices[label == main]).query(mesh.vertices[others], distance_upper_bound=max_gap)
        near = np.bincount(label[others], weights=np.isfinite(gap), minlength=count) > 0
        near[main] = True
        if far_min_anchors > 0 and unsupported is not None and has_anchors:
            near |= _anchors_held(mesh, label, count, anchors, unsupported[0]) >= far_min_anchors * len(anchors)
        keep &= near
    if unsupported is not None and has_anchors:
        keep &= ~_unsupported(mesh, label, count, main, anchors, *unsupported)
    kept = keep[label[mesh.faces[:, 0]]]
    if min_diameter_fraction > 0 and kept.any():
        small = _small_edge_pieces(mesh, min_diameter_fraction * mesh.diagonal())
        if (kept & ~small).any():  # never the whole mesh
            kept &= ~small
    out = mesh.submesh(kept)
    out.info["floater_faces_removed"] = out.info.get("floater_faces_removed", 0) + mesh.num_faces - out.num_faces
    return out


def _unsupported(mesh: TriangleMesh, label, count: int, main: int, anchors, distance: float, density_share: float, area_share: float) -> Bool[np.ndarray, "count"]:
    """Components other than ``main`` with ``area_share`` of its area or more and fewer than ``density_share`` of its
    anchors (within ``distance`` of one of their vertices) per unit area."""
    held = _anchors_held(mesh, label, count, anchors, distance)
    v = mesh.vertices[mesh.faces]
    area = np.bincount(label[mesh.faces[:, 0]], weights=0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1), minlength=count)
    density = held / np.maximum(area, 1e-300)
    out = (area >= area_share * area[main]) & (density < density_share * density[main])
    out[main] = False
    return out


def _anchors_held(mesh: TriangleMesh, label, count: int, anchors, distance: float) -> Int[np.ndarray, "count"]:
    """How many ``anchors`` lie within ``distance`` of each component (of its nearest vertex's)."""
    from scipy.spatial import cKDTree

    used = np.unique(mesh.faces)
    gap, nearest = cKDTree(mesh.vertices[used]).query(np.asarray(anchors, dtype=np.float64), distance_upper_bound=distance)
    return np.bincount(label[used[nearest[np.isfinite(gap)]]], minlength=count)


def _main_component(mesh: TriangleMesh, label, count: int, anchors) -> int:
    """The component whose vertices are nearest to the most ``anchors``; the largest by area without them."""
    from scipy.spatial import cKDTree

    used = np.unique(mesh.faces)
    if anchors is not None and len(anchors) > 0:
        _, nearest = cKDTree(mesh.vertices[used]).query(np.asarray(anchors, dtype=np.float64))
        return int(np.argmax(np.bincount(label[used[nearest]], minlength=count)))
    v = mesh.vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    return int(np.argmax(np.bincount(label[mesh.faces[:, 0]], weights=area, minlength=count)))


def faces_near_box_sides(mesh: TriangleMesh, aabb: Float[np.ndarray, "2 3"], distance: float) -> Bool[np.ndarray, "num_faces"]:
    """Faces with a vertex within ``distance`` of a side of the box ``[min, max]``.

    A field that cannot place the background (walls, a far table) inside its box paints it on the
    box's sides; marching cubes turns that paint into walls that run along the sides ("fog walls").
    """
    lo, hi = np.asarray(aabb, dtype=np.float64)
    near = np.any((mesh.vertices - lo < distance) | (hi - mesh.vertices < distance), axis=1)
    return near[mesh.faces].any(axis=1)


def close_holes(mesh: TriangleMesh, max_hole_edges: int = 30) -> TriangleMesh:
    """Fill holes bounded by at most ``max_hole_edges`` edges (needs a two-manifold mesh)."""
    ms = _meshset(mesh)
    ms.meshing_repair_non_manifold_edges()
    try:
        ms.meshing_close_holes(maxholesize=int(max_hole_edges))
    except Exception as exc:  # pymeshlab raises PyMeshLabException on non-manifold input
        raise NerfpipeError(f"closing holes failed: {exc}") from exc
    return _result(ms, mesh)


SMOOTH_NORMAL_STEPS = 10
"""Face-normal smoothing iterations of each step of :func:`smooth` (pymeshlab's default 20: on the synthetic demo's
mesh 10 with 10 fitting iterations kept 0.954 of its normal consistency against 0.951 for 20 with 20, in 3.5 s against 4.5)."""
SMOOTH_FIT_STEPS = 10
"""Vertex-fitting iterations of each step of :func:`smooth`."""


def smooth(mesh: TriangleMesh, steps: int, feature_angle: float = 60.0) -> TriangleMesh:
    """Feature-preserving smoothing (pymeshlab's two-step smoothing, Belyaev and Ohtake: face normals averaged with
    neighbours whose normals lie within ``feature_angle`` degrees, then vertices moved to fit the smoothed normals),
    ``steps`` times; vertices and faces keep their order and colours. The TSDF surface of a trained field is
    rippled at a few voxels (the field's own noise, the same in every rendered view, so fusion does not average
    it out); edges and corners sharper than ``feature_angle`` are kept."""
    if steps <= 0 or mesh.num_faces == 0:
        return mesh
    ms = _meshset(mesh)
    try:
        ms.apply_coord_two_steps_smoothing(stepsmoothnum=int(steps), normalthr=float(feature_angle),
                                           stepnormalnum=SMOOTH_NORMAL_STEPS, stepfitnum=SMOOTH_FIT_STEPS)
    except Exception as exc:  # pymeshlab raises PyMeshLabException on meshes it cannot walk
        raise NerfpipeError(f"smoothing the mesh failed: {exc}") from exc
    return _result(ms, mesh)


def simplify(mesh: TriangleMesh, target_faces: int) -> TriangleMesh:
    """Quadric edge collapse down to at most ``target_faces`` faces (normals and topology preserved)."""
    if target_faces < 4:
        raise NerfpipeError(f"target face count must be at least 4, got {target_faces}")
    if target_faces >= mesh.num_faces:
        raise NerfpipeError(f"target face count {target_faces} is not below the mesh's {mesh.num_faces} faces: nothing to simplify; choose a smaller --faces")
    ms = _meshset(mesh)
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(target_faces), preservenormal=True, preservetopology=False, optimalplacement=True, planarquadric=True, autoclean=True)
    out = _result(ms, mesh)
    if out.num_faces > target_faces:  # quadric collapse can stop a little short; a second pass finishes
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(target_faces), preservenormal=True, autoclean=True)
        out = _result(ms, mesh)
    return out


def hausdorff_distance(a: TriangleMesh, b: TriangleMesh, samples: int = 50_000) -> "dict[str, float]":
    """Symmetric Hausdorff distance (max) and the mean distance between two meshes (pymeshlab sampling: every vertex
    and ``samples`` points on the faces, each way). 200,000 samples until session 71: the mesh stage's meshes against
    their simplified copies, 200,000 / 50,000 / 20,000 samples, max and mean alike but for the max of colmap_mouse's
    (0.00739 / 0.00704 / 0.00700) and the demo's at 20,000 (0.0125 / 0.0125 / 0.0084), in 2.4-3.2 / 0.8-1.4 / 0.5-0.9 s
    on 2 cores: 1.8 s of every mesh stage, which the orbit render after it gets under a budget."""
    pymeshlab = require("pymeshlab", "mesh")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(a.to_pymeshlab())
    ms.add_mesh(b.to_pymeshlab())
    d_ab = ms.get_hausdorff_distance(sampledmesh=0, targetmesh=1, samplevert=True, sampleface=True, samplenum=int(samples), maxdist=pymeshlab.PercentageValue(100.0))
    d_ba = ms.get_hausdorff_distance(sampledmesh=1, targetmesh=0, samplevert=True, sampleface=True, samplenum=int(samples), maxdist=pymeshlab.PercentageValue(100.0))
    return {"max": max(d_ab["max"], d_ba["max"]), "mean": 0.5 * (d_ab["mean"] + d_ba["mean"])}


def visible_faces(
    mesh: TriangleMesh, cameras: Cameras, max_side: int = 128, tolerance: "float | None" = None, front_only: bool = False,
) -> Bool[np.ndarray, "num_faces"]:
    """Faces whose centre some camera sees: in its image and not behind the ray-cast surface.

    For each camera a depth map of the mesh is ray-cast at ``max_side`` pixels; a face is
    seen when its centre projects into the image at a depth within ``tolerance`` (default
    0.5% of the mesh diagonal) of the farthest ray-cast depth among the 3×3 pixels around it (lenient at silhouettes
    and grazing angles; faces hidden behind a visible surface are still caught). With ``front_only`` a face
    counts only when the camera is on its outer side (counter-clockwise winding): a camera stands in free
    space, so a face it sees from behind is the inside of a solid, seen through a hole in its front.
    """
    o3d = require("open3d", "mesh")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh.to_open3d_tensor())
    cams = cameras.reshape(-1).to(dtype=torch.float64).capped(max_side)
    tol = 0.005 * mesh.diagonal() if tolerance is None else tolerance
    centres = torch.from_numpy(mesh.vertices[mesh.faces].mean(1))
    normals = torch.from_numpy(mesh.face_normals())
    seen = torch.zeros(mesh.num_faces, dtype=torch.bool)
    for i in range(len(cams)):
        zbuf = _depth_map(scene, cams, i)
        zbuf = torch.nn.functional.max_pool2d(zbuf[None, None], 3, stride=1, padding=1)[0, 0]
        uv, z = _project(cams[i], centres)
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (z > 0) & (col >= 0) & (row >= 0) & (col < int(cams.width[i])) & (row < int(cams.height[i]))
        depth = torch.full_like(z, -1.0)
        depth[inside] = zbuf[row[inside], col[inside]]
        visible = inside & (z <= depth + tol)
        if front_only:
            visible &= ((cams.world_from_cam[i, :3, 3] - centres) * normals).sum(-1) > 0
        seen |= visible
    return seen.numpy()


def _project(cam: Cameras, points: torch.Tensor):
    """Project world points with one camera: ``(pixel uv, camera-z depth)``."""
    cfw = cam.cam_from_world
    p = points @ cfw[:3, :3].T + cfw[:3, 3]
    z = p[:, 2]
    xy = p[:, :2] / z.clamp(min=1e-12)[:, None]
    if int(cam.distortion) == 0:
        return torch.stack([cam.fx * xy[:, 0] + cam.cx, cam.fy * xy[:, 1] + cam.cy], dim=-1), z
    n = len(points)  # distorted: Cameras.normalized_to_pixel wants one camera per point
    expand = Cameras(cam.world_from_cam.expand(n, 4, 4), cam.fx.expand(n), cam.fy.expand(n), cam.cx.expand(n), cam.cy.expand(n), cam.width.expand(n), cam.height.expand(n), cam.distortion.expand(n), cam.dist_params.expand(n, 4))
    return expand.normalized_to_pixel(xy), z


def _depth_map(scene, cams: Cameras, index: int) -> torch.Tensor:
    """Camera-z depth of the first hit per pixel (inf where the ray misses).

    Pinhole cameras use Open3D's own ray generator (fast); distorted ones nerfpipe's rays.
    """
    import open3d as o3d

    cam = cams[index]
    if int(cam.distortion) == 0:
        k, cfw = (o3d.core.Tensor(m.double().numpy()) for m in (cam.K, cam.cam_from_world))
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(k, cfw, int(cam.width), int(cam.height))
        z_per_t = torch.from_numpy(rays.numpy()[..., 3:]).double() @ cam.forward.double()
    else:
        bundle = camera_rays(cams, index)
        rays = o3d.core.Tensor(torch.cat([bundle.origins, bundle.directions], dim=-1).float().numpy())
        z_per_t = bundle.z_scale.double()
    t = torch.from_numpy(scene.cast_rays(rays)["t_hit"].numpy()).double()
    return t * z_per_t


def faces_blocking_sight_lines(
    mesh: TriangleMesh,
    origins: Float[np.ndarray, "num_lines 3"],
    targets: Float[np.ndarray, "num_lines 3"],
    tau: float,
    min_hits: int = 1,
    keep_near: "Float[np.ndarray, 'num_points 3'] | None" = None,
) -> Bool[np.ndarray, "num_faces"]:
    """Faces that the cameras see through: the first face a camera-to-point sight line hits when that hit
    lies more than ``tau`` before the point (the point was photographed, so nothing can stand there).

    Only the first hit of each line is counted; callers repeat after removing the faces to peel
    fog in layers. A face is marked once ``min_hits`` lines hit it early, unless its centre lies within
    ``tau`` of one of the points ``keep_near``: that is the surface the points lie on, which a line seeing
    its point at a grazing angle crosses early when the surface sits a little in front of the points.
    """
    from scipy.spatial import cKDTree

    from nerfpipe.mesh.metrics import early_hits

    blocked, face = early_hits(mesh, origins, targets, tau)
    marked = np.bincount(face[blocked], minlength=mesh.num_faces) >= min_hits
    if keep_near is not None and len(keep_near) > 0 and marked.any():
        centres = mesh.vertices[mesh.faces[marked]].mean(axis=1)
        near = cKDTree(np.asarray(keep_near, dtype=np.float64)).query(centres, distance_upper_bound=tau)[0] < tau
        marked[np.flatnonzero(marked)[near]] = False
    return marked


SIDE_TEST_ELEMENTS = 1 << 22
"""Elements of the [points, planes] arrays that :func:`support_plane`'s side tests hold at once (32 MB of float64 each)."""


def support_plane(
    candidates: Float[np.ndarray, "num_candidates 3"], points: Float[np.ndarray, "num_points 3"],
    centers: Float[np.ndarray, "num_cameras 3"], tolerance: float, normals: "Float[np.ndarray, 'num_candidates 3'] | None" = None,
    min_inliers: float = 0.05, cameras_above: float = 0.95, points_above: float = 0.98, max_angle_deg: float = 25.0,
    hypotheses: int = 4000, seed: int = 0, up: "Float[np.ndarray, '3'] | None" = None, max_tilt_deg: float = 45.0,
    min_points: float = 0.01,
) -> "Float[np.ndarray, '4'] | None":
    """The plane an object stands on: of the planes with ``cameras_above`` of the cameras on one side and
    ``points_above`` of the object's sparse ``points`` on that side or within ``tolerance`` of it (a plane
    that bounds the object from below, seen from above), the one with the most ``candidates`` within
    ``tolerance``: RANSAC over planes through three candidates, refined by least squares on its inliers.

    Candidates are surface samples and sparse points: a white table has few sparse points but a flat
    surface, a textured one many. The side tests are made inside the RANSAC loop, because Open3D's
    ``segment_plane`` only returns the largest plane, which on a capture is often a face of the object
    or a slice of fog.

    With ``up`` (the cameras' mean up direction), only planes whose normal lies within ``max_tilt_deg`` of it
    count: a photo collection's wall or the back of a dome also has every camera and point on one side.
    A plane must also hold ``min_points`` of the ``points`` within ``tolerance``: an object touches what it
    stands on and SfM sees the contact (even on a white table), while a flat slice through the fog of a mesh
    fused from few views, which can hold more surface samples than the table's noisy patch, holds none.

    Returns:
        ``(a, b, c, d)`` with a unit normal and ``a x + b y + c z + d > 0`` on the cameras' side; None
        when no plane qualifies or none holds ``min_inliers`` of the candidates (a free-standing object, an
        object seen from all around, a scene without a dominant plane).
    """
    cand = np.asarray(candidates, dtype=np.float64)
    points, centers = np.asarray(points, dtype=np.float64), np.asarray(centers, dtype=np.float64)
    if len(cand) < 3:
        return None
    tri = cand[np.random.default_rng(seed).integers(0, len(cand), size=(hypotheses, 3))]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    normal, tri = normal[length > 0] / length[length > 0, None], tri[length > 0]
    planes = np.concatenate([normal, -(normal * tri[:, 0]).sum(axis=1, keepdims=True)], axis=1)
    keep = np.zeros(len(planes), dtype=bool)
    step = max(1, SIDE_TEST_ELEMENTS // max(len(points), len(centers), 1))  # [points, planes] arrays of bounded size
    for start in range(0, len(planes), step):
        chunk = planes[start : start + step]  # a view: _bounds_from_below turns its planes towards the cameras in place
        ok = _bounds_from_below(chunk, points, centers, tolerance, cameras_above, points_above)
        keep[start : start + step] = ok & (np.mean(np.abs(points @ chunk[:, :3].T + chunk[:, 3]) < tolerance, axis=0) >= min_points)
    planes = planes[keep]
    if up is not None:  # a floor or a table, not a wall: its normal within max_tilt_deg of the cameras' up
        planes = planes[planes[:, :3] @ (np.asarray(up, dtype=np.float64) / np.linalg.norm(up)) >= np.cos(np.radians(max_tilt_deg))]
    if len(planes) == 0:
        return None
    count = np.zeros(len(planes), dtype=np.int64)
    for start in range(0, len(cand), 4096):  # candidates x planes, 4096 candidates at a time
        count += _inliers(cand[start : start + 4096], None if normals is None else normals[start : start + 4096], planes, tolerance, max_angle_deg).sum(axis=0)
    if count.max() < min_inliers * len(cand):
        return None
    best = planes[int(np.argmax(count))]
    inliers = cand[_inliers(cand, normals, best[None], tolerance, max_angle_deg)[:, 0]]
    centre = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centre, full_matrices=False)[2][-1]
    refined = np.concatenate([normal, [-normal @ centre]])[None]
    return refined[0] if _bounds_from_below(refined, points, centers, tolerance, cameras_above, points_above)[0] else best


def _inliers(cand, normals, planes, tolerance: float, max_angle_deg: float) -> Bool[np.ndarray, "num_candidates num_planes"]:
    """Candidates within ``tolerance`` of each plane and, where they have a normal, parallel to it within
    ``max_angle_deg`` (a slice through fog crosses surfaces at all angles, a table lies in its plane)."""
    near = np.abs(cand @ planes[:, :3].T + planes[:, 3]) < tolerance
    if normals is None:
        return near
    flat = np.abs(normals @ planes[:, :3].T) > np.cos(np.radians(max_angle_deg))
    return near & (flat | ~np.any(normals != 0, axis=1, keepdims=True))


def _bounds_from_below(planes, points, centers, tolerance: float, cameras_above: float, points_above: float) -> Bool[np.ndarray, "num_planes"]:
    """Turn each of ``planes`` (in place) towards the majority of the cameras; whether it has ``cameras_above``
    of them strictly on that side and ``points_above`` of the points above ``-tolerance``."""
    side = centers @ planes[:, :3].T + planes[:, 3]
    flip = np.mean(side > 0, axis=0) < 0.5
    planes[flip] *= -1
    side[:, flip] *= -1
    height = points @ planes[:, :3].T + planes[:, 3]
    return (np.mean(side > 0, axis=0) >= cameras_above) & (np.mean(height > -tolerance, axis=0) >= points_above)


def faces_on_or_below_plane(mesh: TriangleMesh, plane: Float[np.ndarray, "4"], tolerance: float) -> Bool[np.ndarray, "num_faces"]:
    """Faces with every vertex within ``tolerance`` above the plane or under it (the support and what the
    cameras never see below it)."""
    height = mesh.vertices @ plane[:3] + plane[3]
    return (height[mesh.faces] < tolerance).all(axis=1)


def faces_outside_footprint(
    mesh: TriangleMesh, plane: Float[np.ndarray, "4"], points: Float[np.ndarray, "num_points 3"], tolerance: float, margin: float
) -> Bool[np.ndarray, "num_faces"]:
    """Faces whose foot on the support ``plane`` lies more than ``margin`` outside the object's footprint: the
    convex hull, on the plane, of the sparse ``points`` more than ``tolerance`` above it (an object that stands on
    a table stands over its own points; what lies beside it is table or fog). None outside when fewer than three
    points are above the plane or they are all on a line."""
    from scipy.spatial import ConvexHull, QhullError

    n, d = plane[:3] / np.linalg.norm(plane[:3]), plane[3] / np.linalg.norm(plane[:3])
    above = points[points @ n + d > tolerance]
    outside = np.zeros(mesh.num_faces, dtype=bool)
    if len(above) < 3:
        return outside
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    basis = np.stack([a, np.cross(n, a)], axis=1)  # [3, 2]: coordinates on the plane
    try:
        hull = ConvexHull(above @ basis)
    except QhullError:
        return outside
    feet = mesh.vertices[mesh.faces].mean(axis=1) @ basis
    # the largest signed distance to the hull's edge lines: a lower bound of the distance to the hull outside it
    return (feet @ hull.equations[:, :2].T + hull.equations[:, 2]).max(axis=1) > margin
