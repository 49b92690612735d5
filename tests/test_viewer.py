"""The browser viewer: what it draws, the live render (sizes, strips = whole frames), camera paths rendered
headless equal to the viewer's frames, the server, the page in headless Chromium, and training watched."""

import os
import time
import urllib.request

import numpy as np
import pytest
import torch

from nerfpipe.data_adapters import load
from nerfpipe.camera_path import CameraPath, Keyframe, path_from_keyframes, read_camera_path, write_camera_path
from nerfpipe.cli import main
from nerfpipe.orbit import look_at
from nerfpipe.render import render_cameras, to_uint8
from nerfpipe.viewer import content
from nerfpipe.viewer.progressive import ProgressiveRenderer, ViewRequest, pinhole_camera
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


def _drain(renderer: ProgressiveRenderer) -> None:
    while renderer.step():
        pass


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
    renderer = ProgressiveRenderer(source.render, frames.append, max_size=64, strip_seconds=0.0)  # one row per strip
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
    renderer = ProgressiveRenderer(source.render, frames.append, strip_seconds=0.0)
    for i in range(3):
        c = read_camera_path(file).cameras[i]
        fov = float(2 * torch.atan(c.height.double() / (2 * c.fy.double())))
        renderer.request(ViewRequest(c.world_from_cam.numpy(), fov, 20 / 16, time.perf_counter(), size=(20, 16)))
        _drain(renderer)
        headless = iio.imread(run / "render" / "my_path_frames" / f"{i:05d}.png")
        assert headless.shape == frames[-1].image.shape == (16, 20, 3)
        assert np.abs(headless.astype(int) - frames[-1].image.astype(int)).max() <= 1
    whole = render_cameras(open_source(run).model, pinhole_camera(m[0].numpy(), 0.7, 20, 16))[0]  # a whole frame = its strips
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
        assert set(viewer.layers) == {"/cameras", "/box", "/points", "/rays", "/mesh"}
    finally:
        viewer.stop()


def test_view_command_serves_a_dataset_and_finds_a_pipeline_runs_training(synth, tmp_path, capsys):
    _viser()
    from nerfpipe.runs import find_run

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
    from nerfpipe.viewer.headless import BACKGROUND_JS, FRUSTUMS_JS, Chromium, find_chromium
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
    from nerfpipe.trainer import Trainer, TrainerConfig
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
