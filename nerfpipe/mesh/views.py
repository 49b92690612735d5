"""``mesh_views.png``: a mesh ray-cast from four views, shaded and coloured, no window needed.

Row 1 is Lambert shading of the face normals (shape only); row 2 is the vertex colours
(interpolated over each triangle) times the same shading, or a normal map when the mesh
has no colours. Back faces seen through holes are tinted red so holes and flipped faces show.
Rendering uses Open3D's ``RaycastingScene`` (CPU, headless).
"""

import math
from pathlib import Path

import numpy as np
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.orbit import covered_arc
from nerfpipe.data.rays import camera_rays
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.atomic import write_bytes
from nerfpipe.util.errors import require
from nerfpipe.util.typing import Float

BACKGROUND = 1.0
BACKFACE_TINT = np.array([1.0, 0.45, 0.45])


def look_at(eye: Float[np.ndarray, "3"], target: Float[np.ndarray, "3"], up: Float[np.ndarray, "3"]) -> Float[np.ndarray, "4 4"]:
    """``world_from_cam`` (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    f = target - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    r = r / max(np.linalg.norm(r), 1e-12)
    d = np.cross(f, r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, d, f, eye
    return m


def orbit_cameras(
    mesh: TriangleMesh, up=(0.0, 0.0, 1.0), size: int = 360, count: int = 4, elevation_deg: float = 25.0, fov_deg: float = 40.0,
    seen_from: "np.ndarray | None" = None,
) -> Cameras:
    """``count`` cameras around the mesh's bounding box, framing it whole: all round, or spread over the arc
    that the photographs' centres ``seen_from`` (``[N, 3]``) cover when they leave a wide gap
    (:func:`nerfpipe.data.orbit.covered_arc`: a facade or a wall-mounted object is not shown from behind)."""
    lo, hi = mesh.bounds()
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    side = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    side /= np.linalg.norm(side)
    dist = 1.05 * radius / math.sin(math.radians(fov_deg) / 2)
    el = math.radians(elevation_deg)
    start, span = 2 * math.pi * 0.125 / count, 2 * math.pi
    if seen_from is not None and len(seen_from):
        rel = np.asarray(seen_from, dtype=np.float64).reshape(-1, 3) - centre
        arc_start, arc_span = covered_arc(torch.from_numpy(np.arctan2(rel @ np.cross(up, side), rel @ side)))
        if arc_span < 2 * math.pi:
            start, span = arc_start + arc_span / (2 * count), arc_span
    mats = []
    for k in range(count):
        az = start + span * k / count
        horiz = math.cos(az) * side + math.sin(az) * np.cross(up, side)
        mats.append(look_at(centre + dist * (math.cos(el) * horiz + math.sin(el) * up), centre, up))
    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    return Cameras.create(np.stack(mats), f, f, size / 2, size / 2, size, size, dtype=torch.float64)


def _shade(mesh: TriangleMesh, hit: dict, dirs: np.ndarray, light: np.ndarray):
    """Shaded grey and coloured images of one camera's hits."""
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    ok = np.isfinite(hit["t_hit"].numpy())
    n = mesh.face_normals()[np.where(ok, prim, 0)]
    back = np.sum(n * dirs, axis=-1) > 0
    n = np.where(back[..., None], -n, n)
    lam = 0.25 + 0.75 * np.clip(np.sum(n * light, axis=-1), 0, 1)
    grey = lam[..., None] * np.where(back[..., None], BACKFACE_TINT, 0.85)
    if mesh.vertex_colors is None:
        col = 0.5 + 0.5 * n
    else:
        uv = hit["primitive_uvs"].numpy()
        vc = mesh.vertex_colors.astype(np.float64)[mesh.faces[np.where(ok, prim, 0)]] / 255.0
        col = (1 - uv[..., :1] - uv[..., 1:]) * vc[..., 0, :] + uv[..., :1] * vc[..., 1, :] + uv[..., 1:] * vc[..., 2, :]
        col = col * (0.45 + 0.55 * lam[..., None])
    bg = np.full_like(grey, BACKGROUND)
    return np.where(ok[..., None], grey, bg), np.where(ok[..., None], col, bg)


def render_views(mesh: TriangleMesh, up=(0.0, 0.0, 1.0), size: int = 360, seen_from: "np.ndarray | None" = None) -> Float[np.ndarray, "H W 3"]:
    """A ``2 x 4`` grid (shaded row, coloured row) as float RGB in [0, 1], from :func:`orbit_cameras`."""
    o3d = require("open3d", "mesh")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh.to_open3d_tensor())
    cams = orbit_cameras(mesh, up, size, seen_from=seen_from)
    rows = [[], []]
    for i in range(len(cams)):
        rays = camera_rays(cams, i)
        dirs = rays.directions.numpy()
        hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([rays.origins.numpy(), dirs], -1).astype(np.float32)))
        cam = cams.world_from_cam[i].numpy()
        light = -cam[:3, 2] * 0.8 - cam[:3, 1] * 0.5 - cam[:3, 0] * 0.3  # from the viewer, above, left
        grey, col = _shade(mesh, hit, dirs, light / np.linalg.norm(light))
        rows[0].append(grey)
        rows[1].append(col)
    return np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)


def write_views(mesh: TriangleMesh, path: "str | Path", up=(0.0, 0.0, 1.0), size: int = 360, seen_from: "np.ndarray | None" = None) -> Path:
    """Render :func:`render_views` and write it as PNG atomically."""
    import imageio.v3 as iio

    img = (np.clip(render_views(mesh, up, size, seen_from), 0, 1) * 255 + 0.5).astype(np.uint8)
    write_bytes(path, iio.imwrite("<bytes>", img, extension=".png"))
    return Path(path)
