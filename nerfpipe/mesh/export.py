"""Writing and reading meshes: PLY export in the dataset's input frame, written atomically.

:func:`to_input_frame` undoes the normalisation an adapter applied
(``SceneData.world_from_input``), so the exported mesh sits on the input's cameras and
points. :func:`write_ply` writes binary little-endian PLY (float xyz, uchar rgb, int faces),
which Open3D, trimesh and MeshLab read.
"""

from pathlib import Path

import numpy as np

from nerfpipe.data.scene import Similarity
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.atomic import write_bytes
from nerfpipe.util.errors import NerfpipeError, require


def to_input_frame(mesh: TriangleMesh, world_from_input: Similarity) -> TriangleMesh:
    """Map a world-frame mesh to the input frame (the inverse of the adapter's normalisation)."""
    out = mesh.transformed(world_from_input.inverse())
    out.info["frame"] = "input"
    return out


def ply_bytes(mesh: TriangleMesh) -> bytes:
    """Binary PLY of the mesh (vertex colours when present), via trimesh's exporter."""
    trimesh = require("trimesh", "mesh")
    return trimesh.exchange.ply.export_ply(mesh.to_trimesh(), encoding="binary", vertex_normal=False, include_attributes=False)


def write_ply(mesh: TriangleMesh, path: "str | Path") -> Path:
    """Write ``mesh`` to ``path`` atomically (nothing half-written on failure)."""
    if mesh.num_faces == 0:
        raise NerfpipeError("refusing to write an empty mesh (no faces)", path)
    write_bytes(path, ply_bytes(mesh))
    return Path(path)


def read_mesh(path: "str | Path") -> TriangleMesh:
    """Read a triangle mesh file (PLY, OBJ, STL, OFF, GLB...) with trimesh."""
    trimesh = require("trimesh", "mesh")
    path = Path(path)
    if not path.is_file():
        raise NerfpipeError("mesh file not found", path)
    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise NerfpipeError(f"cannot read mesh ({type(exc).__name__}: {exc})", path) from exc
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise NerfpipeError("file holds no triangles", path)
    if not np.isfinite(m.vertices).all():
        raise NerfpipeError("mesh has vertices with NaN or Inf coordinates", path)
    if m.faces.min() < 0 or m.faces.max() >= len(m.vertices):
        raise NerfpipeError(f"mesh has faces that index missing vertices (it has {len(m.vertices)})", path)
    colors = None
    if m.visual.kind == "vertex":
        colors = m.visual.vertex_colors[:, :3]
    return TriangleMesh(m.vertices, m.faces, colors)
