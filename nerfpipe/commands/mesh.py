"""``nerfpipe mesh``: a mesh of a trained run (marching cubes or TSDF), cleaned, simplified, coloured.

The options are generated from the config dataclasses (tyro), so none is restated here: every field of
:class:`~nerfpipe.mesh.pipeline.MeshConfig` is ``--FIELD`` (``--method``, ``--support-tolerance``, ...) and every
field of :class:`~nerfpipe.mesh.trained.RenderedViews` is ``--views.FIELD`` (``--views.tsdf-views``), each with its
attribute docstring as help: the names of the pipeline's ``nerfpipe run --mesh.mesh.FIELD`` / ``--mesh.views.FIELD``
and ``nerfpipe stage mesh``.
"""

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro
from tyro.conf import OmitArgPrefixes, Positional

from nerfpipe.mesh.pipeline import MeshConfig
from nerfpipe.mesh.trained import RenderedViews


@dataclass
class MeshCommand:
    """Extract a mesh from a trained run into RUN_DIR/mesh/ (in the input dataset's frame).

    Writes mesh.ply, mesh_simplified.ply, mesh_views.png (four views, shaded and coloured) and mesh.json
    (level, face counts, Hausdorff distance of the simplification, timings)."""

    run_dir: Annotated[Path, Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """A run folder written by nerfpipe train or nerfpipe run."""
    mesh: OmitArgPrefixes[MeshConfig] = field(default_factory=MeshConfig)
    """How the mesh is extracted, cleaned and simplified."""
    views: RenderedViews = field(default_factory=RenderedViews)
    """Training views rendered for the depth level and TSDF fusion (min-views, budget-share and fixed-seconds act
    only under a time budget: nerfpipe run --time-budget)."""
    out: "Path | None" = None
    """Output folder (default RUN_DIR/mesh)."""
    device: str = "auto"
    """Torch device (auto: CUDA when present, else CPU; named in the printed JSON)."""
    threads: "int | None" = None
    """Torch CPU threads (default: torch's; 1 is much faster on a machine busier than its cores)."""


def main(argv: "list[str]") -> int:
    """Parse ``nerfpipe mesh ARGV`` from the configs and mesh."""
    return mesh(tyro.cli(MeshCommand, args=argv, prog="nerfpipe mesh"))


def mesh(cmd: MeshCommand) -> int:
    """Mesh the run as ``cmd`` says and print mesh.json's figures, the files and the device as JSON."""
    import json

    from nerfpipe.mesh.pipeline import MESH_DEPENDENCIES, write_meshes
    from nerfpipe.mesh.trained import mesh_model
    from nerfpipe.training.runs import load_run
    from nerfpipe.util.devices import check_device
    from nerfpipe.util.errors import NerfpipeError, refuse_unless, require_all
    from nerfpipe.util.paths import check_output_folder
    from nerfpipe.util.scoped import torch_threads

    if cmd.mesh.level is not None and cmd.mesh.method != "mc":
        raise NerfpipeError("--level sets the marching-cubes iso-level: add --method mc")
    refuse_unless([("threads", cmd.threads is None or cmd.threads >= 1, "at least 1", cmd.threads)])
    run_dir = Path(cmd.run_dir)
    out = check_output_folder(Path(cmd.out) if cmd.out is not None else run_dir / "mesh")
    require_all(MESH_DEPENDENCIES)
    with torch_threads(cmd.threads):  # handed back after (a caller's own count stays)
        device = check_device(cmd.device)  # stdout is the JSON, which names it
        scene, model, _ = load_run(run_dir, device)
        result = mesh_model(cmd.mesh, model, scene, cmd.views, device)
        paths = write_meshes(result, out, scene.world_from_input, seen_from=scene.split_cameras("train").centers.reshape(-1, 3).double().numpy())
        print(json.dumps({**result.figures, "files": [str(p) for p in paths.values()], "device": device}, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
