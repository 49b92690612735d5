"""The browser viewer (viser): the scene's cameras, points, box, training rays and mesh, a live render of
the trained field from the browser's camera, and camera paths placed as keyframes.

viser is an optional dependency (``pip install 'nerfpipe[viewer]'``), imported when a
:class:`Viewer` is made; its web client is bundled in the package, so nothing is fetched at run time.

Scene tree (names under which things are drawn): ``/cameras/<split>/<index>`` (one frustum per
camera, its photo on it), ``/points``, ``/box``, ``/rays/lines`` and ``/rays/samples``, ``/mesh``,
``/path/keyframes/<i>`` and ``/path/spline``. The live render is viser's background image.

Rendering is driven from outside the server's threads: by a :class:`~nerfpipe.viewer.progressive.RenderThread`
(``nerfpipe view``), or by the training loop (:mod:`nerfpipe.viewer.training`), through :meth:`Viewer.renderers`.
"""

import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from nerfpipe.data.camera_path import CameraPath, Keyframe, matrix_to_wxyz, path_from_keyframes, wxyz_to_matrix
from nerfpipe.data.scene import SceneData
from nerfpipe.outputs.render import RenderedView
from nerfpipe.util.errors import NerfpipeError, require
from nerfpipe.viewer import content
from nerfpipe.viewer.progressive import Frame, ProgressiveRenderer, ViewRequest

VIEWER_DEPENDENCIES = (("viser", "viewer"),)
PREVIEW_HOLD = 2.0
"""Seconds after a path preview moved a browser's camera during which its camera updates are that move
(the browser's camera glides to a new pose over a few frames), not the user's."""


def camera_matrix(wxyz, position) -> np.ndarray:
    """``world_from_cam`` ``[4, 4]`` (float64) of a viser camera (OpenCV axes)."""
    m = np.eye(4)
    m[:3, :3] = wxyz_to_matrix(torch.as_tensor(np.asarray(wxyz, dtype=np.float64))).numpy()
    m[:3, 3] = np.asarray(position, dtype=np.float64)
    return m


class Viewer:
    """A viser server showing one scene (and, given ``render``, its trained field).

    Args:
        scene: the scene to show.
        render: renders a ``[1]`` batch of cameras with the trained model; None for a dataset alone.
        host: interface to serve on (``127.0.0.1``: this machine only).
        port: port (0: a free one).
        path_file: where "save path" writes the camera path.
        mesh: a mesh file to show (in the input frame, as ``nerfpipe mesh`` writes it).
        max_size: longer side of the sharpest live frame, in pixels.
        thumbnails: put each camera's photo on its frustum (read in a background thread).
    """

    def __init__(
        self,
        scene: SceneData,
        render: "Callable | None",
        host: str = "127.0.0.1",
        port: int = 0,
        path_file: Path = Path("camera_path.json"),
        mesh: "Path | None" = None,
        max_size: int = 512,
        thumbnails: bool = True,
    ) -> None:
        viser = require("viser", "viewer")
        self.scene, self.render, self.path_file, self.max_size = scene, render, Path(path_file), max_size
        self.server = viser.ViserServer(host=host, port=_free_port(host) if port == 0 else port, label="nerfpipe", verbose=False)
        self.renderer_of: "dict[int, ProgressiveRenderer]" = {}
        self.frames: "list[dict]" = []
        """Every frame shown: ``client``, ``level``, ``levels``, ``width``, ``height``, ``seconds``, ``latency``, ``shown`` (wall time)."""
        self.preview_frames: "dict[int, np.ndarray]" = {}
        """The last finished image of each previewed path frame (uint8, the path's size)."""
        self.keyframes: "list[Keyframe]" = []
        self.wake: "Callable[[], None]" = lambda: None
        """Called when a renderer got work (the render thread's ``wake``)."""
        self._preview: "dict[int, tuple[np.ndarray, float]]" = {}
        """Per client, the pose a path preview put its camera at, and until when its moves are the browser getting there."""
        self._preview_index: "dict[int, int]" = {}
        """Per client, the path frame it previews."""
        self.layers: "dict[str, list]" = {}
        """Handles of what is drawn, per layer (``/cameras``, ``/points``, ...), for the visibility boxes."""
        self._lock = threading.Lock()
        self._stopped = False
        self._first_frame = threading.Event()
        """Set when the first live frame was shown: the photos on the frustums wait for it (decoding them competes for the CPU)."""
        self._draw_scene(mesh, thumbnails)
        self._build_gui()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda client: self.renderer_of.pop(client.client_id, None))

    # ---------------------------------------------------------------- the scene
    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'localhost' if host in ('0.0.0.0', '127.0.0.1') else host}:{self.server.get_port()}"

    def _draw_scene(self, mesh: "Path | None", thumbnails: bool) -> None:
        s, scene = self.server.scene, self.scene
        self.frustum_handles = {}
        scale = content.frustum_scale(scene)
        diagonal = float(np.linalg.norm(scene.aabb.double().numpy()[1] - scene.aabb.double().numpy()[0]))
        for f in content.frustums(scene):
            self.frustum_handles[f.name] = s.add_camera_frustum(
                f"/cameras/{f.name}", fov=f.fov, aspect=f.aspect, scale=scale, color=content.SPLIT_COLOURS[f.split],
                wxyz=f.wxyz, position=f.position, thickness=0.0015 * scale / 0.06, variant="wireframe")  # fmt: skip
        self.layers["/cameras"] = list(self.frustum_handles.values())
        self.layers["/box"] = [s.add_line_segments("/box", content.box_segments(scene.aabb), (230, 60, 60), thickness=0.004 * diagonal)]
        points = content.sparse_points(scene)
        if points is not None:
            self.layers["/points"] = [s.add_point_cloud("/points", points[0], points[1], point_size=0.004 * diagonal)]
        lines, samples = content.training_rays(scene, num_rays=24)
        if len(lines):
            self.layers["/rays"] = [s.add_line_segments("/rays/lines", lines, (250, 200, 40), thickness=0.0005 * diagonal),
                                    s.add_point_cloud("/rays/samples", samples, (250, 80, 40), point_size=0.006 * diagonal)]  # fmt: skip
        if mesh is not None:
            import trimesh

            v, f, colours = content.read_mesh(mesh, scene)
            shown = trimesh.Trimesh(v, f, vertex_colors=colours, process=False)
            handle = s.add_mesh_trimesh("/mesh", shown) if colours is not None else s.add_mesh_simple("/mesh", v, f, color=(200, 200, 200))
            # hidden while there is a live render: it covers the render, and the browser drawing its faces
            # (software WebGL, 100k faces) took 0.5 s a frame on this CPU, to the page showing a new frame
            handle.visible = self.render is None
            self.layers["/mesh"] = [handle]
        self._set_initial_camera()
        self._thumbnails = threading.Thread(target=self._add_thumbnails, name="nerfpipe-view-thumbnails", daemon=True)
        if thumbnails:
            self._thumbnails.start()

    def _set_initial_camera(self) -> None:
        train = self.scene.splits["train"]
        first = int(train[0]) if len(train) else 0
        cams = self.scene.cameras
        centre = self.scene.aabb.double().mean(0).numpy()
        eye = centre + 1.8 * (cams.centers[first].double().numpy() - centre)  # behind the first camera: the rig in view
        self.server.initial_camera.position = tuple(eye)
        self.server.initial_camera.look_at = tuple(centre)
        self.server.initial_camera.fov = float(2 * torch.atan(cams.height[first].double() / (2 * cams.fy[first].double())))

    def _add_thumbnails(self) -> None:
        """Every photo shrunk first, then all sent at once: the page takes them in one frame (one at a
        time, each cost the browser a frame of its software WebGL, and the page lagged for seconds)."""
        self._first_frame.wait(timeout=None if self.render is not None else 0.0)
        images, shrunk = self.scene.images, {}
        for name in list(self.frustum_handles):
            i = int(name.split("/")[1])
            if self._stopped:
                return
            if images.has(i):
                try:
                    shrunk[name] = content.thumbnail(images.load(i))
                except Exception:  # noqa: BLE001 - a photo that does not decode stays a bare frustum
                    continue
        with self.server.atomic():
            for name, image in shrunk.items():
                self.frustum_handles[name].image = image

    # ---------------------------------------------------------------- the panel
    def _build_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Live render"):
            self.mode = gui.add_dropdown("Show", ("rgb", "depth"), initial_value="rgb")
            self.size_slider = gui.add_slider("Max size (px)", min=64, max=2048, step=32, initial_value=self.max_size)
            self.status = gui.add_markdown("no trained field: cameras and points only" if self.render is None else "waiting for the browser's camera")
        self.mode.on_update(lambda _: self._settings_changed())
        self.size_slider.on_update(lambda _: self._settings_changed())
        with gui.add_folder("Layers"):
            for label, node in (("Cameras", "/cameras"), ("Points", "/points"), ("Box", "/box"), ("Training rays", "/rays"), ("Mesh", "/mesh")):
                if node in self.layers:
                    box = gui.add_checkbox(label, initial_value=all(h.visible for h in self.layers[node]))
                    box.on_update(lambda e, node=node: self._set_visible(node, e.target.value))
        self._build_path_gui()

    def _set_visible(self, node: str, visible: bool) -> None:
        for handle in self.layers.get(node, []):
            handle.visible = visible

    def _build_path_gui(self) -> None:
        gui = self.server.gui
        cams = self.scene.split_cameras("train")
        w, h = (int(cams.width[0]), int(cams.height[0])) if len(cams) else (640, 480)
        from nerfpipe.outputs.render import capped_size

        w, h = capped_size(w, h, 1.0, 800)
        with gui.add_folder("Camera path"):
            add = gui.add_button("Add keyframe")
            clear = gui.add_button("Clear keyframes")
            self.path_width = gui.add_number("Width", initial_value=w, min=8, max=8192, step=1)
            self.path_height = gui.add_number("Height", initial_value=h, min=8, max=8192, step=1)
            self.path_fps = gui.add_number("FPS", initial_value=24.0, min=1.0, max=240.0, step=1.0)
            self.path_seconds = gui.add_number("Seconds", initial_value=4.0, min=0.1, max=3600.0, step=0.1)
            self.path_cycle = gui.add_checkbox("Loop", initial_value=False)
            self.path_name = gui.add_text("File", initial_value=str(self.path_file))
            save = gui.add_button("Save path")
            load = gui.add_button("Load path")
            self.preview = gui.add_slider("Preview frame", min=0, max=1, step=1, initial_value=0, disabled=True)
            self.path_status = gui.add_markdown("place keyframes from the current view")
        add.on_click(lambda e: self.add_keyframe_from(e.client))
        clear.on_click(lambda _: self.clear_keyframes())
        save.on_click(lambda _: self.save_path())
        load.on_click(lambda _: self.load_path())
        self.preview.on_update(lambda e: self.preview_frame(int(e.target.value), e.client))

    # ---------------------------------------------------------------- live render
    def _connect(self, client) -> None:
        if self.render is None:
            return
        renderer = ProgressiveRenderer(self.render, lambda frame: self._show(client, frame), max_size=int(self.size_slider.value))
        renderer.mode = self.mode.value
        self.renderer_of[client.client_id] = renderer
        client.camera.on_update(lambda camera: self._camera_moved(client, camera))

    def renderers(self) -> "list[ProgressiveRenderer]":
        return list(self.renderer_of.values())

    def _camera_moved(self, client, camera) -> None:
        m = camera_matrix(camera.wxyz, camera.position)
        preview = self._preview.get(client.client_id)
        if preview is not None and (np.abs(preview[0] - m).max() < 1e-5 or time.monotonic() < preview[1]):
            return  # the browser moving to (and reporting) the pose a preview set
        self._preview.pop(client.client_id, None)
        self._preview_index.pop(client.client_id, None)
        renderer = self.renderer_of.get(client.client_id)
        if renderer is not None:
            renderer.request(ViewRequest(m, float(camera.fov), float(camera.aspect), time.perf_counter()))
            self.wake()

    def _settings_changed(self) -> None:
        for r in self.renderers():
            r.mode, r.max_size = self.mode.value, int(self.size_slider.value)
            r.refresh()
        self.wake()

    def _show(self, client, frame: Frame) -> None:
        h, w = frame.image.shape[:2]
        self._first_frame.set()
        final = frame.level == frame.levels
        client.scene.set_background_image(frame.image, format="png" if final else "jpeg", jpeg_quality=85)
        rays_s = w * h / max(frame.seconds, 1e-9)
        label = "low" if frame.level == 0 else f"{frame.level}/{frame.levels}"
        self.status.content = f"{w}x{h} ({label}) in **{frame.seconds:.2f} s** ({rays_s / 1000:.0f} k rays/s); {frame.latency:.2f} s after the move"
        with self._lock:
            self.frames.append({"client": client.client_id, "level": frame.level, "levels": frame.levels, "width": w, "height": h,
                                "seconds": frame.seconds, "latency": frame.latency, "shown": time.time()})  # fmt: skip
            preview = self._preview_index.get(client.client_id)
            if preview is not None and final and (w, h) == self._path_size():
                self.preview_frames[preview] = frame.image

    # ---------------------------------------------------------------- camera paths
    def add_keyframe_from(self, client) -> Keyframe:
        """A keyframe at a client's current camera (the browser's view)."""
        camera = client.camera
        key = Keyframe(torch.as_tensor(camera_matrix(camera.wxyz, camera.position)), float(camera.fov), float(camera.aspect))
        return self.add_keyframe(key)

    def add_keyframe(self, key: Keyframe) -> Keyframe:
        self.keyframes.append(key)
        i = len(self.keyframes) - 1
        handle = self.server.scene.add_camera_frustum(
            f"/path/keyframes/{i}", fov=key.fov, aspect=key.aspect, scale=content.frustum_scale(self.scene) * 1.5, color=(250, 220, 0),
            wxyz=matrix_to_wxyz(key.world_from_cam[:3, :3].double()).numpy(), position=key.world_from_cam[:3, 3].double().numpy())  # fmt: skip
        self.layers.setdefault("/path", []).append(handle)
        self._path_changed()
        return key

    def clear_keyframes(self) -> None:
        self.keyframes = []
        for handle in self.layers.pop("/path", []):
            handle.remove()
        self._path_changed()

    def _path_size(self) -> "tuple[int, int]":
        return int(self.path_width.value), int(self.path_height.value)

    def path(self) -> "CameraPath | None":
        """The camera path the keyframes make at the panel's size, frames per second and length."""
        if not self.keyframes:
            return None
        frames = max(1, round(float(self.path_fps.value) * float(self.path_seconds.value)))
        w, h = self._path_size()
        cams = path_from_keyframes(self.keyframes, w, h, frames, bool(self.path_cycle.value))
        return CameraPath(cams, list(self.keyframes), float(self.path_fps.value), bool(self.path_cycle.value))

    def _path_changed(self) -> None:
        path = self.path()
        n = 0 if path is None else len(path.cameras)
        self.preview.max, self.preview.disabled = max(1, n - 1), n < 2
        if path is not None and len(self.keyframes) > 1:
            pos = path.cameras.centers.double().numpy()
            spline = self.server.scene.add_line_segments("/path/spline", np.stack([pos[:-1], pos[1:]], 1), (250, 220, 0), thickness=0.05 * content.frustum_scale(self.scene))
            self.layers.setdefault("/path", []).append(spline)
        self.path_status.content = f"{len(self.keyframes)} keyframes, {n} frames"

    def save_path(self, file: "Path | None" = None) -> Path:
        """Write the camera path (nerfstudio's ``camera_path.json``) to ``file`` (default: the panel's)."""
        from nerfpipe.data.camera_path import write_camera_path

        path = self.path()
        if path is None:
            self.path_status.content = "add a keyframe first"
            raise NerfpipeError("the camera path has no keyframes")
        target = Path(file) if file is not None else Path(self.path_name.value)
        write_camera_path(target, path, self.scene.world_from_input.matrix())
        self.path_status.content = f"saved {len(path.cameras)} frames to `{target}`"
        return target

    def load_path(self, file: "Path | None" = None) -> int:
        """Replace the keyframes by those of a camera path file (default: the panel's); returns how many."""
        from nerfpipe.data.camera_path import read_camera_path

        target = Path(file) if file is not None else Path(self.path_name.value)
        try:
            path = read_camera_path(target)
        except NerfpipeError as exc:
            self.path_status.content = f"cannot load: {exc}"
            return 0
        self.clear_keyframes()
        cams = path.cameras
        self.path_width.value, self.path_height.value = int(cams.width[0]), int(cams.height[0])
        self.path_fps.value, self.path_cycle.value = path.fps, path.is_cycle
        self.path_seconds.value = len(cams) / path.fps
        for key in path.keyframes:
            self.add_keyframe(key)
        self.path_status.content = f"loaded {len(path.keyframes)} keyframes from `{target}`"
        return len(path.keyframes)

    def preview_frame(self, index: int, client) -> None:
        """Move a client's camera to frame ``index`` of the path and render that frame at the path's size."""
        path = self.path()
        renderer = self.renderer_of.get(client.client_id) if client is not None else None
        if path is None or renderer is None or not 0 <= index < len(path.cameras):
            return
        cam = path.cameras[index]
        m = cam.world_from_cam.double().numpy()
        fov = float(2 * torch.atan(cam.height.double() / (2 * cam.fy.double())))
        self._preview_index[client.client_id] = index
        self._preview[client.client_id] = (m, time.monotonic() + PREVIEW_HOLD)
        with client.atomic():
            client.camera.wxyz = matrix_to_wxyz(torch.as_tensor(m[:3, :3])).numpy()
            client.camera.position = m[:3, 3]
            client.camera.fov = fov
        w, h = self._path_size()
        renderer.request(ViewRequest(m, fov, w / h, time.perf_counter(), size=(w, h)))
        self.wake()

    def stop(self) -> None:
        self._stopped = True
        self._first_frame.set()
        if self._thumbnails.is_alive():
            self._thumbnails.join(timeout=10)
        self.server.stop()


def _free_port(host: str) -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host if host != "0.0.0.0" else "", 0))
        return s.getsockname()[1]


__all__ = ["VIEWER_DEPENDENCIES", "Viewer", "camera_matrix"]
