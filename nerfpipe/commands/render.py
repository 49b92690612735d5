"""``nerfpipe render``: novel views of a trained run (test poses, a generated orbit or a camera_path.json file)."""

from pathlib import Path
from typing import Literal

from tyro.conf import Positional


def render(
    run_dir: Positional[Path],
    path: str = "orbit",
    depth: bool = True,
    background: Literal["auto", "black", "white"] = "auto",
    size: "str | None" = None,
    scale: float = 1.0,
    max_size: int = 400,
    frames: int = 60,
    chunk: int = 4096,
    fps: float = 15.0,
    device: str = "auto",
    pngs: bool = False,
) -> int:
    """Render a camera path of a trained run into RUN_DIR/render/ (the files the pipeline's render stage writes).

    Args:
        run_dir: a run folder written by nerfpipe train or nerfpipe run.
        path: orbit (around the scene centre), test (the dataset's test poses; orbit when it has none), or a
            camera_path.json file (nerfstudio's format, as ``nerfpipe view`` saves it; see nerfpipe/data/camera_path.py),
            written as render/<file name>.gif/mp4 at the file's fps and size.
        depth: also write depth_<path>.gif (turbo colour map, mapping printed and saved).
        background: auto (the run's evaluation background), black or white.
        size: output size WxH, e.g. 800x800 (default: the cameras' own times --scale, capped at --max-size).
        scale: resolution factor of the frames relative to the cameras.
        max_size: longer side of the frames in pixels at most (after --scale; not applied to --size nor to a file's size).
        frames: number of frames (test and orbit; a file gives its own).
        chunk: rays per forward pass (bounds memory).
        fps: frames per second of the GIF and the video (a camera_path.json file gives its own).
        device: torch device (auto: CUDA when present, else CPU; named in the printed JSON).
        pngs: also write every colour frame losslessly, as render/<name>_frames/00000.png, ...
    """
    import json

    from nerfpipe.outputs.artifacts import SEQUENCE_DEPENDENCIES
    from nerfpipe.outputs.novel_views import RENDER_DIR, RenderConfig, background as bg, read_path_file, render_sequence, write_render
    from nerfpipe.training.runs import load_run
    from nerfpipe.util.devices import check_device
    from nerfpipe.util.errors import require_all

    config = RenderConfig(path=path, frames=frames, depth=depth, background=background, size=size, scale=scale,
                          max_size=max_size, chunk=chunk, fps=fps, pngs=pngs)  # fmt: skip
    require_all(SEQUENCE_DEPENDENCIES)
    camera_file = read_path_file(config)  # a bad file is refused before the run loads
    device = check_device(device)  # stdout is the JSON, which names it
    scene, model, cfg = load_run(Path(run_dir), device)
    views, info = render_sequence(model, scene, config, bg(config, cfg, scene), device, None, camera_file)
    info = write_render(Path(run_dir) / RENDER_DIR, views, config, {**info, "device": device}, camera_file.fps if camera_file else None)
    print(json.dumps(info, indent=2))
    return 0
