"""``nerfpipe mesh``: a mesh of a trained run (marching cubes or TSDF), cleaned, simplified, coloured."""

from pathlib import Path
from typing import Annotated, Literal

import tyro
from tyro.conf import Positional


def mesh(
    run_dir: Annotated[Path, Positional, tyro.conf.arg(metavar="RUN_DIR")],
    method: Literal["mc", "tsdf"] = "mc",
    resolution: int = 256,
    faces: "int | None" = None,
    level: "float | None" = None,
    level_from: Literal["opacity", "depth"] = "opacity",
    min_component: float = 0.05,
    remove_unseen: bool = True,
    close_holes: int = 0,
    colors: bool = True,
    tsdf_views: int = 48,
    tsdf_size: int = 256,
    chunk: int = 4096,
    out: "Path | None" = None,
    device: str = "cpu",
) -> int:
    """Extract a mesh from a trained run into RUN_DIR/mesh/ (in the input dataset's frame).

    Writes mesh.ply, mesh_simplified.ply, mesh_views.png (four views, shaded and coloured) and
    mesh.json (level, face counts, Hausdorff distance of the simplification, timings).

    Args:
        run_dir: a run folder written by nerfpipe train.
        method: mc (marching cubes on the density) or tsdf (fuse depth rendered from training views).
        resolution: grid samples (mc) or TSDF voxels (tsdf) along the longest side of the box.
        faces: face count of mesh_simplified.ply (default 100000; a copy when the mesh is smaller).
        level: density iso-level for mc (default: chosen by --level-from).
        level_from: automatic level: opacity (ln 2 / voxel size, one voxel half opaque) or depth
            (the median density where rays of rendered training views end).
        min_component: drop pieces smaller than this fraction of the mesh's diagonal (floaters).
        remove_unseen: drop faces no training camera sees.
        close_holes: fill holes of at most this many edges (0: off).
        colors: vertex colours from the field (mc) or the rendered images (tsdf).
        tsdf_views: training views rendered for tsdf (evenly spread).
        tsdf_size: longer side in pixels of the tsdf depth renders.
        chunk: rays per forward pass when rendering (tsdf).
        out: output folder (default RUN_DIR/mesh).
        device: torch device.
    """
    import json

    import torch

    from nerfpipe.mesh.pipeline import MeshConfig, build_meshes, write_meshes
    from nerfpipe.runs import load_run

    scene, model, _ = load_run(Path(run_dir), device)
    cfg = MeshConfig(method=method, resolution=resolution, level=level, level_from=level_from, faces=faces, min_component=min_component,
                     remove_unseen=remove_unseen, close_holes=close_holes, colors=colors)
    aabb, occupancy_fn = _box_and_occupancy(model, scene.aabb)
    train = scene.split_cameras("train")
    frame_fn, tsdf_cams = (None, None)
    if method == "tsdf":
        tsdf_cams, frame_fn = _tsdf_frames(model, train, tsdf_views, tsdf_size, chunk, device)
    points = _surface_points(model, train, chunk, device) if method == "mc" and level is None and level_from == "depth" else None
    with torch.no_grad():
        result = build_meshes(cfg, aabb, density_fn=model.density_fn, rgb_fn=model.rgb_fn, occupancy_fn=occupancy_fn,
                              frame_fn=frame_fn, cameras=tsdf_cams if tsdf_cams is not None else train, surface_points=points)
    paths = write_meshes(result, Path(out) if out is not None else Path(run_dir) / "mesh", scene.world_from_input)
    print(json.dumps({**result.figures, "files": [str(p) for p in paths.values()]}, indent=2))
    return 0


def _box_and_occupancy(model, scene_aabb):
    """The box to mesh: the occupancy grid's occupied box (one cell margin) when the model has one."""
    import torch

    grid = getattr(model, "grid", None)
    if grid is None or not hasattr(grid, "occupied_aabb"):
        return scene_aabb.float(), None
    box = grid.occupied_aabb().float().cpu()
    cell = (grid.aabb[1] - grid.aabb[0]).float().cpu() / grid.cfg.resolution
    box = torch.stack([torch.maximum(box[0] - cell, grid.aabb[0].cpu()), torch.minimum(box[1] + cell, grid.aabb[1].cpu())])
    return box, lambda p: grid.occupied(p.to(grid.aabb.device))


def _surface_points(model, train, chunk: int, device: str, views: int = 8, size: int = 128):
    """Where the rays of a few rendered training views end (opaque pixels only), world frame."""
    import torch

    from nerfpipe.rays import camera_rays
    from nerfpipe.render import render_cameras, resize_cameras

    idx = torch.linspace(0, len(train) - 1, min(views, len(train))).round().long().unique()
    cams = _resize_each(train[idx], size / torch.maximum(train[idx].width, train[idx].height).double(), resize_cameras)
    pts = []
    for i, view in enumerate(render_cameras(model, cams.to(device), chunk)):
        rays = camera_rays(cams, i)
        opaque = view.acc.cpu() > 0.9
        pts.append(rays.points_at(view.surface_depth.cpu())[opaque])
    return torch.cat(pts)


def _tsdf_frames(model, train, views: int, size: int, chunk: int, device: str):
    """Undistorted, resized training cameras and a ``frame_fn`` rendering their depth and colour."""
    import dataclasses

    import numpy as np
    import torch

    from nerfpipe.rays import camera_rays
    from nerfpipe.render import render_cameras, resize_cameras

    idx = torch.from_numpy(np.unique(np.linspace(0, len(train) - 1, min(views, len(train))).round().astype(np.int64)))
    cams = train[idx]
    cams = dataclasses.replace(cams, distortion=torch.zeros_like(cams.distortion), dist_params=torch.zeros_like(cams.dist_params))
    scale = size / torch.maximum(cams.width, cams.height).double()
    cams = _resize_each(cams, scale, resize_cameras)

    def frame(i: int):
        view = render_cameras(model, cams[i : i + 1].to(device), chunk)[0]
        depth = torch.where(view.acc > 0.5, view.surface_depth, torch.zeros_like(view.depth)).cpu()
        z = depth * camera_rays(cams, i).z_scale
        return z.double().numpy(), (view.rgb.cpu().numpy() * 255 + 0.5).astype(np.uint8)

    return cams, frame


def _resize_each(cams, scale, resize_cameras):
    """Scale every camera by its own factor (sizes may differ within a scene)."""
    from nerfpipe.cameras import Cameras

    parts = []
    for i in range(len(cams)):
        w = max(1, int(round(float(cams.width[i]) * float(scale[i]))))
        h = max(1, int(round(float(cams.height[i]) * float(scale[i]))))
        parts.append(resize_cameras(cams[i : i + 1], w, h))
    return Cameras.cat(parts)
