"""The viewer's goals, measured in headless Chromium on this machine.

1. **Start**: ``nerfpipe view RUN`` launched as a process, to the page showing every camera frustum and
   the first live render (seconds from the launch).
2. **Move latency**: the browser's camera turned (``cameraControl.rotate``), to the page showing the
   low frame of the new view (the first frame under 256 pixels on its longer side after the move: the
   low frame is at most half the first refinement, 256 at ``--max-size 512``), timed by the page's own
   clock (ms since the epoch, on both sides); ``--moves`` times, each after the page's render stayed
   unchanged for 1.5 s (a refinement of 512 px may still be running: a move then interrupts it). Each
   move is split by the page's clock (``move_parts_s``): until the page sent the camera, from then to
   the page receiving the image (the server and the socket), and from then to the page showing it.
   Then, in-process, the server's side: browser to server, the server's low frame, server to the page.
   And one more move, to the page showing the half and the full ``--max-size`` frames (``refine_s``).
3. **Path = viewer**: keyframes placed from the browser's camera (two moves apart), the path saved,
   each frame previewed in the viewer at the path's size, then ``nerfpipe render RUN --path FILE --pngs``:
   the largest pixel difference (of 255) between the two.
4. **Training overhead** (``--train DATASET``): ``nerfpipe train DATASET --iters N --num-threads 1 --clock cpu``
   alone and with ``--view`` and a browser watching (its camera turned every few seconds), alternately
   ``--repeats`` times each: iterations per training second of each. The CPU clock (process CPU
   seconds: training, the live render between steps and viser's threads, not the browser's process)
   keeps the figure steady on a shared machine, where wall-clock rates of one command vary twofold.

Usage::

    python -m benchmarks.viewer_bench RUN [--train DATASET --iters 150] [--json out.json]
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from nerfpipe.viewer.headless import BACKGROUND_JS, FRUSTUMS_JS, WATCH_BACKGROUND_JS, WATCH_MESSAGES_JS, Chromium

PY = [sys.executable, "-m", "nerfpipe"]
ROTATE_JS = "(() => { window.__viserMutable.cameraControl.rotate(%f, %f, false); return Date.now(); })()"


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]) + os.pathsep + os.environ.get("PYTHONPATH", "")}


LOW_FRAME_JS = """(() => { const t = %d; const sent = window.__cameraSent.filter(e => e >= t)[0];
  const got = sent === undefined ? undefined : window.__imageReceived.filter(e => e >= sent)[0];
  return got === undefined ? null : window.__bgLog.filter(e => e[0] >= got && Math.max(e[1], e[2]) < 256)[0] || null; })()"""
"""The page's first low frame after the move at ``t``: shown after an image came that was sent for the new camera
(a frame of the former view still on its way is not it)."""


def _launch_view(run: Path, port: int) -> "tuple[subprocess.Popen, str, float]":
    start = time.perf_counter()
    proc = subprocess.Popen([*PY, "view", str(run), "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_env())
    for line in proc.stdout:
        m = re.search(r"at (http://\S+)", line)
        if m and "nerfpipe view" in line:
            return proc, m.group(1), start
    raise RuntimeError("nerfpipe view did not start")


def _quiet(browser: Chromium, still: float = 1.5, timeout: float = 60.0) -> None:
    """Wait until the page's render has not changed for ``still`` seconds (the refinement finished)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        n = browser.evaluate("window.__bgLog.length")
        time.sleep(still)
        if browser.evaluate("window.__bgLog.length") == n:
            return


def measure_view(run: Path, moves: int, tmp: Path) -> dict:
    num_cameras = None
    proc, url, start = _launch_view(run, 7117)
    browser = Chromium(tmp / "profile-view", width=1200, height=800)
    try:
        url_seconds = time.perf_counter() - start
        browser.open(url)
        num_cameras = browser.wait_for(FRUSTUMS_JS, lambda n: n is not None and n > 0, timeout=60.0)
        frustum_seconds = time.perf_counter() - start
        size = browser.wait_for(BACKGROUND_JS, timeout=60.0)
        render_seconds = time.perf_counter() - start
        browser.evaluate(WATCH_BACKGROUND_JS)
        browser.evaluate(WATCH_MESSAGES_JS)
        latencies, sizes, parts = [], [], []
        for k in range(moves):
            _quiet(browser)
            load = Path("/proc/loadavg").read_text().split()[0]
            t = browser.evaluate(ROTATE_JS % (0.25 if k % 2 == 0 else -0.2, 0.03))
            # the low frame: at most half the first refinement's size (half of --max-size 512 on the longer
            # side), so smaller than any refinement; a refinement of the previous view may still land after the move
            # (and a low frame of it: the page's log of what it sent and received tells them apart)
            try:
                first = browser.wait_for(LOW_FRAME_JS % t, timeout=30.0)
            except TimeoutError:  # the page never showed it (it took a later image in the same frame): a miss, recorded
                latencies.append(None), sizes.append(None), parts.append({"load": float(load)})
                continue
            latencies.append((first[0] - t) / 1000)
            sizes.append(first[1:])
            parts.append(_split(browser, t, first[0]) | {"load": float(load)})
        refine = _refinement(browser)
        _quiet(browser)
        browser.screenshot(tmp / "view.png")
        outside = browser.outside_requests()
    finally:
        browser.close()
        proc.terminate()
        proc.wait(timeout=30)
    return {"url_printed_s": url_seconds, "frustums_shown_s": frustum_seconds, "first_render_shown_s": render_seconds, "cameras": num_cameras,
            "first_size": size, "move_latency_s": latencies, "move_first_size": sizes, "move_parts_s": parts, "refine_s": refine, "outside_requests": outside,
            "screenshot": str(tmp / "view.png")}  # fmt: skip


def _refinement(browser: Chromium, sizes: "tuple[int, ...]" = (256, 512), timeout: float = 180.0) -> dict:
    """One more move, then the seconds until the page shows its frame of each refinement (longer side
    ``sizes``: half and full ``--max-size 512``), with the load at the move."""
    _quiet(browser)
    out = {"load": float(Path("/proc/loadavg").read_text().split()[0])}
    t = browser.evaluate(ROTATE_JS % (0.2, 0.0))
    for size in sizes:
        try:
            shown = browser.wait_for(f"window.__bgLog.filter(e => e[0] > {t} && Math.max(e[1], e[2]) == {size})[0] || null", timeout=timeout)
            out[str(size)] = (shown[0] - t) / 1000
        except TimeoutError:
            out[str(size)] = None
    return out


def _split(browser: Chromium, t: int, shown: int) -> dict:
    """Where one move's latency went, by the page's clock: until the page sent the camera, from then to the
    last live render the page received before it showed the low frame (the server, and the socket both
    ways), and from that to the page showing it (decoding and drawing)."""
    sent = browser.evaluate(f"window.__cameraSent.filter(e => e >= {t})[0] || null")
    got = browser.evaluate(f"window.__imageReceived.filter(e => e >= {t} && e <= {shown}).pop() || null")
    if sent is None or got is None:
        return {"page_to_send_s": None, "server_s": None, "page_to_show_s": None}
    return {"page_to_send_s": (sent - t) / 1000, "server_s": (got - sent) / 1000, "page_to_show_s": (shown - got) / 1000}


def _first_of_view(browser: Chromium, viewer, n: int, t: int, timeout: float = 30.0) -> list:
    """The page's first render after ``t`` of a size the server made for the new view (its low frame,
    or a refinement when a loaded page skipped the low frame)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sizes = {(f["width"], f["height"]) for f in viewer.frames[n:]}
        for entry in browser.evaluate(f"window.__bgLog.filter(e => e[0] > {t})") or []:
            if (entry[1], entry[2]) in sizes:
                return entry
        time.sleep(0.02)
    raise TimeoutError("the page showed no render of the new view")


def _scratch_run(run: Path, tmp: Path) -> Path:
    """A folder that reads as ``run`` (a link to each of its entries) but gets a ``render/`` of its own:
    the run measured is left as it was."""
    scratch = tmp / "run"
    scratch.mkdir()
    for entry in run.iterdir():
        if entry.name != "render":
            (scratch / entry.name).symlink_to(entry.resolve())
    return scratch


def measure_path(run: Path, tmp: Path, size: "tuple[int, int]" = (160, 120), frames: int = 4) -> dict:
    """Keyframes from the browser, previews in the viewer, the same path rendered headless: max difference."""
    import imageio.v3 as iio

    from nerfpipe.viewer.progressive import RenderThread
    from nerfpipe.viewer.server import Viewer
    from nerfpipe.viewer.source import open_source

    source = open_source(run)
    viewer = Viewer(source.scene, source.render, port=0, path_file=tmp / "bench_path.json", thumbnails=False)
    thread = RenderThread(viewer.renderers, threads=1)  # as nerfpipe view's default
    viewer.wake = thread.wake
    browser = Chromium(tmp / "profile-path", width=1200, height=800)
    try:
        browser.open(viewer.url)
        browser.wait_for(BACKGROUND_JS, timeout=60.0)
        client = next(iter(viewer.server.get_clients().values()))
        browser.evaluate(WATCH_BACKGROUND_JS)
        split = []  # where a move's latency goes: browser -> server, render, server -> page shown
        for k in range(3):
            _quiet(browser)
            n = len(viewer.frames)
            t = browser.evaluate(ROTATE_JS % (0.2, 0.0))
            deadline = time.monotonic() + 30
            while not any(f["level"] == 0 for f in viewer.frames[n:]) and time.monotonic() < deadline:
                time.sleep(0.01)
            low = next(f for f in viewer.frames[n:] if f["level"] == 0)
            shown = _first_of_view(browser, viewer, n, t)
            sent = low["shown"] - t / 1000
            split.append({"to_server_s": sent - low["latency"], "request_to_frame_s": low["latency"], "render_s": low["seconds"],
                          "to_page_s": shown[0] / 1000 - low["shown"], "total_s": (shown[0] - t) / 1000, "size": [low["width"], low["height"]]})  # fmt: skip
        for turn in (0.0, 0.5):
            browser.evaluate(ROTATE_JS % (turn, 0.0))
            time.sleep(1.0)
            viewer.add_keyframe_from(client)
        viewer.path_width.value, viewer.path_height.value = size
        viewer.path_fps.value, viewer.path_seconds.value = float(frames), 1.0
        file = viewer.save_path()
        for k in range(frames):
            viewer.preview_frame(k, client)
            deadline = time.monotonic() + 120
            while k not in viewer.preview_frames and time.monotonic() < deadline:
                time.sleep(0.05)
    finally:
        browser.close()
        thread.stop()
        viewer.stop()
    scratch = _scratch_run(run, tmp)
    subprocess.run([*PY, "render", str(scratch), "--path", str(file), "--pngs"], check=True, capture_output=True, env=_env())
    diffs = []
    for k in range(frames):
        headless = iio.imread(scratch / "render" / f"{file.stem}_frames" / f"{k:05d}.png").astype(int)
        shown = viewer.preview_frames.get(k)
        diffs.append(None if shown is None else int(np.abs(headless - shown.astype(int)).max()))  # None: the preview never finished
    return {"path_file": str(file), "frames": frames, "size": list(size), "max_pixel_difference": diffs, "move_latency_split": split}


def _train(dataset: Path, out: Path, iters: int, view: bool, tmp: Path) -> float:
    args = [*PY, "train", str(dataset), "--out", str(out), "--iters", str(iters), "--video-frames", "0", "--eval-every", "0", "--final-eval-views", "1", "--eval-scale", "0.25",
            "--num-threads", "1", "--clock", "cpu"]
    if view:
        args += ["--view", "--view-port", "7118"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_env())
    browser = None
    try:
        if view:
            for line in proc.stdout:
                m = re.search(r"watching the training at (http://\S+)", line)
                if m:
                    browser = Chromium(tmp / f"profile-train-{time.monotonic_ns()}", width=1000, height=700)
                    browser.open(m.group(1))
                    break
            while proc.poll() is None:  # turn the camera now and then, as a user would
                time.sleep(3.0)
                try:
                    browser.evaluate(ROTATE_JS % (0.2, 0.0))
                except Exception:  # noqa: BLE001 - the page goes when training ends
                    break
        proc.wait()
    finally:
        if browser is not None:
            browser.close()
    metrics = json.loads((out / "metrics.json").read_text())
    return metrics["iterations"] / metrics["train_seconds"]


def measure_training(dataset: Path, iters: int, repeats: int, tmp: Path) -> dict:
    rates = {"plain": [], "view": []}
    for r in range(repeats):
        for mode in ("plain", "view"):
            rates[mode].append(_train(dataset, tmp / f"train-{mode}-{r}", iters, mode == "view", tmp))
    plain, view = np.median(rates["plain"]), np.median(rates["view"])
    return {"iters": iters, "its_per_s": rates, "overhead": float(1 - view / plain)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("--moves", type=int, default=5)
    p.add_argument("--train", type=Path, default=None)
    p.add_argument("--iters", type=int, default=150)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--skip-view", action="store_true")
    p.add_argument("--skip-path", action="store_true", help="leave out the path = viewer check (and the in-process latency split)")
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="viewer_bench-"))
    out = {"run": str(a.run), "loadavg_start": Path("/proc/loadavg").read_text().split()[:3]}
    if not a.skip_view:
        out["view"] = measure_view(a.run, a.moves, tmp)
        print(json.dumps(out["view"], indent=1), flush=True)
    if not a.skip_view and not a.skip_path:
        out["path"] = measure_path(a.run, tmp)
        print(json.dumps(out["path"], indent=1), flush=True)
    if a.train is not None:
        out["training"] = measure_training(a.train, a.iters, a.repeats, tmp)
        print(json.dumps(out["training"], indent=1), flush=True)
    out["loadavg_end"] = Path("/proc/loadavg").read_text().split()[:3]
    print(json.dumps(out, indent=1))
    if a.json is not None:
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
