"""``nerfpipe view``: the browser viewer of a run or a dataset."""

from pathlib import Path

from tyro.conf import Positional


def view(
    path: Positional[Path],
    port: int = 7007,
    host: str = "127.0.0.1",
    max_size: int = 512,
    path_file: "Path | None" = None,
    device: str = "auto",
    seconds: "float | None" = None,
    threads: int = 1,
) -> int:
    """Show a trained run (cameras, points, box, training rays, mesh and a live render of the field) or a
    dataset (cameras, points, box, rays) in the browser, and place camera paths.

    Serves on HOST:PORT and prints the URL; open it in a browser. Stop with Ctrl-C.

    Args:
        path: a run folder (nerfpipe train's, or a pipeline run with train/) or a dataset.
        port: port to serve on (0: any free one).
        host: interface (127.0.0.1: this machine only; 0.0.0.0: every interface, with no access control).
        max_size: longer side of the sharpest live frame in pixels (frames start small and sharpen while the view is still).
        path_file: where "Save path" writes the camera path (default: RUN/camera_path.json, or ./camera_path.json for a dataset).
        device: torch device of the live render (auto: CUDA when present, else CPU; printed at start).
        seconds: stop after this many seconds (default: run until interrupted).
        threads: torch threads of the live render. One leaves the other cores to the browser and the
            server (a camera move reaches the server, and the page shows the new frame, while a refinement
            renders), and never spins against other processes: with two of two cores and a busy machine a
            small frame took 0.1-0.3 s instead of 13 ms (README, viewer).
    """
    import time

    from nerfpipe.util.devices import announce
    from nerfpipe.util.errors import refuse_unless, require_all
    from nerfpipe.viewer.progressive import RenderThread
    from nerfpipe.viewer.server import VIEWER_DEPENDENCIES, Viewer
    from nerfpipe.viewer.source import open_source

    refuse_unless([("port", 0 <= port <= 65535, "a port number (0: any free one)", port), ("max_size", 16 <= max_size <= 4096, "between 16 and 4096", max_size),
                   ("seconds", seconds is None or seconds >= 0, "0 or more", seconds), ("threads", threads >= 1, "1 or more", threads)])  # fmt: skip
    require_all(VIEWER_DEPENDENCIES)
    start = time.perf_counter()
    device = announce(device)
    source = open_source(Path(path), device)
    default_file = (source.run_dir if source.run_dir is not None else Path(".")) / "camera_path.json"
    viewer = Viewer(source.scene, source.render, host, port, path_file or default_file, source.mesh, max_size)
    thread = RenderThread(viewer.renderers, threads)
    viewer.wake = thread.wake
    what = "trained run" if source.render is not None else "dataset (no trained field: no live render)"
    print(f"nerfpipe view: {path} ({what}, {len(source.scene.cameras)} cameras) at {viewer.url} (ready in {time.perf_counter() - start:.1f} s)", flush=True)
    try:
        deadline = None if seconds is None else time.monotonic() + seconds
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        thread.stop()
        viewer.stop()
    return 0
