"""The browser viewer: what it draws, the live render (sizes, strips = whole frames), camera paths rendered
headless equal to the viewer's frames, the server, the page in headless Chromium, and training watched."""

import json
import math
import os
import time
import urllib.request

import numpy as np
import pytest
import torch

from nerfpipe.cli import main
from nerfpipe.data.camera_path import CameraPath, Keyframe, path_from_keyframes, read_camera_path, write_camera_path
from nerfpipe.data.orbit import look_at
from nerfpipe.data_adapters import load
from nerfpipe.outputs.render import RenderedView, render_cameras, to_uint8
from nerfpipe.viewer import content
from nerfpipe.viewer.progressive import ProgressiveRenderer, RenderCost, ViewRequest, cpu_sample, others_busy, pinhole_camera
from nerfpipe.viewer.source import open_source


def _require(what: str, available: bool, install: str) -> None:
    """Skip when an optional part is missing, except under CI, where the bootstrap installs it."""
    if not available:
        msg = f"{what} is not installed ({install})"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)


def _viser() -> None:
    try:
        import viser  # noqa: F401
    except ImportError:
        _require("viser", False, "pip install 'nerfpipe[viewer]'")


@pytest.fixture(autouse=True)
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    out = tmp_path_factory.mktemp("viewer") / "synth"
    assert main(["synth", str(out), "--views", "8", "--size", "24x24"]) == 0
    return out


@pytest.fixture(scope="module")
def run(synth, tmp_path_factory):
    out = tmp_path_factory.mktemp("viewer") / "run"
    args = ["train", str(synth), "--model", "vanilla", "--out", str(out), "--iters", "2", "--rays-per-step", "32", "--model.num-samples", "8", "--video-frames", "0", "--eval-every", "0"]
    assert main(args) == 0
    return out


def _drain(renderer: ProgressiveRenderer, wait=time.sleep) -> None:
    """Every unit of work, waiting (``wait(seconds)``) whenever the renderer has none yet (settle, rests)."""
    while renderer.busy:
        if not renderer.step():
            wait(renderer.wait_seconds() or 0.0)


# ---------------------------------------------------------------- what is drawn


def test_frustums_rays_and_box_of_a_scene(synth):
    scene = load(synth)
    frustums = content.frustums(scene)
    assert len(frustums) == len(scene.cameras)
    assert "train" in {f.split for f in frustums} and {f.split for f in frustums} <= set(content.SPLIT_COLOURS)
    i = len(frustums) - 1
    assert frustums[i].fov == pytest.approx(float(2 * torch.atan(scene.cameras.height[i] / (2 * scene.cameras.fy[i]))))
    np.testing.assert_allclose(frustums[i].position, scene.cameras.centers[i].double().numpy())
    lines, samples = content.training_rays(scene, num_rays=16, num_samples=8)
    lo, hi = scene.aabb.double().numpy()
    assert lines.shape == (16, 2, 3) and len(samples) > 0
    assert (samples >= lo - 1e-6).all() and (samples <= hi + 1e-6).all()  # samples where the rays cross the box
    assert content.box_segments(scene.aabb).shape == (12, 2, 3)
    assert content.thumbnail(np.zeros((200, 300, 4), np.uint8), 96).shape == (50, 75, 3)  # a factor of 4


# ---------------------------------------------------------------- the live render


def test_a_live_render_request_returns_an_image_of_the_requested_size(run):
    source = open_source(run)
    frames = []
    renderer = ProgressiveRenderer(source.render, frames.append, max_size=64)
    eye = look_at(torch.tensor([0.0, -4.0, 1.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    renderer.request(ViewRequest(eye.numpy(), 0.8, 2.0, time.perf_counter()))
    _drain(renderer)
    assert [f.level for f in frames] == [0, 1, 2]
    assert frames[-1].image.shape == (32, 64, 3) and frames[1].image.shape == (16, 32, 3)  # levels: half, then max_size
    assert frames[0].image.shape[0] * frames[0].image.shape[1] <= 64 * 32
    renderer.mode = "depth"
    renderer.request(ViewRequest(eye.numpy(), 0.8, 2.0, time.perf_counter(), size=(40, 30)))
    _drain(renderer)
    assert frames[-1].image.shape == (30, 40, 3) and frames[-1].level == frames[-1].levels == 1


def test_a_new_camera_interrupts_a_refinement_within_one_strip(run):
    source = open_source(run)
    frames = []
    renderer = ProgressiveRenderer(source.render, frames.append, max_size=64, strip_seconds=0.0, settle=0.0, refine_share=1.0)  # one row per strip
    eye = look_at(torch.tensor([0.0, -4.0, 1.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    renderer.request(ViewRequest(eye.numpy(), 0.8, 1.0, time.perf_counter()))
    renderer.step(), renderer.step(), renderer.step()  # the low frame, two strips
    renderer.request(ViewRequest(eye.numpy(), 0.5, 1.0, time.perf_counter()))
    renderer.step()
    assert [f.level for f in frames] == [0, 0]  # the second low frame came next, no refined frame of the first camera
    _drain(renderer)
    renderer.mode = "depth"
    renderer.refresh()  # after a finished refinement: the same camera again, from its low frame
    _drain(renderer)
    assert [f.level for f in frames][-3:] == [0, 1, 2] and frames[-1].image.shape == frames[-4].image.shape
    renderer.refresh(again=True)  # the field changed while training: only the sharpest level again
    _drain(renderer)
    assert (frames[-1].level, frames[-1].levels) == (1, 1) and frames[-1].image.shape == frames[-2].image.shape


class FakeRender:
    """A render that takes ``overhead + pixels / rate`` seconds of its own clock and returns a flat view
    whose colour is the camera's focal length (which camera it was)."""

    def __init__(self, overhead: float = 0.02, rate: float = 10_000.0) -> None:
        self.overhead, self.rate, self.now, self.calls = overhead, rate, 0.0, []

    def clock(self) -> float:
        return self.now

    def wait(self, seconds: float) -> None:
        self.now += seconds

    def __call__(self, cams) -> RenderedView:
        w, h = int(cams.width[0]), int(cams.height[0])
        seconds = self.overhead + w * h / self.rate
        self.now += seconds
        self.calls.append((w, h, seconds))
        return RenderedView(torch.full((h, w, 3), float(cams.fy[0])), torch.ones(h, w), torch.ones(h, w), None)


def _camera(fov: float, size=None) -> ViewRequest:
    return ViewRequest(np.eye(4), fov, 1.5, time.perf_counter(), size)


def test_other_load_is_the_busy_cpus_less_this_process():
    assert others_busy((0.0, 0.0, 0.0), (400.0, 100.0, 50.0), cpus=2) == pytest.approx(1.25)  # 1.5 busy, 0.25 ours
    assert others_busy((0.0, 0.0, 0.0), (400.0, 200.0, 200.0), cpus=2) == 0.0  # all the busy time ours
    assert others_busy((5.0, 1.0, 1.0), (5.0, 1.0, 1.0), cpus=2) == 0.0  # no tick counted: no measurement
    sample = cpu_sample()
    assert sample is None or (sample[0] > sample[1] >= 0 and sample[2] >= 0)


def test_render_cost_separates_the_per_call_time_from_the_per_pixel_time():
    cost = RenderCost()
    for pixels, calls in ((600, 1), (40_000, 20), (800, 1), (700, 1), (90_000, 45), (650, 1)):
        cost.observe(pixels, calls * 0.015 + pixels / 12_000, calls)
    assert cost.overhead == pytest.approx(0.015, rel=1e-6) and cost.rate == pytest.approx(12_000, rel=1e-6)
    assert cost.seconds(cost.pixels(0.1)) == pytest.approx(0.1)
    cost.observe(700, 5.0)  # one render under a burst of load: the median rate hardly moves
    assert cost.rate == pytest.approx(12_000, rel=0.1)
    alike = RenderCost(overhead=0.01)
    for _ in range(3):
        alike.observe(1000, 0.11)  # one size only: the overhead kept, the rate from the times
    assert alike.overhead == pytest.approx(0.01) and alike.rate == pytest.approx(10_000)


def test_the_low_frame_takes_about_low_seconds_and_stays_smaller_than_a_refinement():
    fake = FakeRender(overhead=0.02, rate=10_000.0)
    renderer = ProgressiveRenderer(fake, lambda frame: None, max_size=512, low_seconds=0.1, strip_seconds=0.05, settle=0.0, contended=lambda: True, clock=fake.clock)
    for k in range(8):  # distinct cameras, each refined to the end: the cost is measured on low frames and whole levels
        renderer.request(_camera(0.5 + 0.01 * k))
        _drain(renderer, fake.wait)
    w, h = renderer.low_size(_camera(0.9))
    assert fake.overhead + w * h / fake.rate == pytest.approx(0.1, rel=0.05)
    low = [c for c in fake.calls if c[0] < 256]
    assert 0.08 < low[-1][2] < 0.12  # the last low frame rendered took its 0.1 s
    strips = [c[2] for c in fake.calls if c[0] in (256, 512)]
    assert max(strips[-20:]) < 0.05 * 1.5  # strips: a move waits at most about strip_seconds
    quick = FakeRender(overhead=0.001, rate=1e9)
    renderer = ProgressiveRenderer(quick, lambda frame: None, max_size=512, settle=0.0, clock=quick.clock)
    for fov in (0.8, 0.9):  # the first low frame is sized before anything was measured
        renderer.request(_camera(fov))
        _drain(renderer, quick.wait)
    assert [c[:2] for c in quick.calls[3:]] == [(128, 85), (256, 171), (512, 341)]  # low frame: half the first level


def test_the_refinement_waits_for_the_camera_to_settle_and_only_the_newest_camera_is_rendered():
    fake = FakeRender()
    frames = []
    renderer = ProgressiveRenderer(fake, frames.append, max_size=64, settle=0.3, contended=lambda: True, clock=fake.clock)
    renderer.request(_camera(0.8))
    assert renderer.step() and [f.level for f in frames] == [0]
    assert renderer.step() is False and renderer.busy  # still: the refinement waits
    assert renderer.wait_seconds() == pytest.approx(0.3 - fake.calls[0][2])
    fake.now += renderer.wait_seconds()
    assert renderer.step() and renderer.wait_seconds() == pytest.approx(fake.calls[-1][2])  # a strip, then as long a rest
    assert renderer.step() is False
    renderer.contended = lambda: False  # nobody else wants the CPU: no rest
    fake.now += renderer.wait_seconds()
    assert renderer.step() and renderer.wait_seconds() == 0.0
    for fov in (0.7, 0.6, 0.5):  # the browser sent three cameras while a strip rendered
        renderer.request(_camera(fov))
    renderer.request(_camera(0.5))  # and the last one again, as it does
    n = len(fake.calls)
    assert renderer.step() and len(fake.calls) == n + 1 and [f.level for f in frames] == [0, 0]
    focal = frames[-1].image.shape[0] / 2 / math.tan(0.5 / 2)
    assert frames[-1].view.rgb[0, 0, 0].item() == pytest.approx(focal, rel=1e-5)  # the newest camera
    assert renderer.step() is False  # moved again: refinement waits anew
    fake.now += 1.0
    _drain(renderer, fake.wait)
    assert [f.level for f in frames] == [0, 0, 1, 2]
    renderer.request(_camera(0.5))  # the camera on show, sent again: nothing to do
    assert not renderer.busy and renderer.wait_seconds() is None


def test_a_failing_render_drops_the_camera_and_goes_on(caplog):
    def broken(cams):
        raise RuntimeError("out of memory")

    renderer = ProgressiveRenderer(broken, lambda frame: None)
    renderer.request(ViewRequest(np.eye(4), 0.8, 1.0, time.perf_counter()))
    assert renderer.step() is False and not renderer.busy
    assert "live render failed (RuntimeError: out of memory)" in caplog.text


def test_a_camera_path_renders_headless_as_the_viewer_renders_it(run, tmp_path):
    """The goal: a path authored in the viewer, rendered by ``nerfpipe render --path``, gives the frames the
    viewer showed for it (strip by strip, through the same renderer), within 1/255."""
    source = open_source(run)
    eyes = torch.tensor([[3.0, -3.0, 1.5], [-3.0, -3.0, 2.0]], dtype=torch.float64)
    m = look_at(eyes, torch.zeros_like(eyes), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    keys = [Keyframe(m[0], 0.7, 1.25), Keyframe(m[1], 0.9, 1.25)]
    cams = path_from_keyframes(keys, 20, 16, num_frames=3)
    file = write_camera_path(tmp_path / "my_path.json", CameraPath(cams, keys, fps=10.0))
    assert main(["render", str(run), "--path", str(file), "--pngs"]) == 0
    import imageio.v3 as iio

    frames = []
    renderer = ProgressiveRenderer(source.render, frames.append, strip_seconds=0.0, settle=0.0, refine_share=1.0)
    for i in range(3):
        c = read_camera_path(file).cameras[i]
        fov = float(2 * torch.atan(c.height.double() / (2 * c.fy.double())))
        renderer.request(ViewRequest(c.world_from_cam.numpy(), fov, 20 / 16, time.perf_counter(), size=(20, 16)))
        _drain(renderer)
        headless = iio.imread(run / "render" / "my_path_frames" / f"{i:05d}.png")
        assert headless.shape == frames[-1].image.shape == (16, 20, 3)
        assert np.abs(headless.astype(int) - frames[-1].image.astype(int)).max() <= 1
    from nerfpipe.outputs.novel_views import RenderConfig, background

    src = open_source(run)  # the run's evaluation background (grey: its scene shows surroundings), as both renderers use it
    bg = background(RenderConfig(), json.loads((run / "config.json").read_text()), src.scene)
    whole = render_cameras(src.model, pinhole_camera(m[0].numpy(), 0.7, 20, 16), background=bg)[0]  # a whole frame = its strips
    assert (run / "render" / "my_path.gif").is_file() and whole.rgb.shape == (16, 20, 3)
    assert np.abs(to_uint8(whole.rgb).astype(int) - iio.imread(run / "render" / "my_path_frames" / "00000.png").astype(int)).max() <= 1


def test_bad_camera_path_and_missing_input_are_one_line_errors(run, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    assert main(["render", str(run), "--path", str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err
    assert main(["view", str(tmp_path / "nothing_here"), "--seconds", "0"]) == 2


# ---------------------------------------------------------------- the server and the page


def test_the_viewer_serves_its_page_on_a_free_port(synth, tmp_path):
    _viser()
    from nerfpipe.viewer.server import Viewer

    import trimesh

    mesh = tmp_path / "mesh" / "mesh.ply"
    mesh.parent.mkdir()
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    viewer = Viewer(load(synth), None, port=0, mesh=content.find_mesh([tmp_path]), thumbnails=False)
    try:
        page = urllib.request.urlopen(viewer.url, timeout=30).read().decode()
        assert "<html" in page.lower() and viewer.server.get_port() > 0
        assert set(viewer.layers) == {"/cameras", "/box", "/points", "/rays", "/mesh"} and viewer.layers["/mesh"][0].visible
    finally:
        viewer.stop()
    viewer = Viewer(load(synth), lambda cams: None, port=0, mesh=content.find_mesh([tmp_path]), thumbnails=False)
    try:  # with a live render the mesh starts hidden (it covers the render and slows the page's drawing)
        assert not viewer.layers["/mesh"][0].visible
    finally:
        viewer.stop()


def test_view_command_serves_a_dataset_and_finds_a_pipeline_runs_training(synth, tmp_path, capsys):
    _viser()
    from nerfpipe.training.runs import find_run

    assert main(["view", str(synth), "--port", "0", "--seconds", "0"]) == 0
    assert "(dataset (no trained field: no live render), 8 cameras) at http://localhost:" in capsys.readouterr().out
    (tmp_path / "pipeline" / "train").mkdir(parents=True)
    (tmp_path / "pipeline" / "train" / "config.json").write_text("{}")
    assert find_run(tmp_path / "pipeline") == tmp_path / "pipeline" / "train" and find_run(synth) is None


def test_in_headless_chromium_the_page_shows_the_cameras_and_the_live_render(run, tmp_path):
    """The page loads from the viewer alone (nothing from the internet), its scene holds one frustum per
    camera, the live render arrives, a keyframe placed from the browser's camera saves as a path, and
    the screenshot is not blank."""
    _viser()
    from nerfpipe.viewer.headless import BACKGROUND_JS, FRUSTUMS_JS, WATCH_MESSAGES_JS, Chromium, find_chromium
    from nerfpipe.viewer.progressive import RenderThread
    from nerfpipe.viewer.server import Viewer

    _require("chromium", find_chromium() is not None, "apt-get install chromium; scripts/bootstrap.sh --test does")
    source = open_source(run)
    viewer = Viewer(source.scene, source.render, port=0, path_file=tmp_path / "camera_path.json", max_size=64)
    thread = RenderThread(viewer.renderers)
    viewer.wake = thread.wake
    browser = Chromium(tmp_path / "profile", width=1000, height=700)
    try:
        browser.open(viewer.url)
        assert browser.wait_for(FRUSTUMS_JS, lambda n: n == len(source.scene.cameras), timeout=60.0) == len(source.scene.cameras)
        assert browser.wait_for(BACKGROUND_JS, timeout=60.0)[0] > 0
        browser.evaluate(WATCH_MESSAGES_JS)  # a move: the page sends the camera, a frame of it comes back
        moved = browser.evaluate("(() => { window.__viserMutable.cameraControl.rotate(0.3, 0.0, false); return Date.now(); })()")
        sent = browser.wait_for(f"window.__cameraSent.filter(e => e >= {moved})[0] || null", timeout=60.0)
        assert browser.wait_for(f"window.__imageReceived.filter(e => e >= {sent}).length", timeout=60.0) >= 1
        client = next(iter(viewer.server.get_clients().values()))
        viewer.add_keyframe_from(client)
        viewer.add_keyframe(Keyframe(viewer.keyframes[0].world_from_cam.clone(), 0.9, 1.0))
        saved = read_camera_path(viewer.save_path())
        assert len(saved.keyframes) == 2 and len(saved.cameras) == round(24 * 4.0)
        viewer.clear_keyframes()
        assert viewer.load_path() == 2 and viewer.path().cameras.world_from_cam.allclose(saved.cameras.world_from_cam, atol=1e-9)
        shot = browser.screenshot(tmp_path / "viewer.png")
        assert browser.outside_requests() == []
    finally:
        browser.close()
        thread.stop()
        viewer.stop()
    import imageio.v3 as iio

    img = iio.imread(shot)[..., :3].astype(float)
    assert img.shape[:2] == (700, 1000) and img.std() > 20.0
    assert len(np.unique(img.reshape(-1, 3)[::7], axis=0)) > 100  # frustums, points, panel text: not flat boxes


# ---------------------------------------------------------------- training watched


def test_a_watched_training_trains_as_an_unwatched_one(synth, tmp_path):
    """Rendering happens between steps within its share of the time, and puts the model's random stream
    back: the parameters after training are the same with and without the viewer."""
    _viser()
    from nerfpipe.fields.vanilla import VanillaFieldConfig
    from nerfpipe.models.vanilla import VanillaConfig
    from nerfpipe.training.trainer import Trainer, TrainerConfig
    from nerfpipe.viewer.training import watch

    scene = load(synth)
    model = VanillaConfig(num_samples=8, field=VanillaFieldConfig(width=16, depth=2, skip=1, head_width=8, pos_frequencies=4, dir_frequencies=2))
    cfg = TrainerConfig(iters=6, rays_per_step=64, eval_every=3, video_frames=0, write_outputs=False, seed=1)
    plain = Trainer(cfg, scene, "vanilla", model, tmp_path / "a")
    plain.train()
    watched = Trainer(cfg, scene, "vanilla", model, tmp_path / "b")
    view = watch(watched, port=0, share=1.0)
    eye = look_at(torch.tensor([0.0, -4.0, 1.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    frames = []
    renderer = ProgressiveRenderer(view.viewer.render, frames.append, max_size=32)
    view.viewer.renderer_of[0] = renderer
    renderer.request(ViewRequest(eye.numpy(), 0.8, 1.0, time.perf_counter()))
    try:
        watched.train()
    finally:
        view.viewer.stop()
    assert frames and view.render_seconds > 0
    for (name, a), b in zip(plain.model.state_dict().items(), watched.model.state_dict().values()):
        torch.testing.assert_close(a, b, msg=name)


def test_train_view_on_the_command_line_serves_and_closes(synth, tmp_path, capsys):
    _viser()
    args = ["train", str(synth), "--model", "vanilla", "--out", str(tmp_path / "run"), "--iters", "2", "--rays-per-step", "32",
            "--model.num-samples", "8", "--video-frames", "0", "--eval-every", "0", "--view", "--view-port", "0"]  # fmt: skip
    assert main(args) == 0
    out = capsys.readouterr().out
    url = out.split("watching the training at ")[1].split()[0]
    assert "the live view rendered" in out
    with pytest.raises(OSError):  # the page closed with the training
        urllib.request.urlopen(url, timeout=5)
