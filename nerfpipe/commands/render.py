"""``nerfpipe render``: novel views of a trained run (test poses, a generated orbit or a camera_path.json file).

The options are generated from :class:`~nerfpipe.outputs.novel_views.RenderConfig` (tyro), so none is restated here:
every field is ``--FIELD`` (``--path``, ``--frames``, ``--max-size``, ...), with its attribute docstring as help,
the names of the pipeline's ``nerfpipe run --render.FIELD`` and ``nerfpipe stage render``.
"""

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro
from tyro.conf import OmitArgPrefixes, Positional

from nerfpipe.outputs.novel_views import RenderConfig


@dataclass
class RenderCommand:
    """Render a camera path of a trained run into RUN_DIR/render/ (the files the pipeline's render stage writes)."""

    run_dir: Annotated[Path, Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """A run folder written by nerfpipe train or nerfpipe run."""
    render: OmitArgPrefixes[RenderConfig] = field(default_factory=RenderConfig)
    """What to render (min-frames and budget-share act only under a time budget: nerfpipe run --time-budget)."""
    device: str = "auto"
    """Torch device (auto: CUDA when present, else CPU; named in the printed JSON)."""


def main(argv: "list[str]") -> int:
    """Parse ``nerfpipe render ARGV`` from the config and render."""
    return render(tyro.cli(RenderCommand, args=argv, prog="nerfpipe render"))


def render(cmd: RenderCommand) -> int:
    """Render as ``cmd`` says and print the render's JSON (frames, size, depth mapping, device)."""
    import json

    from nerfpipe.outputs.artifacts import SEQUENCE_DEPENDENCIES
    from nerfpipe.outputs.novel_views import RENDER_DIR, background as bg, read_path_file, render_sequence, write_render
    from nerfpipe.training.runs import load_run
    from nerfpipe.util.devices import check_device
    from nerfpipe.util.errors import require_all

    config = cmd.render
    require_all(SEQUENCE_DEPENDENCIES)
    camera_file = read_path_file(config)  # a bad file is refused before the run loads
    device = check_device(cmd.device)  # stdout is the JSON, which names it
    scene, model, cfg = load_run(Path(cmd.run_dir), device)
    views, info = render_sequence(model, scene, config, bg(config, cfg, scene), device, None, camera_file)
    info = write_render(Path(cmd.run_dir) / RENDER_DIR, views, config, {**info, "device": device}, camera_file.fps if camera_file else None)
    print(json.dumps(info, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
