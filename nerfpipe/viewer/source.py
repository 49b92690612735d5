"""What ``nerfpipe view`` opens: a trained run (a ``nerfpipe train`` folder, or a pipeline run with ``train/``)
or a dataset (any format ``data_adapters`` reads); a run is found by the one run-folder reader, :mod:`nerfpipe.training.runs`."""

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.scene import SceneData
from nerfpipe.outputs.render import RenderedView


@dataclass
class ViewSource:
    """A scene to show and, for a trained run, how to render it."""

    scene: SceneData
    render: "Callable[[Cameras], RenderedView] | None"
    """Renders a ``[1]`` camera batch with the trained model (None for a dataset)."""
    run_dir: "Path | None"
    """The trained run folder (where ``config.json`` is), or None."""
    mesh: "Path | None"
    """A mesh of the run to show, if it has one."""
    model: "object | None" = None


def model_renderer(model, background, device: str, chunk: int = 4096) -> "Callable[[Cameras], RenderedView]":
    """The one renderer (:func:`nerfpipe.outputs.render.render_cameras`) for a ``[1]`` camera batch."""
    from nerfpipe.outputs.render import render_cameras

    bg = background.to(device)
    return lambda cams: render_cameras(model, cams.to(device), chunk, bg)[0]


def open_source(path: Path, device: str = "cpu") -> ViewSource:
    """A run folder (its scene, model and mesh) or a dataset; either is refused with one line when unreadable."""
    from nerfpipe.data_adapters import load

    from nerfpipe.outputs.novel_views import RenderConfig, background
    from nerfpipe.training.runs import find_run, load_run
    from nerfpipe.viewer.content import find_mesh

    path = Path(path)
    run = find_run(path) if path.is_dir() else None
    if run is None:
        return ViewSource(load(path), None, None, None)
    scene, model, cfg = load_run(run, device)
    bg = background(RenderConfig(), cfg, scene)  # the run's evaluation background, as nerfpipe render's default
    return ViewSource(scene, model_renderer(model, bg, device), run, find_mesh([run, path]), model)
