""":class:`TriangleMesh`, the plain mesh record passed between the mesh stages.

Vertices and faces are numpy arrays (meshes leave torch at marching cubes); conversions to
trimesh, Open3D and pymeshlab objects are done lazily, on demand.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from nerfpipe.data.scene import Similarity
from nerfpipe.util.typing import Float, Int, Shaped


@dataclass
class TriangleMesh:
    """A triangle mesh with optional per-vertex colours, in one named frame."""

    vertices: Float[np.ndarray, "num_verts 3"]
    """Vertex positions (float64)."""
    faces: Int[np.ndarray, "num_faces 3"]
    """Vertex indices per triangle (int64), counter-clockwise seen from outside."""
    vertex_colors: "Shaped[np.ndarray, 'num_verts 3'] | None" = None
    """Per-vertex RGB as uint8, or ``None``."""
    info: dict = field(default_factory=dict)
    """Provenance figures (level, voxel size, face counts, ...), reported in mesh.json."""

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if self.vertex_colors is not None:
            self.vertex_colors = np.asarray(self.vertex_colors, dtype=np.uint8).reshape(-1, 3)

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def bounds(self) -> Float[np.ndarray, "2 3"]:
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    def diagonal(self) -> float:
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def face_normals(self) -> Float[np.ndarray, "num_faces 3"]:
        """Unit face normals (zero for degenerate faces)."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.maximum(norm, 1e-30)

    def vertex_normals(self) -> Float[np.ndarray, "num_verts 3"]:
        """Area-weighted unit vertex normals."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        out = np.zeros_like(self.vertices)
        for k in range(3):
            np.add.at(out, self.faces[:, k], n)
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-30)

    def transformed(self, sim: Similarity) -> "TriangleMesh":
        """Apply a similarity to the vertices; a reflection would flip the winding, so it is undone."""
        r = sim.rotation.double().numpy()
        verts = sim.scale * self.vertices @ r.T + sim.translation.double().numpy()
        faces = self.faces if np.linalg.det(r) > 0 else self.faces[:, ::-1].copy()
        return replace(self, vertices=verts, faces=faces, info=dict(self.info))

    def canonical(self) -> "TriangleMesh":
        """The same surface with vertices sorted by position and faces by their vertices (each face turned to start
        at its smallest index, its orientation kept): meshes that differ only in order (a multi-threaded extraction's)
        become equal arrays, so what follows (sampling, RANSAC, simplification) repeats exactly."""
        order = np.lexsort(self.vertices.T[::-1])
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        faces = rank[self.faces]
        first = faces.argmin(axis=1)
        faces = faces[np.arange(len(faces))[:, None], (first[:, None] + np.arange(3)) % 3]
        faces = faces[np.lexsort(faces.T[::-1])]
        colors = None if self.vertex_colors is None else self.vertex_colors[order]
        return replace(self, vertices=self.vertices[order], faces=faces, vertex_colors=colors, info=dict(self.info))

    def submesh(self, face_mask: "Shaped[np.ndarray, 'num_faces']") -> "TriangleMesh":
        """Keep the faces where ``face_mask`` is true, dropping unreferenced vertices."""
        faces = self.faces[np.asarray(face_mask, dtype=bool)]
        used, inverse = np.unique(faces.reshape(-1), return_inverse=True)
        colors = None if self.vertex_colors is None else self.vertex_colors[used]
        return TriangleMesh(self.vertices[used], inverse.reshape(-1, 3), colors, dict(self.info))

    # ------------------------------------------------------------ conversions (lazy imports)
    def to_trimesh(self):
        import trimesh

        colors = None if self.vertex_colors is None else self.vertex_colors
        return trimesh.Trimesh(self.vertices, self.faces, vertex_colors=colors, process=False)

    def to_open3d(self):
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.faces.astype(np.int32)))
        if self.vertex_colors is not None:
            m.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors.astype(np.float64) / 255.0)
        return m

    def to_open3d_tensor(self):
        """An ``open3d.t.geometry.TriangleMesh`` (float32/uint32), e.g. for a RaycastingScene."""
        import open3d as o3d

        m = o3d.t.geometry.TriangleMesh()
        m.vertex.positions = o3d.core.Tensor(self.vertices.astype(np.float32))
        m.triangle.indices = o3d.core.Tensor(self.faces.astype(np.uint32))
        return m

    @classmethod
    def from_open3d(cls, m) -> "TriangleMesh":
        colors = None
        if m.has_vertex_colors():
            colors = np.clip(np.asarray(m.vertex_colors) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return cls(np.asarray(m.vertices), np.asarray(m.triangles), colors)

    def to_pymeshlab(self):
        import pymeshlab

        kwargs = {}
        if self.vertex_colors is not None:
            rgba = np.concatenate([self.vertex_colors / 255.0, np.ones((self.num_vertices, 1))], axis=1)
            kwargs["v_color_matrix"] = rgba.astype(np.float64)
        return pymeshlab.Mesh(vertex_matrix=self.vertices, face_matrix=self.faces.astype(np.int32), **kwargs)

    @classmethod
    def from_pymeshlab(cls, m, with_colors: bool, info: "dict | None" = None) -> "TriangleMesh":
        """pymeshlab meshes always carry a colour array (white by default): say whether it is real."""
        colors = None
        if with_colors:
            colors = np.clip(m.vertex_color_matrix()[:, :3] * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return cls(m.vertex_matrix(), m.face_matrix(), colors, dict(info or {}))
