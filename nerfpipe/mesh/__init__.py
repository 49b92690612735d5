"""Mesh post-stages: extraction (marching cubes, TSDF), cleaning, simplification, export, metrics.

Everything here takes callables (``density_fn``, ``rgb_fn``, ``frame_fn``) and plain
:class:`TriangleMesh` records, never model classes (STYLE habit 4). Heavy libraries
(scikit-image, pymeshlab, open3d, trimesh) are imported inside the functions that use them.

Glossary:
    world frame   nerfpipe's normalised frame; extraction, cleaning and pictures work here
    input frame   the dataset's own frame; exports are written here (``world_from_input.inverse()``)
    level         the density iso-value of the surface (see :func:`nerfpipe.mesh.extract.auto_level`)
    h             grid spacing (voxel size) of the extraction grid, in world units
"""

from nerfpipe.mesh.clean import close_holes, hausdorff_distance, remove_small_components, simplify, visible_faces
from nerfpipe.mesh.color import vertex_colors
from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.export import read_mesh, to_input_frame, write_ply
from nerfpipe.mesh.extract import auto_level, extract_mesh
from nerfpipe.mesh.metrics import MeshMetrics, compare_meshes, point_fraction
from nerfpipe.mesh.pipeline import MeshConfig, build_meshes, write_meshes
from nerfpipe.mesh.tsdf import tsdf_fuse
from nerfpipe.mesh.views import render_views, write_views

__all__ = [
    "MeshConfig",
    "MeshMetrics",
    "TriangleMesh",
    "auto_level",
    "build_meshes",
    "close_holes",
    "compare_meshes",
    "extract_mesh",
    "hausdorff_distance",
    "point_fraction",
    "read_mesh",
    "remove_small_components",
    "render_views",
    "simplify",
    "to_input_frame",
    "tsdf_fuse",
    "vertex_colors",
    "visible_faces",
    "write_meshes",
    "write_ply",
]
