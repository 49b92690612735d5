"""Stage ``load``: read the input into a :class:`~nerfpipe.data.scene.SceneData` and summarise it.

Where the scene comes from, first match wins:

1. an in-memory ``pycolmap.Reconstruction`` in the context cache (``reconstruction``), with its
   images (``images``: a folder, or ``{image name: uint8 array}``). The model is written to
   ``RUN_DIR/input`` (``sparse/0`` + ``images/``, linked or written) and read by the COLMAP adapter,
   so a resumed run or ``nerfpipe stage`` finds the same scene without the caller;
2. the ``sfm`` stage's COLMAP folder ``RUN_DIR/sfm``;
3. the input path, through :func:`data_adapters.load`, with the points that the ``sfm`` stage triangulated
   for it when there are some (``RUN_DIR/sfm/points``).

Artifacts: ``scene.json`` (summary, and where to reload the scene from) on disk; ``scene`` in memory.
"""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerfpipe.data.image_file import image_uint8
from nerfpipe.data.scene import SceneData, check_images
from nerfpipe.pipeline.report_items import Shown
from nerfpipe.pipeline.stages import StageContext, StageSpec, atomic_path, write_json
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.paths import resolve_inside

SCENE_JSON = "scene.json"
INPUT_DIR = "input"
SFM_DIR = "sfm"
POINTS_DIR = f"{SFM_DIR}/points"
"""The ``sfm`` stage's points triangulated for a posed input (:data:`nerfpipe.plugins.sfm.POINTS_DIR` in its folder)."""


@dataclass
class LoadConfig:
    """Options of the ``load`` stage."""

    format: "str | None" = None
    """Adapter name (``colmap``, ``transforms``, ``npz``...); None detects the format."""


def summary(scene: SceneData, input_path: Path, format: "str | None", run_dir: "Path | None" = None) -> dict:
    """What ``scene.json`` records: where the scene was read from (relative to ``run_dir`` when it lies in the run
    folder, its ``sfm`` or ``input``, so that a run folder copied or moved elsewhere still reloads it), and its main
    figures."""
    cams = scene.cameras
    where, run = Path(input_path).resolve(), None if run_dir is None else Path(run_dir).resolve()
    if run is not None and where.is_relative_to(run):
        where = where.relative_to(run)
    return {
        "input": str(where),
        "format": format,
        "adapter": scene.format,
        "num_cameras": len(cams),
        "splits": {k: int(len(v)) for k, v in scene.splits.items()},
        "image_sizes": sorted({(int(w), int(h)) for w, h in zip(cams.width.tolist(), cams.height.tolist())}),
        "camera_models": sorted(set(scene.camera_models)),
        "near": float(scene.near),
        "far": float(scene.far),
        "aabb": scene.aabb.tolist(),
        "world_from_input": scene.world_from_input.matrix().tolist(),
        "num_points": 0 if scene.points is None else int(len(scene.points.xyz)),
        "has_alpha": bool(scene.has_alpha),
    }


def write_reconstruction(rec, images: "Path | dict[str, np.ndarray]", target: Path) -> Path:
    """Write ``rec`` as ``target/sparse/0`` plus ``target/images`` (a link to a folder, or PNG files)."""
    with atomic_path(target) as tmp:
        (tmp / "sparse" / "0").mkdir(parents=True)
        rec.write(str(tmp / "sparse" / "0"))
        if isinstance(images, dict):
            _write_images(images, tmp / "images")
        else:
            images = Path(images).resolve()
            if not images.is_dir():
                raise NerfpipeError("the images of the reconstruction must be a folder or a dict of arrays", images)
            (tmp / "images").symlink_to(images, target_is_directory=True)
    return target


def _write_images(images: "dict[str, np.ndarray]", folder: Path) -> None:
    """PNG files named by the dict's keys; a name must stay inside ``folder``, an array must be an image."""
    import imageio.v3 as iio

    for name, array in images.items():
        path = resolve_inside(folder, name, "images")
        pixels = image_uint8(array, f"images[{name!r}]")
        path.parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(path, pixels, extension=".png")


def input_path(ctx: StageContext) -> "tuple[Path, str | None]":
    """The dataset to read and its format (see the module docstring)."""
    if "reconstruction" in ctx.cache:
        if "images" not in ctx.cache:
            raise NerfpipeError("an in-memory reconstruction needs its images (a folder or a dict of arrays)")
        return write_reconstruction(ctx.cache["reconstruction"], ctx.cache["images"], ctx.path(INPUT_DIR)), "colmap"
    if ctx.path(SFM_DIR).is_dir() and not ctx.path(POINTS_DIR).is_dir():
        return ctx.path(SFM_DIR), "colmap"
    if ctx.source is None:
        raise NerfpipeError("no input: give a dataset path, or a reconstruction and its images", ctx.run_dir)
    return ctx.source, None


def run(config: LoadConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe import data_adapters

    path, fmt = input_path(ctx)
    fmt = config.format or fmt
    scene = _with_triangulated_points(data_adapters.load(path, fmt), ctx)
    check_images(scene)  # adapters read headers only: a truncated image stops the run here, before any work
    write_json(ctx.path(SCENE_JSON), summary(scene, path, fmt, ctx.run_dir))
    ctx.log.info("loaded %d cameras (%s) from %s", len(scene.cameras), scene.format, path)
    return {"scene": scene, SCENE_JSON: ctx.path(SCENE_JSON)}


def restore(config: LoadConfig, ctx: StageContext) -> "dict[str, object]":
    """Reload the scene recorded in ``scene.json``: the run's own input, or a folder inside the run
    (``input``, ``sfm``); a record naming anything else is refused (run folders are passed around)."""
    from nerfpipe import data_adapters

    file = ctx.path(SCENE_JSON)
    try:
        record = json.loads(file.read_text())
        path, fmt = Path(record["input"]), record["format"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise NerfpipeError(f"not a scene record of the load stage ({type(exc).__name__}: {exc})", file) from exc
    if ctx.source is None or path != Path(ctx.source).resolve():  # else the scene was read in the run folder
        path = resolve_inside(ctx.run_dir, path, file)
    return {"scene": _with_triangulated_points(data_adapters.load(path, fmt), ctx)}


def _with_triangulated_points(scene: SceneData, ctx: StageContext) -> SceneData:
    """The scene with the ``sfm`` stage's triangulated points, when it made some for this input."""
    if not ctx.path(POINTS_DIR).is_dir() or scene.points is not None:
        return scene
    from nerfpipe.data_adapters.colmap import with_points

    return with_points(scene, ctx.path(POINTS_DIR))


STAGE = StageSpec(
    name="load",
    description="read the input (any adapter, the sfm result or an in-memory reconstruction) into a scene",
    config=LoadConfig,
    run=run,
    produces=(SCENE_JSON,),
    shows=(Shown("scene", "table", (SCENE_JSON,), "scene summary"),),
    provides=("scene",),
    restore=restore,
)
