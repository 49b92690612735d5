"""``nerfpipe render``: novel views of a trained run (test poses, a generated orbit or a camera_path.json file)."""

from pathlib import Path

from tyro.conf import Positional


def render(
    run_dir: Positional[Path],
    path: str = "test",
    depth: bool = False,
    background: "str | None" = None,
    size: "str | None" = None,
    frames: int = 60,
    chunk: int = 4096,
    device: str = "auto",
    pngs: bool = False,
) -> int:
    """Render a camera path of a trained run into RUN_DIR/renders/.

    Args:
        run_dir: a run folder written by nerfpipe train or nerfpipe run.
        path: test (the dataset's test poses; orbit when it has none), orbit (around the scene centre), or a
            camera_path.json file (nerfstudio's format, as ``nerfpipe view`` saves it; see nerfpipe/camera_path.py),
            written as renders/<file name>.gif/mp4 at the file's fps and size.
        depth: also write depth_<path>.gif (turbo colour map, mapping printed and saved).
        background: black | white (default: the run's evaluation background).
        size: output size WxH, e.g. 800x800 (default: the cameras' own).
        frames: number of frames (test and orbit; a file gives its own).
        chunk: rays per forward pass (bounds memory).
        device: torch device (auto: CUDA when present, else CPU; named in the printed JSON).
        pngs: also write every colour frame losslessly, as renders/<name>_frames/00000.png, ...
    """
    import json

    import torch

    from nerfpipe.artifacts import SEQUENCE_DEPENDENCIES, write_sequence
    from nerfpipe.atomic import write_json
    from nerfpipe.camera_path import read_camera_path
    from nerfpipe.devices import check_device
    from nerfpipe.errors import NerfpipeError, refuse_unless, require_all
    from nerfpipe.orbit import path_cameras
    from nerfpipe.pixel_sampler import BACKGROUNDS, background_colors
    from nerfpipe.render import render_cameras, resize_cameras
    from nerfpipe.runs import load_run
    from nerfpipe.trainer import backgrounds

    from_file = path.lower().endswith(".json")
    if not from_file and path not in ("test", "orbit"):
        raise NerfpipeError(f"unknown --path '{path}' (test, orbit or a camera_path.json file)")
    if background is not None and background not in BACKGROUNDS:
        raise NerfpipeError(f"unknown --background '{background}' ({' or '.join(BACKGROUNDS)})")
    refuse_unless([("frames", 1 <= frames <= 10_000, "between 1 and 10000", frames), ("chunk", chunk >= 1, "at least 1", chunk)])
    wh = None if size is None else _parse_size(size)
    require_all(SEQUENCE_DEPENDENCIES)
    camera_path = read_camera_path(Path(path)) if from_file else None  # a bad file is refused before the run loads
    device = check_device(device)  # stdout is the JSON, which names it
    scene, model, cfg = load_run(Path(run_dir), device)
    cams = path_cameras(scene, path, frames) if camera_path is None else camera_path.cameras.to(dtype=torch.float32)
    name, fps = (path, 15.0) if camera_path is None else (Path(path).stem, camera_path.fps)
    if wh is not None:
        cams = resize_cameras(cams, *wh)
    bg = background or backgrounds(cfg["trainer"].get("background", "auto"), scene.has_alpha)[1]
    with torch.no_grad():
        views = render_cameras(model, cams.to(device), chunk, background_colors(bg, 1)[0])
    info = write_sequence(views, Path(run_dir) / "renders", name, depth=depth, fps=fps)
    info["device"] = device
    if pngs:
        info["pngs"] = str(_write_pngs(views, Path(run_dir) / "renders" / f"{name}_frames"))
    write_json(Path(run_dir) / "renders" / (f"{name}.json" if camera_path is None else f"{name}.render.json"), info)
    print(json.dumps(info, indent=2))
    return 0


def _write_pngs(views, folder: Path) -> Path:
    import imageio.v3 as iio

    from nerfpipe.atomic import atomic_path
    from nerfpipe.render import to_uint8

    with atomic_path(folder) as tmp:
        tmp.mkdir()
        for i, v in enumerate(views):
            iio.imwrite(tmp / f"{i:05d}.png", to_uint8(v.rgb))
    return folder


def _parse_size(text: str) -> "tuple[int, int]":
    from nerfpipe.errors import NerfpipeError

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise NerfpipeError(f"--size must be WxH, e.g. 800x800 (got '{text}')") from exc
    if not (0 < w <= 8192 and 0 < h <= 8192):
        raise NerfpipeError(f"--size must be positive, at most 8192x8192 (got '{text}')")
    return w, h
