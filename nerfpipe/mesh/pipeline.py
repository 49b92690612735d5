"""The mesh post-stage as one function over callables: extract -> clean -> colour -> simplify -> write.

:func:`build_meshes` works in the world frame with a ``density_fn`` (marching cubes) or a
``render_fn`` (TSDF of rendered depth); :func:`write_meshes` maps the results to the input frame
and writes ``mesh.ply``, ``mesh_simplified.ply``, ``mesh_views.png`` and ``mesh.json``. Nothing
is written until every mesh is built, so bad input leaves no files behind.
"""

import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np


from nerfpipe.data.cameras import Cameras
from nerfpipe.util.atomic import write_json
from nerfpipe.util.errors import NerfpipeError, refuse_unless
from nerfpipe.mesh.clean import (
    close_holes, faces_blocking_sight_lines, faces_near_box_sides, faces_on_or_below_plane, faces_outside_footprint, hausdorff_distance,
    remove_small_components,
    simplify, smooth, support_plane, visible_faces,
)
from nerfpipe.data.normalize import upright_direction
from nerfpipe.data.normalize import OBJECT_PAD
from nerfpipe.data.scene import Similarity
from nerfpipe.mesh.color import RgbFn, vertex_colors
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.export import to_input_frame, write_ply
from nerfpipe.mesh.extract import DensityFn, OccupancyFn, Volume, auto_level, level_from_surface_points, mesh_volume, sample_volume
from nerfpipe.mesh.level import choose_level
from nerfpipe.mesh.metrics import robust_diagonal
from nerfpipe.mesh.tsdf import FrameFn, tsdf_fuse
from nerfpipe.mesh.views import write_views
from nerfpipe.util.typing import Float, Tensor

MESH_DEPENDENCIES = (("skimage.measure", "mesh"), ("open3d", "mesh"), ("pymeshlab", "mesh"), ("trimesh", "mesh"))
"""What meshing, cleaning, simplifying and writing need beyond the core (checked before the work starts)."""

DEFAULT_FACES = 100_000
FILES = ("mesh.ply", "mesh_simplified.ply", "mesh_views.png", "mesh.json")


@dataclass
class MeshConfig:
    """How a mesh is extracted, cleaned and simplified."""

    method: Literal["mc", "tsdf"] = "tsdf"
    """tsdf (default): fuse the depth at which rendered training rays stop (the model's stop opacity), so the
    surface sits where the photographs see it and fog that rays pass through leaves nothing; on colmap_mouse
    95% -> 98% of the sparse points near the mesh and free-space violation 0.65 -> 0.035 over mc. mc: marching
    cubes on the density field (closed shells, also where no camera looks, but fog becomes surface)."""
    resolution: int = 256
    """Grid samples along the longest side of the box (mc), or TSDF voxels along it (tsdf)."""
    truncation: float = 4.0
    """tsdf: the truncation distance in voxels. A larger one lets views whose rendered depths disagree (a texture-less
    side, seen at grazing angles) fill the surface instead of carving holes into each other, but lets early stops
    pull it outward. Session 70, the mesh stage re-run on one checkpoint each (one smoothing step), 4 / 6 / 8: the
    synthetic demo against its true mesh F-score@1 % 0.977 / 0.989 / 0.989, Chamfer-L1 0.0070 / 0.0053 / 0.0049,
    free-space violation 0.020 / 0.033 / 0.044; colmap_mouse 98.1 / 98.1 / 98.0 % of the points within 1 % and 0.024 /
    0.029 / 0.034 (the lilac end's holes mostly closed at 8, 0.047 at 12); 23 of ngp_fox's photos 99.7 / 99.7 / 99.6 %
    and 0.0066 / 0.0086 / 0.0134; the Sceaux castle 93.7 / 92.7 / 92.2 % and 0.015 / 0.018 / 0.023: on real captures
    no more points near the mesh and more sight lines blocked, so 4 stays the default."""
    level: "float | None" = None
    """Density iso-level (mc); default: chosen by ``level_from``."""
    level_from: Literal["agreement", "quantile", "opacity"] = "opacity"
    """Automatic level (mc). opacity (default): the density at which a ray crossing one voxel of the grid is
    ``level_opacity`` blocked, ``-ln(1 - level_opacity) / h`` (of the three rules it measured best on both
    references we have, the demo's ground-truth mesh and colmap_mouse's sparse points: see the README).
    quantile: the ``level_quantile`` quantile of the density where rendered training rays end. agreement: the candidate level whose surface is closest to the points where
    rendered training rays end (at their median depth in the sampled volume when the ray origins are given; clamped Chamfer distance, candidates meshed on a ``level_downsample`` times
    coarser copy of the sampled volume; see :mod:`nerfpipe.mesh.level`). agreement and quantile need rendered
    surface points."""
    level_opacity: float = 0.05
    """With ``level_from=opacity``: the opacity of one voxel at the level (0.5 puts the surface at the core of
    a soft shell and leaves holes; 0.05 at its front, where the photographs see it)."""
    level_quantile: float = 0.1
    """With ``level_from=quantile``: the level is this quantile of the densities where rendered rays end,
    i.e. the surface encloses ``1 - level_quantile`` of the observed surface points."""
    level_downsample: int = 2
    """With ``level_from=agreement``: candidates are meshed on every n-th sample per axis."""
    level_clamp: float = 3.0
    """With ``level_from=agreement``: a point's distance counts at most this many coarse voxels."""
    crop_to_points: bool = True
    """Mesh only the object region of the input's sparse points (:func:`nerfpipe.data.normalize.object_region`: their
    2-98% extent per axis near the cameras' focus, grown by ``crop_margin``), intersected with the occupied box;
    inputs without sparse points keep the occupied box."""
    crop_margin: float = OBJECT_PAD
    """Growth of the sparse points' extent, as a fraction of it: the object region's own margin (0.05 and 0.1
    cut colmap_mouse's texture-less end off; the table it stands on enters the box and is found as the
    support plane)."""
    box_sides: float = 2.0
    """Drop faces within this many voxels of the meshed box's sides (background painted on the box: fog walls); 0: keep."""
    support_plane: bool = True
    """Object captures: drop the plane the object stands on and whatever lies below it (after the unseen faces
    are gone). The plane bounds the object's sparse points (those in the meshed box) from below, 98% of them
    above it, has 95% of the cameras on one side, and holds at least ``support_min_share`` of the surface samples (lying in it,
    normals within ``support_max_angle``) and sparse points; of such planes the one holding the most (RANSAC, see
    :func:`nerfpipe.mesh.clean.support_plane`). Faces within ``support_tolerance`` above it go with it. Needs
    sparse points; an object seen from all around, or standing on a surface the field did not make a surface
    (a white table under fog), keeps everything. mesh.json records ``support_plane`` (world frame, None when
    none qualified), ``support_plane_input_frame`` and ``support_faces_removed``."""
    support_min_share: float = 0.02
    """The support plane must hold at least this share of the candidates (surface samples and sparse points):
    a white table that TSDF fusion keeps only in noisy patches near the object holds 2-3% on colmap_mouse
    (the side tests, not this share, keep the object's own faces from qualifying)."""
    support_min_points: float = 0.01
    """The support plane must also have this share of the object's sparse points within ``support_tolerance``
    (the object's base touches it, and SfM sees the contact even on a white table): on 23 of colmap_mouse's photos
    a flat slice through the fog under the mouse, tilted 17 degrees, held more surface samples (5.3%) than the
    table's noisy patch (4.2%) and 1 of 2,663 points (the table: 186), and the table stayed as a skirt."""
    support_max_angle: float = 40.0
    """A surface sample lies in the support plane when its normal is within this many degrees of the plane's
    (a TSDF table is noisy: on colmap_mouse after 180 s the table held 2.0% of the candidates at 25 degrees, 3.9%
    at 40; a slice through fog crosses surfaces at all angles)."""
    support_max_tilt: float = 45.0
    """The support plane's normal lies within this many degrees of the cameras' mean up direction (a floor or a
    table; the Sacre Coeur photos otherwise gave a plane through the back of the dome)."""
    support_from_points: bool = True
    """Where the model knows the plane its object stands on from the sparse points (``SceneInfo.support_plane``: the
    plane the ``fast`` model's table texture lies on, :func:`nerfpipe.training.trainer.support_plane_of`), that plane is
    the support plane, not one found in the mesh, where it holds ``support_min_points`` of the object's points (the
    object touches it; a floor far under a table does not). A TSDF-fused white table is a noisy layer under the true table (on
    colmap_mouse its flat samples lie mostly 0.5 to 2 tolerances below the sparse points' plane, on the 23-photo cut a
    slice 2.8 below holds the most), and the plane RANSAC finds in it wanders by degrees from run to run (six seeds on
    one colmap_mouse mesh: two orientations 4.9 degrees apart, 93.2 to 96.5 % of the box's points within 1 %), each
    degree tilting it into one side of the object's base or leaving table flakes on the other (session 36)."""
    footprint_margin: "float | None" = 0.05
    """With a support plane, faces whose foot on it lies farther than this share of the sparse points' extent
    outside the footprint of the object's points (their convex hull on the plane) are removed: table and fog beside
    the object (None: kept)."""
    support_tolerance: float = 0.02
    """Faces up to this height above the support plane go with it (fraction of the robust extent diagonal of
    the sparse points on the object); also the RANSAC inlier distance. On colmap_mouse with a TSDF of 25
    views at 256 px, 0.01 left a skirt of table fragments around the mouse (the box's field holds the
    table as a rough, speckled layer); 0.02 leaves the mouse alone, with 96.2% of the points within 0.0372
    against 97.1%, and free-space violation 0.018 against 0.019."""
    free_space_passes: int = 3
    """Fog the cameras see through: drop the faces that a sparse point's sight line (camera to observed point)
    crosses more than ``free_space_slack`` before the point, but for faces within that distance of a sparse
    point (the surface the points lie on, crossed early by lines that see it at a grazing angle); each pass
    removes the first face each line crosses, exposing the next layer, until no line is blocked or this many
    passes. 0: keep. Needs track observations (COLMAP)."""
    free_space_slack: float = 0.03
    """How far before its point a sight line may cross the mesh (fraction of the sparse points' robust extent
    diagonal): the surface a point lies on is noisy and the 5%-opacity level puts it a voxel or two in front of
    the points, so at the free-space metric's 1% the passes would eat the surface itself."""
    faces: "int | None" = None
    """Face count of mesh_simplified.ply; default 100000 (a copy when the mesh is already smaller)."""
    min_component: "float | None" = None
    """Drop connected pieces whose diagonal is below this fraction of the mesh's (floaters; since session 80 also
    the flaps that touch a kept piece at a vertex only: the meshes of session 80's six end-to-end runs went from
    17-141 pieces to 16-73, recall and violation unchanged to the fourth decimal, the demo's F-score 0.9892 ->
    0.9893). Default: 0.01 with tsdf (fog leaves no floaters there; 0.05 dropped the parts of the demo's base seen
    from below: F-score 0.967 -> 0.976), 0.05 with mc."""
    max_gap: float = 0.05
    """Drop connected pieces farther than this fraction of the mesh's diagonal from the main one (the piece the
    most sparse points of the object lie on; the largest without sparse points); 0: keep them."""
    far_min_points: float = 0.02
    """Pieces farther than ``max_gap`` from the main one stay where they hold this share of the object's sparse points or
    more (within 1% of their robust extent diagonal) and are not unsupported (``unsupported_density``): parts of the
    object the mesh does not join to the rest. photos_sacre_coeur (session 47): the main dome, 15 % of the points, lay
    beyond the gap above the facade (its drum a hole) and went as a floater: the mesh stage of one run re-run with it
    held 93.6 % of the points within 1 % instead of 55.2 % (free-space violation 0.0051 against 0.0025); colmap_mouse's
    and the Sceaux castle's meshes unchanged (98.1 % / 0.024, 93.1 % / 0.012). 0: the gap alone decides."""
    unsupported_density: float = 0.05
    """Drop pieces beside the main one that hold ``unsupported_area`` of its area or more but under this share of its
    sparse points per area (points within 1% of their robust extent diagonal of the piece); 0: keep them. On
    colmap_mouse a sheet of fog beside the mouse, a fifth of its area within the 5% gap, held 1.3 points per unit
    area against the mouse's 521."""
    unsupported_area: float = 0.01
    """See ``unsupported_density``: smaller pieces stay (a patch of a texture-less side cut off by holes holds few points)."""
    remove_unseen: bool = True
    """Drop faces no training camera sees (inner blobs); needs the training cameras."""
    remove_unseen_from_behind: bool = True
    """With ``remove_unseen``: a face counts as seen only from its outer side, so the inside of a blob or of
    the object's shell, seen through a hole in its front, goes too (the red of mesh_views.png)."""
    close_holes: int = 300
    """Fill holes with at most this many boundary edges, after the cleaning passes (0: leave holes); a mesh
    pymeshlab cannot fill keeps its holes, with a warning. Larger holes stay open: on the real captures the bottom
    where the support plane went (1,300-2,200 edges); a smaller object's bottom gets a lid. Session 80, the same
    TSDF meshes with 0 / 300: colmap_mouse's 258 holes (5,417 boundary edges) -> 44 (1,513), the holes of its
    lilac end filled in ``mesh_views.png``, 98.0 % of the points within 1 % both, free-space violation 0.0213 /
    0.0215; the synthetic demo against its true mesh F-score@1 % 0.9890 / 0.9892, Chamfer-L1 0.00569 / 0.00572,
    normal consistency 0.942 / 0.939, violation 0.0176 / 0.0176; the synthetic room of 26 views F-score@1 %
    0.970 / 0.973; session 78, the posed 23-photo cut of colmap_mouse: 282 holes -> 34, 99.0 / 99.1 % within 1 %,
    violation 0.0185 / 0.0191. About a second on 150,000 faces."""
    smooth: "int | None" = None
    """Steps of feature-preserving smoothing after cleaning (:func:`nerfpipe.mesh.clean.smooth`; 0: none). Default: 1
    with tsdf, whose surface from a trained field is rippled a few voxels wide (its shading grainy in
    ``mesh_views.png``); 0 with mc (a level set of a smooth density is smooth already: one step there moved a
    48-voxel sphere's vertices 0.0044 from its radius of 0.5 on average, against 0.0005, as each step works over
    about ten rings of edges, not a distance). Session 70, the TSDF meshes of session 69's runs, 0 / 1 / 3 steps:
    the synthetic demo against its true mesh normal consistency 0.904 / 0.937 / 0.954, Chamfer-L1 0.0066 / 0.0063 /
    0.0062, F-score@1 % 0.984 all, free-space violation 0.034 / 0.021 / 0.017; but on real captures each step
    fills concave detail that sight lines reach points through (a groove, a window): violation colmap_mouse
    0.021 / 0.023 / 0.028, the Sceaux castle 0.012 / 0.015 / 0.022, the Sacre Coeur 0.005 / 0.007 / 0.011, 23 of
    ngp_fox's photos 0.0059 / 0.0069 / 0.0090. One step takes the grain away (about 2 microseconds a face)."""
    colors: bool = True
    """Vertex colours from the field (mc) or the rendered images (tsdf)."""
    chunk: int = 1 << 18
    """Points per density / colour call."""

    def __post_init__(self) -> None:
        """Impossible values stop here, before a model is loaded or a file written."""
        refuse_unless((
            ("resolution", 8 <= self.resolution <= 4096, "between 8 and 4096", self.resolution),
            ("truncation", 0 < self.truncation <= 64, "in (0, 64] voxels", self.truncation),
            ("level", self.level is None or math.isfinite(self.level), "a finite density", self.level),
            ("faces", self.faces is None or self.faces >= 4, "at least 4", self.faces),
            ("min_component", self.min_component is None or 0 <= self.min_component < 1, "a fraction in [0, 1)", self.min_component),
            ("close_holes", self.close_holes >= 0, "0 or more", self.close_holes),
            ("smooth", self.smooth is None or self.smooth >= 0, "0 or more", self.smooth),
            ("level_opacity", 0 < self.level_opacity < 1, "in (0, 1)", self.level_opacity),
            ("level_quantile", 0 < self.level_quantile < 1, "in (0, 1)", self.level_quantile),
            ("chunk", self.chunk >= 1, "at least 1", self.chunk),
        ))  # fmt: skip


BUDGET_RESOLUTIONS = (256, 192, 128)
"""Resolutions :func:`resolution_for_budget` steps down through."""


def mesh_seconds(resolution: int, seconds_fixed: float = 20.0, seconds_per_million: float = 2.0) -> float:
    """Rough cost of a marching-cubes mesh on 2 CPU cores: a fixed part (depth renders, level search,
    cleaning, simplification, metrics) plus a part proportional to the grid samples (field calls)."""
    return seconds_fixed + seconds_per_million * resolution**3 / 1e6


def resolution_for_budget(resolution: int, seconds_left: "float | None", share: float = 0.5) -> int:
    """The largest of ``resolution`` and the lower :data:`BUDGET_RESOLUTIONS` whose :func:`mesh_seconds`
    fits in ``share`` of the time left (the smallest when none fits); ``resolution`` without a budget."""
    if seconds_left is None:
        return resolution
    options = [resolution] + [r for r in BUDGET_RESOLUTIONS if r < resolution]
    for r in options:
        if mesh_seconds(r) <= share * seconds_left:
            return r
    return options[-1]


@dataclass
class MeshOutputs:
    """Meshes in the world frame and the figures that go into mesh.json."""

    full: TriangleMesh
    simplified: TriangleMesh
    figures: dict = field(default_factory=dict)


def _extract(cfg: MeshConfig, aabb, density_fn, occupancy_fn, frame_fn, cameras, surface, figures, max_faces: "int | None" = None) -> TriangleMesh:
    if cfg.method == "mc":
        if density_fn is None:
            raise NerfpipeError("marching cubes needs a density field")
        volume = sample_volume(density_fn, aabb, cfg.resolution, occupancy_fn, cfg.chunk)
        start = time.perf_counter()
        level = _level(cfg, volume, density_fn, surface, figures)
        figures["seconds_level"] = time.perf_counter() - start
        res = mesh_volume(volume, level)
        figures.update(level=res.level, voxel_size=res.voxel_size, resolution=cfg.resolution, evaluated_fraction=res.evaluated_fraction)
        return res.mesh
    if frame_fn is None or cameras is None:
        raise NerfpipeError("TSDF fusion needs rendered depth and the training cameras")
    side = float((aabb[1] - aabb[0]).max())
    coarsest = side / min(cfg.resolution, min(BUDGET_RESOLUTIONS))
    mesh = tsdf_fuse(cameras, frame_fn, aabb, side / cfg.resolution, trunc_voxels=cfg.truncation, max_faces=max_faces, max_voxel_size=coarsest)
    voxel = mesh.info["voxel_size"]
    figures.update(voxel_size=voxel, resolution=round(side / voxel), max_faces=max_faces, truncation_voxels=cfg.truncation)
    return mesh


def _level(cfg: MeshConfig, volume: Volume, density_fn, surface, figures: dict) -> float:
    """The iso-level by ``cfg.level`` or ``cfg.level_from``; records the rule (and candidates) in ``figures``."""
    if cfg.level is not None:
        figures["level_rule"] = "given"
        return float(cfg.level)
    if cfg.level_from == "opacity":
        figures.update(level_rule="opacity", level_opacity=cfg.level_opacity)
        return auto_level(volume.grid.spacing, cfg.level_opacity)
    if surface is None:
        raise NerfpipeError(f"level_from={cfg.level_from} needs rendered surface points; give a level or use level_from=opacity")
    surface_points, surface_origins = surface
    if cfg.level_from == "quantile":
        figures.update(level_rule="quantile", level_quantile=cfg.level_quantile)
        return level_from_surface_points(density_fn, surface_points, cfg.chunk, cfg.level_quantile)
    choice = choose_level(volume, surface_points, surface_origins, cfg.level_downsample, cfg.level_clamp)
    figures.update(choice.to_dict())
    return choice.level


def _clean(mesh: TriangleMesh, cfg: MeshConfig, cameras: "Cameras | None", figures: dict, aabb=None, lines=None,
           known_support=None) -> TriangleMesh:
    """Box sides, fog seen through, unseen faces, support plane, floaters and distant pieces, holes (MeshConfig)."""
    figures["faces_extracted"] = mesh.num_faces
    if cfg.box_sides > 0 and aabb is not None:
        near = faces_near_box_sides(mesh, aabb.double().cpu().numpy(), cfg.box_sides * figures["voxel_size"])
        figures["box_side_faces_removed"] = int(near.sum())
        mesh = mesh.submesh(~near)
    points = None if lines is None else _object_points(lines.points, aabb)
    if points is not None and cfg.free_space_passes > 0:
        mesh = _peel_fog(mesh, cfg, lines, points, cfg.free_space_slack * robust_diagonal(points), figures)
    if cfg.remove_unseen and cameras is not None:
        start = time.perf_counter()
        seen = visible_faces(mesh, cameras, front_only=cfg.remove_unseen_from_behind)
        figures.update(unseen_faces_removed=int((~seen).sum()), seconds_visibility=time.perf_counter() - start)
        if seen.any():
            mesh = mesh.submesh(seen)
    if points is not None and cfg.support_plane and cameras is not None and mesh.num_faces > 0:
        mesh = _remove_support(mesh, cameras, points, cfg, figures, known_support if cfg.support_from_points else None)
    min_component = cfg.min_component if cfg.min_component is not None else (0.01 if cfg.method == "tsdf" else 0.05)
    if min_component > 0 or cfg.max_gap > 0:
        before = mesh.num_faces
        gap = cfg.max_gap * mesh.diagonal() if cfg.max_gap > 0 else None
        unsupported = (0.01 * robust_diagonal(points), cfg.unsupported_density, cfg.unsupported_area) if points is not None and cfg.unsupported_density > 0 else None
        mesh = remove_small_components(mesh, min_component, gap, points, unsupported, cfg.far_min_points)
        figures["floater_faces_removed"] = before - mesh.num_faces
    if cfg.close_holes > 0 and mesh.num_faces > 0:
        before = mesh.num_faces
        try:
            mesh = close_holes(mesh, cfg.close_holes)
            figures["hole_faces_added"] = mesh.num_faces - before
        except NerfpipeError as exc:
            warnings.warn(f"{exc}; the mesh keeps its holes", stacklevel=2)
            figures["hole_faces_added"] = 0
    if mesh.num_faces == 0:
        raise NerfpipeError("nothing is left of the mesh after cleaning (every face was unseen or a floater)")
    return mesh


def _object_points(points: Float[np.ndarray, "num_points 3"], aabb) -> "Float[np.ndarray, 'num_object 3'] | None":
    """The sparse points inside the meshed box (all of them without a box); None when fewer than 20."""
    points = np.asarray(points, dtype=np.float64)
    if aabb is not None:
        lo, hi = aabb.double().cpu().numpy()
        points = points[np.all((points >= lo) & (points <= hi), axis=1)]
    return points if len(points) >= 20 else None


def _peel_fog(mesh: TriangleMesh, cfg: MeshConfig, lines, points, slack: float, figures: dict) -> TriangleMesh:
    """Remove the faces that sight lines cross more than ``slack`` before their point, layer by layer (but
    for those next to a sparse point of the object)."""
    removed, origins, targets = 0, *lines.segments()
    for _ in range(cfg.free_space_passes):
        blocking = faces_blocking_sight_lines(mesh, origins, targets, slack, keep_near=points)
        if not blocking.any() or blocking.all():
            break
        removed += int(blocking.sum())
        mesh = mesh.submesh(~blocking)
    figures.update(free_space_faces_removed=removed, free_space_slack_world=slack)
    return mesh


def _remove_support(mesh: TriangleMesh, cameras: Cameras, points, cfg: MeshConfig, figures: dict, known=None) -> TriangleMesh:
    """Remove the support plane and what lies below it (MeshConfig.support_plane); records the plane. ``known``: the
    plane where the sparse points give it (``MeshConfig.support_from_points``), else it is looked for in the mesh."""
    from nerfpipe.mesh.metrics import sample_surface

    tolerance = cfg.support_tolerance * robust_diagonal(points)
    if known is not None:  # where the object touches it: a floor far under a table holds none of the object's points
        known = np.asarray(known, dtype=np.float64) / np.linalg.norm(np.asarray(known[:3], dtype=np.float64))
        known = known if np.mean(np.abs(points @ known[:3] + known[3]) < tolerance) >= cfg.support_min_points else None
    if known is not None:
        plane = known
    else:
        centers = cameras.centers.double().reshape(-1, 3).cpu().numpy()
        samples, normals = sample_surface(mesh, 20_000)
        candidates, normals = np.concatenate([samples, points]), np.concatenate([normals, np.zeros_like(points)])
        up = upright_direction(cameras.to("cpu")).numpy()
        plane = support_plane(candidates, points, centers, tolerance, normals, min_inliers=cfg.support_min_share, up=up,
                              max_tilt_deg=cfg.support_max_tilt, max_angle_deg=cfg.support_max_angle, min_points=cfg.support_min_points)
    figures.update(support_plane=None if plane is None else plane.tolist(), support_tolerance_world=tolerance,
                   support_plane_from="sparse points" if known is not None else "mesh")
    if plane is None:
        return mesh
    below = faces_on_or_below_plane(mesh, plane, tolerance)
    figures["support_faces_removed"] = int(below.sum())
    if cfg.footprint_margin is not None:
        beside = faces_outside_footprint(mesh, plane, points, tolerance, cfg.footprint_margin * robust_diagonal(points)) & ~below
        figures["footprint_faces_removed"] = int(beside.sum())
        below |= beside
    return mesh if below.all() else mesh.submesh(~below)


def _simplify(mesh: TriangleMesh, target: "int | None", figures: dict) -> TriangleMesh:
    if target is None and mesh.num_faces <= DEFAULT_FACES:
        figures.update(faces_simplified=mesh.num_faces, hausdorff_max=0.0, hausdorff_mean=0.0)
        return mesh
    start = time.perf_counter()
    small = simplify(mesh, DEFAULT_FACES if target is None else target)
    middle = time.perf_counter()
    d = hausdorff_distance(mesh, small)
    figures.update(faces_simplified=small.num_faces, hausdorff_max=d["max"], hausdorff_mean=d["mean"],
                   seconds_quadric=middle - start, seconds_hausdorff=time.perf_counter() - middle)
    return small


def build_meshes(
    cfg: MeshConfig,
    aabb: Float[Tensor, "2 3"],
    density_fn: "DensityFn | None" = None,
    rgb_fn: "RgbFn | None" = None,
    occupancy_fn: "OccupancyFn | None" = None,
    frame_fn: "FrameFn | None" = None,
    cameras: "Cameras | None" = None,
    surface_points: "Float[Tensor, 'num_points 3'] | None" = None,
    surface_origins: "Float[Tensor, 'num_points 3'] | None" = None,
    sight_lines=None,
    support: "Float[np.ndarray, '4'] | None" = None,
    max_faces: "int | None" = None,
) -> MeshOutputs:
    """Extract, clean, colour and simplify, all in the world frame; writes nothing.

    Args:
        cfg: the settings.
        aabb: box to mesh (world frame).
        density_fn: density at points (mc).
        rgb_fn: colour at points seen along directions (mc vertex colours).
        occupancy_fn: skip test for empty space (mc).
        frame_fn: depth and colour per camera index (tsdf).
        cameras: the training cameras (tsdf input; unseen-face removal).
        surface_points: where rendered rays end (mc with ``level_from`` agreement or quantile).
        surface_origins: their ray origins (agreement then uses the rays' median depth in the volume).
        sight_lines: the sparse points' track observations in the world frame
            (:class:`nerfpipe.mesh.reference.SightLines`): support plane and fog removal.
        support: the plane the object stands on where the sparse points give it (world frame, ``a x + b y + c z + d``
            positive on the cameras' side; ``MeshConfig.support_from_points``).
        max_faces: tsdf: at most about this many faces come out of fusion (what follows takes a time about
            proportional to them: a time budget's cap), by coarser voxels, down to the coarsest of
            :data:`BUDGET_RESOLUTIONS` along the box (``tsdf_fuse``); mesh.json's ``resolution`` is the one used.
    """
    if cfg.faces is not None and cfg.faces < 4:
        raise NerfpipeError(f"--faces must be at least 4, got {cfg.faces}")
    figures: dict = {"method": cfg.method}
    t0 = time.perf_counter()
    surface = None if surface_points is None else (surface_points, surface_origins)
    mesh = _extract(cfg, aabb, density_fn, occupancy_fn, frame_fn, cameras, surface, figures, max_faces)
    t1 = time.perf_counter()
    figures["box_world"] = aabb.tolist()
    mesh = _clean(mesh, cfg, cameras, figures, aabb, sight_lines, support)
    steps = cfg.smooth if cfg.smooth is not None else (1 if cfg.method == "tsdf" else 0)
    figures["smooth_steps"] = steps
    if steps > 0:
        start = time.perf_counter()
        mesh = smooth(mesh, steps)
        figures["seconds_smooth"] = time.perf_counter() - start
    if cfg.colors and cfg.method == "mc" and rgb_fn is not None:
        mesh = vertex_colors(mesh, rgb_fn, chunk=cfg.chunk)
    if not cfg.colors:
        mesh.vertex_colors = None
    t2 = time.perf_counter()
    small = _simplify(mesh, cfg.faces, figures)
    t3 = time.perf_counter()
    figures.update(faces=mesh.num_faces, vertices=mesh.num_vertices, seconds_extract=t1 - t0, seconds_clean_color=t2 - t1, seconds_simplify=t3 - t2)
    return MeshOutputs(mesh, small, figures)


def write_meshes(
    out: MeshOutputs, out_dir: "str | Path", world_from_input: Similarity, views: bool = True, seen_from: "np.ndarray | None" = None
) -> "dict[str, Path]":
    """Write the meshes in the input frame (and the picture of the world-frame mesh, +z up, seen from the arc of
    the photographs' centres ``seen_from`` when they do not surround it: :func:`~nerfpipe.mesh.views.orbit_cameras`)."""
    out_dir = Path(out_dir)
    paths = {name: out_dir / name for name in FILES}
    full, small = to_input_frame(out.full, world_from_input), to_input_frame(out.simplified, world_from_input)
    write_ply(full, paths["mesh.ply"])
    write_ply(small, paths["mesh_simplified.ply"])
    if views:
        write_views(out.full, paths["mesh_views.png"], seen_from=seen_from)
    else:
        paths.pop("mesh_views.png")
    record = {**out.figures, "frame": "input", "world_from_input": {"rotation": world_from_input.rotation.tolist(),
              "translation": world_from_input.translation.tolist(), "scale": float(world_from_input.scale)},
              "bounds_input_frame": full.bounds().tolist(), "load": os.getloadavg()[0]}
    if out.figures.get("support_plane") is not None:
        record["support_plane_input_frame"] = plane_in_input_frame(np.asarray(out.figures["support_plane"]), world_from_input).tolist()
    write_json(paths["mesh.json"], record)
    return paths


def plane_in_input_frame(plane: Float[np.ndarray, "4"], world_from_input: Similarity) -> Float[np.ndarray, "4"]:
    """A world-frame plane ``n . x + d = 0`` (unit ``n``) in the input frame, unit normal, same side positive."""
    r, t = world_from_input.rotation.double().numpy(), world_from_input.translation.double().numpy()
    return np.concatenate([r.T @ plane[:3], [(plane[:3] @ t + plane[3]) / world_from_input.scale]])
