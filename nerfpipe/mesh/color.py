"""Vertex colours from a radiance field: :func:`vertex_colors`.

Each vertex is coloured by ``rgb_fn`` at the vertex, seen along the inward normal (as a
camera facing the surface would see it), optionally a little inside the surface where a
trained field's colour is better supervised than at the iso-surface itself.
"""

from collections.abc import Callable

import numpy as np
import torch

from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.util.typing import Float, Tensor

RgbFn = Callable[[Tensor, Tensor], Tensor]
"""``rgb_fn(points [N, 3], directions [N, 3]) -> rgb [N, 3]`` in [0, 1], world coordinates."""


@torch.no_grad()
def vertex_colors(
    mesh: TriangleMesh,
    rgb_fn: RgbFn,
    normals: "Float[np.ndarray, 'num_verts 3'] | None" = None,
    inset: float = 0.0,
    chunk: int = 1 << 16,
    device: "str | torch.device" = "cpu",
) -> TriangleMesh:
    """A copy of ``mesh`` with uint8 vertex colours from ``rgb_fn``.

    Args:
        mesh: the mesh, in the field's (world) frame.
        rgb_fn: colour at points seen along directions.
        normals: outward unit normals per vertex (default: area-weighted from the faces).
        inset: evaluate at ``vertex - inset * normal`` (world units).
        chunk: points per ``rgb_fn`` call.
        device: where points are sent.
    """
    n = torch.from_numpy(mesh.vertex_normals() if normals is None else normals).float()
    p = torch.from_numpy(mesh.vertices).float() - inset * n
    d = -n
    rgb = torch.cat([rgb_fn(pc.to(device), dc.to(device)).float().cpu() for pc, dc in zip(p.split(chunk), d.split(chunk))])
    colors = (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()
    return TriangleMesh(mesh.vertices, mesh.faces, colors, dict(mesh.info))
