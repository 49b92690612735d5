"""``nerfpipe mesh``: a mesh of a trained run (marching cubes or TSDF), cleaned, simplified, coloured."""

from pathlib import Path
from typing import Annotated, Literal

import tyro
from tyro.conf import Positional


def mesh(
    run_dir: Annotated[Path, Positional, tyro.conf.arg(metavar="RUN_DIR")],
    method: Literal["mc", "tsdf"] = "tsdf",
    resolution: int = 256,
    faces: "int | None" = None,
    level: "float | None" = None,
    level_from: Literal["agreement", "quantile", "opacity"] = "opacity",
    min_component: "float | None" = None,
    remove_unseen: bool = True,
    close_holes: int = 0,
    colors: bool = True,
    tsdf_views: int = 48,
    tsdf_size: int = 256,
    chunk: int = 4096,
    out: "Path | None" = None,
    device: str = "auto",
    threads: "int | None" = None,
) -> int:
    """Extract a mesh from a trained run into RUN_DIR/mesh/ (in the input dataset's frame).

    Writes mesh.ply, mesh_simplified.ply, mesh_views.png (four views, shaded and coloured) and
    mesh.json (level, face counts, Hausdorff distance of the simplification, timings).

    Args:
        run_dir: a run folder written by nerfpipe train or nerfpipe run.
        method: tsdf (fuse the depth where rendered training rays stop; the default) or mc (marching cubes on the density).
        resolution: grid samples (mc) or TSDF voxels (tsdf) along the longest side of the box.
        faces: face count of mesh_simplified.ply (default 100000; a copy when the mesh is smaller).
        level: density iso-level for mc (default: chosen by --level-from).
        level_from: automatic level: opacity (the default: the density at which a ray crossing one voxel
            is 5% blocked), quantile (the 0.1 quantile of the density where the rays of 8 rendered training
            views end) or agreement (of log-spaced candidate levels, the one whose surface is closest to
            those points; candidates and scores go to mesh.json).
        min_component: drop pieces smaller than this fraction of the mesh's diagonal (floaters; default 0.01 with tsdf, 0.05 with mc).
        remove_unseen: drop faces no training camera sees.
        close_holes: fill holes of at most this many edges (0: off).
        colors: vertex colours from the field (mc) or the rendered images (tsdf).
        tsdf_views: training views rendered for tsdf (evenly spread).
        tsdf_size: longer side in pixels of the tsdf depth renders.
        chunk: rays per forward pass when rendering (tsdf).
        out: output folder (default RUN_DIR/mesh).
        device: torch device (auto: CUDA when present, else CPU; named in the printed JSON).
        threads: torch CPU threads (default: torch's; 1 is much faster on a machine busier than its cores).
    """
    import json

    from nerfpipe.mesh.pipeline import MESH_DEPENDENCIES, MeshConfig, write_meshes
    from nerfpipe.mesh.trained import RenderedViews, mesh_model
    from nerfpipe.training.runs import load_run
    from nerfpipe.util.devices import check_device
    from nerfpipe.util.errors import NerfpipeError, refuse_unless, require_all
    from nerfpipe.util.paths import check_output_folder
    from nerfpipe.util.scoped import torch_threads

    if level is not None and method != "mc":
        raise NerfpipeError("--level sets the marching-cubes iso-level: add --method mc")
    refuse_unless([("threads", threads is None or threads >= 1, "at least 1", threads)])
    cfg = MeshConfig(method=method, resolution=resolution, level=level, level_from=level_from, faces=faces, min_component=min_component,
                     remove_unseen=remove_unseen, close_holes=close_holes, colors=colors)
    views = RenderedViews(tsdf_views, tsdf_size, chunk)
    out = check_output_folder(Path(out) if out is not None else Path(run_dir) / "mesh")
    require_all(MESH_DEPENDENCIES)
    with torch_threads(threads):  # handed back after (a caller's own count stays)
        device = check_device(device)  # stdout is the JSON, which names it
        scene, model, _ = load_run(Path(run_dir), device)
        result = mesh_model(cfg, model, scene, views, device)
        paths = write_meshes(result, out, scene.world_from_input, seen_from=scene.split_cameras("train").centers.reshape(-1, 3).double().numpy())
        print(json.dumps({**result.figures, "files": [str(p) for p in paths.values()], "device": device}, indent=2))
    return 0
