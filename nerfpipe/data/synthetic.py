"""Synthetic scenes with known geometry: coloured meshes ray-cast into COLMAP or Blender datasets.

The scenes are the project's embedded default data (no download, a few seconds to generate)
and the ground truth for mesh extraction: the exact mesh is saved beside the images, in the
same frame as the cameras.

Glossary:
    input frame   the world coordinates written to disk (+z up, object inside about [-1, 1]^3)
    part          one primitive of a scene (box, sphere, torus), with its own colours
    bary          barycentric weights ``(w0, w1, w2)`` of a hit inside its triangle
    depth         distance along the (unit) ray to the first hit; ``inf`` on background
    track         the views in which a sampled surface point is visible, with its pixels

Rendering is view-independent Lambertian shading (fixed directional light plus ambient) of
barycentrically interpolated vertex colours. Rays come from :func:`nerfpipe.data.rays.camera_rays`,
so pixel-centre and axis conventions are the ones of :class:`~nerfpipe.data.cameras.Cameras`.

Example:
    >>> from nerfpipe.data.synthetic import SynthConfig, generate
    >>> generate("/tmp/synth", SynthConfig(views=8, width=32, height=32))  # doctest: +SKIP
"""

import json
import math
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras, opengl_to_opencv
from nerfpipe.data.rays import camera_rays
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.util.paths import check_output_folder
from nerfpipe.util.typing import Bool, Float, Int, Tensor

SceneName = Literal["composite", "sphere", "room"]
Layout = Literal["colmap", "blender"]

LIGHT_DIR = (0.35, -0.45, 0.82)
"""Direction towards the light, in the input frame (normalised when used)."""
AMBIENT = 0.35
"""Share of light that reaches every surface regardless of its normal."""
BLENDER_CAMERA_ANGLE_X = 0.6911112070083618
"""Horizontal field of view of the Blender synthetic scenes, in radians."""
SPHERE_RADIUS = 0.8
"""Radius of the ``sphere`` scene (centred at the origin)."""
COMPOSITE_SCALE = 1.3
"""Scale of the composite object (fills about 60 % of the default views)."""

ROOM_HALF_WIDTH = 6.0
"""The ``room`` scene's walls stand this far from the origin along x and y."""
ROOM_HEIGHT = 5.0
"""Floor to ceiling of the ``room`` scene; its floor carries the composite object's plinth."""
ROOM_FLOOR = -0.7 * COMPOSITE_SCALE
"""Height of the ``room`` scene's floor: the plinth's underside."""
ROOM_ELEVATIONS = (10.0, 60.0)
"""Camera elevations in degrees that ``nerfpipe synth --scene room`` uses by default (above the floor, below the ceiling)."""
SCENE_FILE = "scene.json"
MESH_FILE = "gt_mesh.ply"
MAX_VIEWS = 2000
"""Most cameras a synthetic scene may have (more is a typo, not a test scene)."""
MAX_PIXELS = 200_000_000
"""Most pixels of all views together: every ray is cast at once, about 100 bytes per pixel."""
SPLIT_PERIOD = 8
"""Views ``i % 8 == 0`` go to the test split and ``i % 8 == 4`` to val (Blender layout)."""


@dataclass
class SynthConfig:
    """A synthetic scene: which object, how many views, how large, which layout."""

    scene: SceneName = "composite"
    """Object: ``composite`` (box + sphere + torus, patterned), ``sphere`` (analytic tests) or ``room`` (the composite
    standing on the patterned floor of a closed room, as a real capture shows an object in its surroundings: every
    ray hits something; ``gt_mesh.ply`` and the mesh figures hold the object alone; cameras above the floor)."""
    layout: Layout = "colmap"
    """``colmap``: images/ + sparse/0 (white background); ``blender``: transforms_*.json + RGBA."""
    views: int = 48
    """Number of cameras (all splits together)."""
    width: int = 128
    """Image width in pixels."""
    height: int = 128
    """Image height in pixels."""
    seed: int = 0
    """Seed of camera azimuths, colour-pattern phases and sparse-point sampling."""
    camera_angle_x: float = BLENDER_CAMERA_ANGLE_X
    """Horizontal field of view in radians (the Blender scenes' value)."""
    distance: float = 4.0
    """Camera distance from the origin, in scene units."""
    min_elevation_deg: float = -25.0
    """Lowest camera elevation (negative: some views from below)."""
    max_elevation_deg: float = 75.0
    """Highest camera elevation."""
    num_points: int = 4000
    """Surface samples tried for the COLMAP sparse points (visible ones are kept)."""
    min_track_length: int = 3
    """A sparse point is kept when it is visible in at least this many views."""
    background: "tuple[float, float, float]" = (1.0, 1.0, 1.0)
    """Background colour of the COLMAP layout (the Blender layout is transparent)."""
    save_depth: bool = False
    """Also write ``depth/<name>.npy`` (float32 distance along the ray, 0 on background)."""

    def __post_init__(self) -> None:
        if not 2 <= self.views <= MAX_VIEWS:
            raise NerfpipeError(f"need at least 2 views and at most {MAX_VIEWS}, got {self.views}")
        if self.width < 4 or self.height < 4:
            raise NerfpipeError(f"image size {self.width}x{self.height} is too small (min 4x4)")
        if self.views * self.width * self.height > MAX_PIXELS:
            raise NerfpipeError(f"{self.views} views of {self.width}x{self.height} exceed {MAX_PIXELS:,} pixels in all (ray casting holds them in memory)")
        if not -90 < self.min_elevation_deg <= self.max_elevation_deg < 90:
            raise NerfpipeError("elevations must satisfy -90 < min <= max < 90 degrees")
        if self.scene == "room":
            lowest, highest = (self.distance * math.sin(math.radians(e)) for e in (self.min_elevation_deg, self.max_elevation_deg))
            if lowest <= ROOM_FLOOR + 0.1 or highest >= ROOM_FLOOR + ROOM_HEIGHT - 0.1 or self.distance >= ROOM_HALF_WIDTH - 0.1:
                raise NerfpipeError(f"the room scene's cameras must stay inside its room (elevations {self.min_elevation_deg:g} to "
                                    f"{self.max_elevation_deg:g} degrees at distance {self.distance:g}: e.g. 10 to 60 at 4)")


@dataclass
class SynthMesh:
    """A triangle mesh with per-vertex colours and a shading mode per face."""

    vertices: Float[np.ndarray, "num_verts 3"]
    faces: Int[np.ndarray, "num_faces 3"]
    colors: Float[np.ndarray, "num_verts 3"]
    """Vertex colours (albedo) in [0, 1]."""
    vertex_normals: Float[np.ndarray, "num_verts 3"]
    face_normals: Float[np.ndarray, "num_faces 3"]
    smooth: Bool[np.ndarray, "num_faces"]
    """True: interpolate vertex normals (curved parts); False: flat face normal (box)."""
    object_faces: "int | None" = None
    """Faces ``[0, object_faces)`` are the object, the rest its surroundings (``gt_mesh.ply`` holds the object alone);
    None: every face is the object."""

    def object_part(self) -> "SynthMesh":
        """The object alone (its faces and the vertices they use: the object's vertices come first)."""
        if self.object_faces is None:
            return self
        faces = self.faces[: self.object_faces]
        n = int(faces.max()) + 1
        return SynthMesh(self.vertices[:n], faces, self.colors[:n], self.vertex_normals[:n], self.face_normals[: self.object_faces],
                         self.smooth[: self.object_faces])

    def surroundings_part(self) -> "SynthMesh | None":
        """The surroundings alone (None without)."""
        if self.object_faces is None:
            return None
        faces = self.faces[self.object_faces :]
        n = int(faces.min())
        return SynthMesh(self.vertices[n:], faces - n, self.colors[n:], self.vertex_normals[n:], self.face_normals[self.object_faces :],
                         self.smooth[self.object_faces :])

    def bounds(self) -> Float[np.ndarray, "2 3"]:
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    def to_trimesh(self):
        trimesh = require("trimesh", "mesh")
        rgba = np.concatenate([self.colors, np.ones_like(self.colors[:, :1])], axis=1)
        colors = np.round(rgba * 255).astype(np.uint8)
        return trimesh.Trimesh(self.vertices, self.faces, vertex_colors=colors, process=False)


@dataclass
class View:
    """One ray-cast image."""

    rgb: Float[np.ndarray, "H W 3"]
    """Shaded colour in [0, 1] (0 on background)."""
    alpha: Bool[np.ndarray, "H W"]
    """Hit mask."""
    depth: Float[np.ndarray, "H W"]
    """Distance along the unit ray to the surface; ``inf`` on background."""


# ---------------------------------------------------------------------------- scenes
def _pattern(
    points: Float[np.ndarray, "num_points 3"], period: float, phase: Float[np.ndarray, "3"]
) -> Float[np.ndarray, "num_points"]:
    """Smooth plaid in [0, 1]: varies along every planar face and over curved parts."""
    k = 2 * math.pi / period
    return 0.5 + np.sin(k * points + phase).sum(-1) / 6


def _part(mesh, base, accent, period: float, smooth: bool, rng: np.random.Generator) -> dict:
    """A trimesh primitive -> arrays of one part, coloured ``mix(base, accent, pattern)``."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    w = _pattern(v, period, rng.uniform(0, 2 * math.pi, 3))[:, None]
    colors = (1 - w) * np.asarray(base) + w * np.asarray(accent)
    return dict(
        vertices=v,
        faces=np.asarray(mesh.faces, dtype=np.int64),
        colors=colors,
        vertex_normals=np.asarray(mesh.vertex_normals, dtype=np.float64),
        face_normals=np.asarray(mesh.face_normals, dtype=np.float64),
        smooth=np.full(len(mesh.faces), smooth),
    )


def _merge(parts: "list[dict]") -> SynthMesh:
    offsets = np.cumsum([0] + [len(p["vertices"]) for p in parts[:-1]])
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "faces"}
    out["faces"] = np.concatenate([p["faces"] + o for p, o in zip(parts, offsets)])
    return SynthMesh(**out)


def composite_scene(seed: int = 0) -> SynthMesh:
    """A box (plinth) carrying a sphere and an upright torus; the parts do not touch.

    Before the final scaling by :data:`COMPOSITE_SCALE`, the box spans z in [-0.7, -0.2]; the
    sphere (r 0.4) and the torus (ring in the y-z plane) float 0.02 above it, so the union is
    three disjoint closed surfaces (genus 0, 0 and 1) inside [-0.94, 0.94]^3.
    """
    trimesh = require("trimesh", "mesh")
    rng = np.random.default_rng(seed)
    box = trimesh.creation.box(extents=(1.2, 0.9, 0.5))
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.04)
    box = trimesh.Trimesh(v + [0.0, 0.0, -0.45], f, process=False)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.4)
    sphere.apply_translation([0.25, 0.0, 0.22])
    torus = trimesh.creation.torus(major_radius=0.34, minor_radius=0.11, major_sections=96, minor_sections=32)
    torus.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))
    torus.apply_translation([-0.42, 0.0, 0.27])
    mesh = _merge([
        _part(box, (0.12, 0.30, 0.80), (0.95, 0.80, 0.25), 0.3, False, rng),
        _part(sphere, (0.85, 0.12, 0.12), (0.98, 0.95, 0.90), 0.22, True, rng),
        _part(torus, (0.10, 0.65, 0.30), (0.05, 0.15, 0.10), 0.15, True, rng),
    ])
    mesh.vertices *= COMPOSITE_SCALE
    return mesh


def sphere_scene(seed: int = 0) -> SynthMesh:
    """A fine icosphere of radius :data:`SPHERE_RADIUS` at the origin (sub-1e-3 faceting)."""
    trimesh = require("trimesh", "mesh")
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS)
    return _merge([_part(sphere, (0.8, 0.2, 0.2), (0.9, 0.9, 0.3), 0.3, True, np.random.default_rng(seed))])


def room_scene(seed: int = 0) -> SynthMesh:
    """The composite object standing on the floor of a closed room (walls :data:`ROOM_HALF_WIDTH` from the origin,
    :data:`ROOM_HEIGHT` high, faces inward), floor and walls patterned in their own colours and periods: what a real
    capture of an object shows around it. The object's faces come first (:attr:`SynthMesh.object_faces`), less its
    plinth's underside, which stands on the floor: no photograph can see it, so the ground truth leaves it out."""
    trimesh = require("trimesh", "mesh")
    rng = np.random.default_rng(seed + 1)  # the surroundings' own phases; the object is composite_scene(seed)
    obj = composite_scene(seed)
    seen = ~(np.abs(obj.vertices[obj.faces][..., 2] - ROOM_FLOOR) < 1e-9).all(-1)  # the plinth's underside lies on the floor
    obj.faces, obj.face_normals, obj.smooth = obj.faces[seen], obj.face_normals[seen], obj.smooth[seen]
    w, h = 2 * ROOM_HALF_WIDTH, ROOM_HEIGHT
    room = trimesh.creation.box(extents=(w, w, h))
    room.invert()  # normals into the room
    v, f = trimesh.remesh.subdivide_to_size(room.vertices, room.faces, max_edge=0.12)
    room = trimesh.Trimesh(v + [0.0, 0.0, ROOM_FLOOR + h / 2], f, process=False)
    walls = _part(room, (0.55, 0.50, 0.42), (0.85, 0.82, 0.74), 0.9, False, rng)
    on_floor = np.abs(walls["vertices"][:, 2] - ROOM_FLOOR) < 1e-6
    floor = (1 - _pattern(walls["vertices"], 0.35, rng.uniform(0, 2 * math.pi, 3)))[:, None]
    walls["colors"] = np.where(on_floor[:, None], 0.35 + 0.45 * floor * np.asarray((0.95, 0.75, 0.55)), walls["colors"])
    parts = [{k: getattr(obj, k) for k in ("vertices", "faces", "colors", "vertex_normals", "face_normals", "smooth")}, walls]
    mesh = _merge(parts)
    mesh.object_faces = len(obj.faces)
    return mesh


SCENES = {"composite": composite_scene, "sphere": sphere_scene, "room": room_scene}


# ---------------------------------------------------------------------------- cameras
def look_at(
    centers: Float[Tensor, "*bs 3"], target: Float[Tensor, "3"], up: Float[Tensor, "3"]
) -> Float[Tensor, "*bs 4 4"]:
    """OpenCV ``world_from_cam`` of cameras at ``centers`` looking at ``target``, image up ~ ``up``."""
    z = torch.nn.functional.normalize(target - centers, dim=-1)
    x = torch.nn.functional.normalize(torch.linalg.cross(z, up.expand_as(z)), dim=-1)
    y = torch.linalg.cross(z, x)
    out = torch.zeros(*centers.shape[:-1], 4, 4, dtype=centers.dtype)
    out[..., :3, 0], out[..., :3, 1], out[..., :3, 2], out[..., :3, 3] = x, y, z, centers
    out[..., 3, 3] = 1
    return out


def orbit_cameras(cfg: SynthConfig) -> Cameras:
    """``cfg.views`` pinhole cameras spread evenly (Fibonacci) over a band of the sphere.

    The band spans elevations ``[min_elevation_deg, max_elevation_deg]``; the seed rotates the
    azimuths. Cameras look at the origin with +z up (upright images). Float64.
    """
    n = cfg.views
    s_lo, s_hi = (math.sin(math.radians(e)) for e in (cfg.min_elevation_deg, cfg.max_elevation_deg))
    z = s_hi - (torch.arange(n, dtype=torch.float64) + 0.5) / n * (s_hi - s_lo)
    offset = float(np.random.default_rng(cfg.seed).uniform(0, 2 * math.pi))
    azimuth = offset + torch.arange(n, dtype=torch.float64) * math.pi * (3 - math.sqrt(5))
    r = torch.sqrt(1 - z**2)
    centers = cfg.distance * torch.stack([r * torch.cos(azimuth), r * torch.sin(azimuth), z], dim=-1)
    zero, up = torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    focal = 0.5 * cfg.width / math.tan(0.5 * cfg.camera_angle_x)
    world_from_cam = look_at(centers, zero, up)
    cx, cy = cfg.width / 2, cfg.height / 2
    return Cameras.create(world_from_cam, focal, focal, cx, cy, cfg.width, cfg.height, dtype=torch.float64)


# ---------------------------------------------------------------------------- rendering
def raycaster(mesh: SynthMesh):
    """An Open3D ``RaycastingScene`` holding ``mesh`` (geometry id 0)."""
    o3d = require("open3d", "mesh")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32))
    )
    return scene


def cast(scene, origins: Float[np.ndarray, "num_points 3"], directions: Float[np.ndarray, "num_points 3"]):
    """First hits: ``(t, face_id, bary)``; ``t = inf`` and ``face_id = -1`` on a miss."""
    o3d = require("open3d", "mesh")
    rays = np.concatenate([origins, directions], axis=-1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64)
    face = hit["primitive_ids"].numpy().astype(np.int64)
    uv = hit["primitive_uvs"].numpy().astype(np.float64)
    face[~np.isfinite(t)] = -1
    bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=-1)
    return t, face, bary


def shade(
    mesh: SynthMesh, face: Int[np.ndarray, "num_points"], bary: Float[np.ndarray, "num_points 3"]
) -> Float[np.ndarray, "num_points 3"]:
    """Lambertian colour of surface points given by triangle and barycentric weights."""
    tri = mesh.faces[face]
    albedo = (mesh.colors[tri] * bary[..., None]).sum(1)
    smooth_n = (mesh.vertex_normals[tri] * bary[..., None]).sum(1)
    normal = np.where(mesh.smooth[face, None], smooth_n, mesh.face_normals[face])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    light = np.asarray(LIGHT_DIR) / np.linalg.norm(LIGHT_DIR)
    lambert = np.clip(normal @ light, 0, None)
    return np.clip(albedo * (AMBIENT + (1 - AMBIENT) * lambert)[:, None], 0, 1)


def render_view(scene, mesh: SynthMesh, cameras: Cameras, index: int) -> View:
    """Ray-cast camera ``index``: rays through pixel centres from :func:`camera_rays`."""
    rays = camera_rays(cameras, index)
    h, w = rays.shape
    t, face, bary = cast(scene, rays.origins.reshape(-1, 3).numpy(), rays.directions.reshape(-1, 3).numpy())
    hit = face >= 0
    rgb = np.zeros((h * w, 3))
    rgb[hit] = shade(mesh, face[hit], bary[hit])
    return View(rgb=rgb.reshape(h, w, 3), alpha=hit.reshape(h, w), depth=t.reshape(h, w))


def to_uint8(view: View, background: "tuple[float, float, float] | None") -> np.ndarray:
    """RGBA uint8 (``background=None``) or RGB composited over a constant background."""
    if background is None:
        rgba = np.concatenate([view.rgb, view.alpha[..., None].astype(np.float64)], axis=-1)
        return np.round(rgba * 255).astype(np.uint8)
    rgb = np.where(view.alpha[..., None], view.rgb, np.asarray(background, dtype=np.float64))
    return np.round(rgb * 255).astype(np.uint8)


# ---------------------------------------------------------------------------- sparse points
@dataclass
class SparsePoints:
    """Surface points with their tracks, for COLMAP's points3D."""

    xyz: Float[np.ndarray, "num_points 3"]
    rgb: Float[np.ndarray, "num_points 3"]
    visible: Bool[np.ndarray, "num_points num_cams"]
    """Point ``p`` is seen by view ``v`` (inside the image, not occluded)."""
    uv: Float[np.ndarray, "num_points num_cams 2"]
    """Pixel coordinates of every point in every view (valid where ``visible``)."""


def sample_points(scene, mesh: SynthMesh, cameras: Cameras, cfg: SynthConfig) -> SparsePoints:
    """Sample the surface uniformly by area; keep points seen unoccluded in ``min_track_length`` views."""
    trimesh = require("trimesh", "mesh")
    xyz, face = trimesh.sample.sample_surface(mesh.object_part().to_trimesh(), cfg.num_points, seed=cfg.seed)
    if mesh.object_faces is not None:  # as many tries on what the photographs show of the far larger surroundings
        xyz2, face2 = _seen_surroundings(scene, mesh, cameras, cfg.num_points, np.random.default_rng(cfg.seed + 1))
        xyz, face = np.concatenate([xyz, xyz2]), np.concatenate([face, face2])
    tri = mesh.vertices[mesh.faces[face]]
    bary = trimesh.triangles.points_to_barycentric(tri, xyz)
    rgb = shade(mesh, np.asarray(face, dtype=np.int64), bary)
    visible, uv = _visibility(scene, torch.from_numpy(np.asarray(xyz, dtype=np.float64)), cameras)
    keep = visible.sum(1) >= cfg.min_track_length
    return SparsePoints(xyz=np.asarray(xyz)[keep], rgb=rgb[keep], visible=visible[keep], uv=uv[keep])


def _seen_surroundings(scene, mesh: SynthMesh, cameras: Cameras, n: int, rng: np.random.Generator):
    """Points of the surroundings where ``n`` random pixels of random views first hit them (as SfM finds keypoints in
    what photographs show), with their faces."""
    from nerfpipe.data.rays import generate_rays

    cam = torch.from_numpy(rng.integers(0, len(cameras), n))
    uv = torch.from_numpy(rng.uniform(0, 1, (n, 2))) * torch.stack([cameras.width[cam], cameras.height[cam]], -1)
    rays = generate_rays(cameras, cam, uv)
    o, d = rays.origins.numpy(), rays.directions.numpy()
    t, face, _ = cast(scene, o, d)
    keep = face >= mesh.object_faces
    return (o + t[:, None] * d)[keep], face[keep]


def _visibility(scene, xyz: Float[Tensor, "num_points 3"], cameras: Cameras):
    """Which views see each point: projected inside the image and first hit along the ray."""
    n_pts, n_cams = len(xyz), len(cameras)
    cams = cameras[torch.arange(n_cams).repeat_interleave(n_pts)]
    pts = xyz.repeat(n_cams, 1)
    uv, z = cams.project(pts)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cams.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cams.height)
    offset = pts - cams.centers
    dist = offset.norm(dim=-1)
    t, _, _ = cast(scene, cams.centers.numpy(), (offset / dist[:, None]).numpy())
    unoccluded = np.abs(t - dist.numpy()) < 1e-3 * dist.numpy()
    visible = (inside.numpy() & unoccluded).reshape(n_cams, n_pts).T
    return visible, uv.numpy().reshape(n_cams, n_pts, 2).transpose(1, 0, 2)


# ---------------------------------------------------------------------------- layouts
def view_name(i: int) -> str:
    return f"view_{i:03d}"


def view_splits(n: int) -> "dict[str, list[int]]":
    """Deterministic train/val/test split of ``n`` views (see :data:`SPLIT_PERIOD`)."""
    idx = list(range(n))
    test = [i for i in idx if i % SPLIT_PERIOD == 0]
    val = [i for i in idx if i % SPLIT_PERIOD == SPLIT_PERIOD // 2]
    return {"train": [i for i in idx if i not in test and i not in val], "val": val, "test": test}


def _write_png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, img, extension=".png")


def write_blender(out: Path, cameras: Cameras, views: "list[View]", cfg: SynthConfig) -> None:
    """``transforms_{train,val,test}.json`` (OpenGL camera-to-world) + RGBA PNGs per split."""
    world_from_cam_gl = opengl_to_opencv(cameras.world_from_cam)  # the flip is its own inverse
    for split, idx in view_splits(len(views)).items():
        frames = []
        for i in idx:
            _write_png(out / split / f"{view_name(i)}.png", to_uint8(views[i], None))
            frames.append({"file_path": f"./{split}/{view_name(i)}", "rotation": 0.0,
                           "transform_matrix": world_from_cam_gl[i].tolist()})
        doc = {"camera_angle_x": cfg.camera_angle_x, "frames": frames}
        (out / f"transforms_{split}.json").write_text(json.dumps(doc, indent=2))


def write_colmap(out: Path, cameras: Cameras, views: "list[View]", points: SparsePoints, cfg: SynthConfig) -> None:
    """``images/*.png`` (on the background colour) + ``sparse/0`` binary model via pycolmap."""
    for i, view in enumerate(views):
        _write_png(out / "images" / f"{view_name(i)}.png", to_uint8(view, cfg.background))
    rec = colmap_reconstruction(cameras, points)
    (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    rec.write(str(out / "sparse" / "0"))


def colmap_reconstruction(cameras: Cameras, points: SparsePoints):
    """A ``pycolmap.Reconstruction``: PINHOLE cameras (shared when equal), trivial rigs/frames, tracks."""
    pycolmap = require("pycolmap", "colmap")
    rec = pycolmap.Reconstruction()
    _add_images(rec, cameras, points)
    point2d_idx = np.cumsum(points.visible, axis=0) - 1  # index of each observation in its image
    for p in range(len(points.xyz)):
        track = pycolmap.Track()
        for v in np.flatnonzero(points.visible[p]):
            track.add_element(int(v) + 1, int(point2d_idx[p, v]))
        rgb = np.round(points.rgb[p] * 255).astype(np.uint8)
        rec.add_point3D(points.xyz[p].astype(np.float64), track, rgb)
    rec.update_point_3d_errors()
    return rec


def _add_images(rec, cameras: Cameras, points: SparsePoints) -> None:
    """Image ``v`` gets id ``v + 1`` and keypoints = the observations of the points it sees."""
    pycolmap = require("pycolmap", "colmap")
    cam_from_world = cameras.cam_from_world.numpy()
    camera_ids: "dict[tuple, int]" = {}
    for v in range(len(cameras)):
        intr = tuple(float(getattr(cameras, k)[v]) for k in ("fx", "fy", "cx", "cy", "width", "height"))
        if intr not in camera_ids:
            camera_ids[intr] = len(camera_ids) + 1
            cam = pycolmap.Camera.create_from_model_name(camera_ids[intr], "PINHOLE", 1.0, int(intr[4]), int(intr[5]))
            cam.params = list(intr[:4])
            rec.add_camera_with_trivial_rig(cam)
        keypoints = points.uv[points.visible[:, v], v].astype(np.float64).reshape(-1, 2)
        name = f"{view_name(v)}.png"
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=camera_ids[intr], image_id=v + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world[v, :3, :3]), cam_from_world[v, :3, 3])
        rec.add_image_with_trivial_frame(image, pose)


# ---------------------------------------------------------------------------- top level
@dataclass
class SynthResult:
    """What :func:`generate` produced."""

    path: Path
    cameras: Cameras
    """The cameras used, in the input frame (float64)."""
    mesh: SynthMesh
    num_points: int = 0
    meta: dict = field(default_factory=dict)


def render_all(cfg: SynthConfig):
    """Build the scene, its cameras and every view: ``(mesh, cameras, views, raycaster)``."""
    mesh = SCENES[cfg.scene](cfg.seed)
    cameras = orbit_cameras(cfg)
    scene = raycaster(mesh)
    views = [render_view(scene, mesh, cameras, i) for i in range(len(cameras))]
    return mesh, cameras, views, scene


def scene_record(cfg: SynthConfig, mesh: SynthMesh, num_points: int) -> dict:
    obj = mesh.object_part()  # what gt_mesh.ply holds
    return {
        "generator": "nerfpipe synth",
        "config": asdict(cfg),
        "frame": "input frame: +z up, cameras look at the origin; OpenCV axes in COLMAP, OpenGL in transforms",
        "mesh": MESH_FILE,
        "bbox": obj.bounds().tolist(),
        "num_vertices": int(len(obj.vertices)),
        "num_faces": int(len(obj.faces)),
        "num_points3D": num_points,
        "splits": view_splits(cfg.views),
        "light_dir": list(LIGHT_DIR),
        "ambient": AMBIENT,
    }


def generate(out: "str | Path", cfg: SynthConfig, overwrite: bool = False) -> SynthResult:
    """Render a synthetic scene into the folder ``out`` (built in a temp folder, then moved).

    Raises:
        NerfpipeError: ``out`` exists and is not empty (and not a previous synthetic scene
            with ``overwrite``).
    """
    out = Path(out)
    _check_target(out, overwrite)
    mesh, cameras, views, scene = render_all(cfg)
    points = sample_points(scene, mesh, cameras, cfg) if cfg.layout == "colmap" else None
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        _write_layout(tmp, cameras, views, points, cfg)
        mesh.object_part().to_trimesh().export(tmp / MESH_FILE)
        record = scene_record(cfg, mesh, 0 if points is None else len(points.xyz))
        (tmp / SCENE_FILE).write_text(json.dumps(record, indent=2))
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return SynthResult(out, cameras, mesh, record["num_points3D"], record)


def _write_layout(tmp: Path, cameras: Cameras, views: "list[View]", points, cfg: SynthConfig) -> None:
    if cfg.layout == "blender":
        write_blender(tmp, cameras, views, cfg)
    else:
        write_colmap(tmp, cameras, views, points, cfg)
    if cfg.save_depth:
        for i, v in enumerate(views):
            (tmp / "depth").mkdir(exist_ok=True)
            np.save(tmp / "depth" / f"{view_name(i)}.npy", np.where(v.alpha, v.depth, 0).astype(np.float32))


def _check_target(out: Path, overwrite: bool) -> None:
    check_output_folder(out)
    if not out.exists() or (out.is_dir() and not any(out.iterdir())):
        return
    if not out.is_dir():
        raise NerfpipeError("output exists and is not a folder", out)
    if not overwrite:
        raise NerfpipeError("output folder is not empty (pass --overwrite to replace a synthetic scene)", out)
    if not (out / SCENE_FILE).is_file():
        raise NerfpipeError(f"refusing to replace a folder without {SCENE_FILE} (not a synthetic scene)", out)


def load_gt_mesh(path: "str | Path"):
    """The ground-truth mesh of a generated scene (``trimesh.Trimesh``, input frame)."""
    trimesh = require("trimesh", "mesh")
    path = Path(path)
    mesh_path = path / MESH_FILE if path.is_dir() else path
    if not mesh_path.is_file():
        raise NerfpipeError(f"no {MESH_FILE} here (not a synthetic scene?)", path)
    return trimesh.load(mesh_path, process=False)
