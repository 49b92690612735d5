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

from nerfpipe.mesh.container import TriangleMesh

__all__ = ["TriangleMesh"]
