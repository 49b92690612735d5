"""Camera paths as files: nerfstudio's ``camera_path.json``, read and written, and keyframe interpolation.

The file (the format nerfstudio's viewer saves and ``ns-render camera-path`` reads)::

    {"camera_type": "perspective", "render_width": 640, "render_height": 480, "fps": 24, "seconds": 4,
     "is_cycle": false, "smoothness_value": 0.0,
     "keyframes": [{"matrix": [16 numbers], "fov": 50.0, "aspect": 1.333, ...}, ...],
     "camera_path": [{"camera_to_world": [16 numbers], "fov": 50.0, "aspect": 1.333}, ...]}

Convention, stated once:

* ``camera_to_world`` and a keyframe's ``matrix``: a 4x4 camera-to-world matrix flattened **row-major**,
  camera axes **OpenGL** (+x right, +y up, looks along -z), as nerfstudio writes them. nerfpipe's
  :class:`~nerfpipe.data.cameras.Cameras` are OpenCV; the two differ by flipping the camera's y and z axes.
* the world frame is **the run's world** (nerfpipe's normalised world, where training happened; see
  :mod:`nerfpipe.data.scene`). nerfstudio's own files are in nerfstudio's normalised world, which is another
  similarity of the input frame: such a file renders on a nerfpipe run of the same data only after
  mapping it (``"nerfpipe": {"world_from_input": ...}`` in the files we write records ours).
* ``fov`` is the **vertical** field of view in degrees; ``aspect`` is width / height; frames are
  ``render_width`` x ``render_height`` pixels with square pixels and the principal point at the centre
  (nerfstudio's reading: ``fy = fx = (H / 2) / tan(fov / 2)``, ``cx = W / 2``, ``cy = H / 2``).
* exact intrinsics: each ``camera_path`` entry we write also carries ``"nerfpipe": {fx, fy, cx, cy,
  width, height, distortion, dist_params}`` (readers that do not know the key ignore it), so a path of
  real cameras (non-square pixels, off-centre principal points, distortion) comes back unchanged.

Keyframes (``keyframes``) are what the viewer places; ``camera_path`` holds the frames interpolated from
them (:func:`interpolate_keyframes`), which is what a renderer reads: nerfpipe renders ``camera_path``.

Glossary:
    wxyz   unit quaternion (scalar first) of a rotation
    fov    vertical field of view (radians in code, degrees in the file)
"""

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from nerfpipe.data.cameras import Cameras, opengl_to_opencv
from nerfpipe.functional.distortion import Distortion
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.typing import Float, Tensor

EXTRA_KEY = "nerfpipe"
"""Key of nerfpipe's additions in the file (exact intrinsics per frame, the world frame) that other readers ignore."""


@dataclass
class Keyframe:
    """A camera the user placed; the path passes through it."""

    world_from_cam: Float[Tensor, "4 4"]
    """Camera-to-world rigid transform, OpenCV camera axes (float64)."""
    fov: float
    """Vertical field of view in radians."""
    aspect: float
    """Width over height."""


@dataclass
class CameraPath:
    """A camera path file's content."""

    cameras: Cameras
    """The frames to render ``[num_frames]`` (OpenCV, the run's world frame)."""
    keyframes: "list[Keyframe]"
    """The keyframes the frames were interpolated from (may be empty: a path written by another tool)."""
    fps: float = 24.0
    """Frames per second of the video."""
    is_cycle: bool = False
    """Whether the path returns to its first keyframe."""
    smoothness: float = 0.0
    """Tension of the spline through the keyframes (0: Catmull-Rom; 1: straight lines between them)."""


# ---------------------------------------------------------------- rotations


def matrix_to_wxyz(rot: Float[Tensor, "*bs 3 3"]) -> Float[Tensor, "*bs 4"]:
    """Unit quaternions (w >= 0) of rotation matrices (Shepperd's method: the largest diagonal term first).

    Example:
        >>> matrix_to_wxyz(torch.eye(3, dtype=torch.float64)).tolist()
        [1.0, 0.0, 0.0, 0.0]
    """
    m = rot
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    candidates = torch.stack([  # 4 * q * q_k for k = w, x, y, z: each row is exact, pick the best conditioned
        torch.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1),
    ], dim=-2)  # fmt: skip
    diag = torch.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = diag.argmax(-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = torch.nn.functional.normalize(q, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def wxyz_to_matrix(q: Float[Tensor, "*bs 4"]) -> Float[Tensor, "*bs 3 3"]:
    """Rotation matrices of (not necessarily unit) quaternions, scalar first."""
    w, x, y, z = torch.nn.functional.normalize(q, dim=-1).unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


# ---------------------------------------------------------------- interpolation


def _cardinal(p: Tensor, t: Tensor, tension: float) -> Tensor:
    """Cardinal spline through the inner rows of ``p [K + 2, D]`` at parameters ``t in [0, 1]`` (``[N]``).

    ``p[0]`` and ``p[-1]`` only shape the end tangents. Segment ``i`` joins ``p[i+1]`` and ``p[i+2]``
    as a cubic Hermite curve with tangents ``(1 - tension) * (p[j+1] - p[j-1]) / 2`` at each end ``j``.
    """
    segments = len(p) - 3
    s = (t * segments).clamp(0, segments)
    i = s.floor().long().clamp(max=segments - 1)
    u = (s - i)[:, None]
    p0, p1, p2, p3 = p[i], p[i + 1], p[i + 2], p[i + 3]
    m1, m2 = (1 - tension) * (p2 - p0) / 2, (1 - tension) * (p3 - p1) / 2
    u2, u3 = u * u, u * u * u
    return (2 * u3 - 3 * u2 + 1) * p1 + (u3 - 2 * u2 + u) * m1 + (-2 * u3 + 3 * u2) * p2 + (u3 - u2) * m2


def interpolate_keyframes(
    keyframes: "list[Keyframe]", num_frames: int, is_cycle: bool = False, smoothness: float = 0.0
) -> "tuple[Float[Tensor, 'num_frames 4 4'], Float[Tensor, 'num_frames']]":
    """``(world_from_cam, fov)`` of ``num_frames`` cameras along a smooth path through the keyframes.

    Keyframes are equally spaced in time. Positions, orientations (quaternions, each turned onto its
    predecessor's hemisphere, normalised after interpolation) and fields of view follow one cardinal
    spline (:func:`_cardinal`, tension ``smoothness``). An open path's first and last frames are its
    first and last keyframes (its end tangents repeat the end keyframe); a cycle goes on to its first
    keyframe, its frames ``i / num_frames`` of the way round, so it loops without repeating a frame.
    """
    if not keyframes:
        raise NerfpipeError("a camera path needs at least one keyframe")
    if num_frames < 1:
        raise NerfpipeError(f"a camera path needs at least one frame, got {num_frames}")
    m = torch.stack([k.world_from_cam.double() for k in keyframes])
    fov = torch.tensor([k.fov for k in keyframes], dtype=torch.float64)[:, None]
    control = torch.cat([m[:, :3, 3], matrix_to_wxyz(m[:, :3, :3]), fov], dim=1)
    n = len(keyframes)
    order = [n - 1, *range(n), 0, 1 % n] if is_cycle else [0, *range(n), n - 1]
    control = control[order]
    for i in range(1, len(control)):  # the shorter way round between neighbours
        if float(control[i, 3:7] @ control[i - 1, 3:7]) < 0:
            control[i, 3:7] = -control[i, 3:7]
    t = torch.arange(num_frames, dtype=torch.float64) / (num_frames if is_cycle else max(num_frames - 1, 1))
    out = _cardinal(control, t, smoothness) if len(control) >= 4 else control[1:2].expand(num_frames, -1)
    world_from_cam = torch.eye(4, dtype=torch.float64).repeat(num_frames, 1, 1)
    world_from_cam[:, :3, :3] = wxyz_to_matrix(out[:, 3:7])
    world_from_cam[:, :3, 3] = out[:, :3]
    return world_from_cam, out[:, 7]


def path_from_keyframes(
    keyframes: "list[Keyframe]", width: int, height: int, num_frames: int, is_cycle: bool = False, smoothness: float = 0.0
) -> Cameras:
    """Pinhole cameras of ``width x height`` pixels along :func:`interpolate_keyframes` (square pixels,
    principal point at the centre, as nerfstudio renders a path)."""
    world_from_cam, fov = interpolate_keyframes(keyframes, num_frames, is_cycle, smoothness)
    focal = (height / 2) / torch.tan(fov / 2)
    return Cameras.create(world_from_cam, focal, focal, width / 2, height / 2, width, height, dtype=torch.float64)


# ---------------------------------------------------------------- to and from the file


def _gl_rows(world_from_cam_cv: Tensor) -> "list[float]":
    """Row-major OpenGL camera-to-world numbers (``opengl_to_opencv`` is its own inverse)."""
    return [float(v) for v in opengl_to_opencv(world_from_cam_cv.double()).reshape(16)]


def to_json(path: CameraPath, world_from_input: "Float[Tensor, '4 4'] | None" = None) -> dict:
    """The file's content for a path (see the module docstring); ``world_from_input`` is recorded when given."""
    cams = path.cameras.reshape(-1)
    if len(cams) == 0:
        raise NerfpipeError("a camera path needs at least one frame")
    frames = []
    for i in range(len(cams)):
        c = cams[i]
        w, h = int(c.width), int(c.height)
        extra = {"fx": float(c.fx), "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy), "width": w, "height": h,
                 "distortion": Distortion(int(c.distortion)).name, "dist_params": [float(v) for v in c.dist_params]}  # fmt: skip
        fov = math.degrees(2 * math.atan(h / (2 * float(c.fy))))
        frames.append({"camera_to_world": _gl_rows(c.world_from_cam), "fov": fov, "aspect": w / h, EXTRA_KEY: extra})
    keyframes = [{"matrix": _gl_rows(k.world_from_cam), "fov": math.degrees(k.fov), "aspect": k.aspect,
                  "override_transition_enabled": False, "override_transition_sec": None} for k in path.keyframes]  # fmt: skip
    first = cams[0]
    out = {
        "camera_type": "perspective",
        "render_width": int(first.width),
        "render_height": int(first.height),
        "fps": path.fps,
        "seconds": len(cams) / path.fps,
        "is_cycle": path.is_cycle,
        "smoothness_value": path.smoothness,
        "keyframes": keyframes,
        "camera_path": frames,
        EXTRA_KEY: {"frame": "the run's world (nerfpipe's normalised frame); OpenGL camera axes, matrices row-major"},
    }
    if world_from_input is not None:
        out[EXTRA_KEY]["world_from_input"] = [float(v) for v in world_from_input.double().reshape(16)]
    return out


def _matrix(value, what: str, source) -> Tensor:
    try:
        m = torch.tensor(value, dtype=torch.float64).reshape(4, 4)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise NerfpipeError(f"{what} must be 16 numbers (a row-major 4x4 matrix)", source) from exc
    rot = m[:3, :3]
    if not torch.isfinite(m).all() or not torch.allclose(rot @ rot.T, torch.eye(3, dtype=torch.float64), atol=1e-4):
        raise NerfpipeError(f"{what} is not a rigid camera-to-world transform (its rotation is not orthonormal)", source)
    return opengl_to_opencv(m)


def _number(entry: dict, key: str, what: str, source, positive: bool = True) -> float:
    value = entry.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or (positive and value <= 0):
        raise NerfpipeError(f"{what} '{key}' must be a {'positive ' if positive else ''}number, got {value!r}", source)
    return float(value)


def _frame(entry, i: int, width: int, height: int, source) -> "tuple[Tensor, list]":
    """``(world_from_cam, [fx, fy, cx, cy, w, h, distortion, k1..k4])`` of one ``camera_path`` entry."""
    what = f"camera_path[{i}]"
    if not isinstance(entry, dict):
        raise NerfpipeError(f"{what} must be an object", source)
    m = _matrix(entry.get("camera_to_world"), f"{what}.camera_to_world", source)
    extra = entry.get(EXTRA_KEY)
    if isinstance(extra, dict):
        fx, fy, cx, cy = (_number(extra, k, what, source, positive=k in ("fx", "fy")) for k in ("fx", "fy", "cx", "cy"))
        w, h = int(_number(extra, "width", what, source)), int(_number(extra, "height", what, source))
        try:
            code = int(Distortion[str(extra.get("distortion", "NONE"))])
            params = [float(v) for v in extra.get("dist_params", [0.0] * 4)][:4]
        except (KeyError, TypeError, ValueError) as exc:
            raise NerfpipeError(f"{what}: unknown distortion {extra.get('distortion')!r} or bad dist_params", source) from exc
        return m, [fx, fy, cx, cy, w, h, code, *params, *[0.0] * (4 - len(params))]
    fov = _number(entry, "fov", what, source)
    if fov >= 180:
        raise NerfpipeError(f"{what} 'fov' must be below 180 degrees, got {fov}", source)
    focal = (height / 2) / math.tan(math.radians(fov) / 2)
    return m, [focal, focal, width / 2, height / 2, width, height, int(Distortion.NONE), 0.0, 0.0, 0.0, 0.0]


def _keyframes(data: dict, source) -> "list[Keyframe]":
    out = []
    for i, k in enumerate(data.get("keyframes") or []):
        if not isinstance(k, dict):
            raise NerfpipeError(f"keyframes[{i}] must be an object", source)
        m = _matrix(k.get("matrix"), f"keyframes[{i}].matrix", source)
        out.append(Keyframe(m, math.radians(_number(k, "fov", f"keyframes[{i}]", source)), _number(k, "aspect", f"keyframes[{i}]", source)))
    return out


def from_json(data, source: "str | Path | None" = None) -> CameraPath:
    """A :class:`CameraPath` from a file's content; anything malformed is one error naming ``source``."""
    if not isinstance(data, dict):
        raise NerfpipeError("not a camera path (the JSON is not an object)", source)
    kind = data.get("camera_type", "perspective")
    if kind not in ("perspective", "pinhole"):
        raise NerfpipeError(f"camera_type '{kind}' is not supported (perspective only)", source)
    frames = data.get("camera_path")
    if not isinstance(frames, list) or not frames:
        raise NerfpipeError("not a camera path: 'camera_path' must be a non-empty list of cameras", source)
    width, height = (int(_number(data, k, "the path's", source)) for k in ("render_width", "render_height"))
    parsed = [_frame(entry, i, width, height, source) for i, entry in enumerate(frames)]
    values = torch.tensor([p[1] for p in parsed], dtype=torch.float64)
    cams = Cameras.create(torch.stack([p[0] for p in parsed]), *values[:, :6].unbind(1), distortion=values[:, 6].long(),
                          dist_params=values[:, 7:], dtype=torch.float64)  # fmt: skip
    fps = _number(data, "fps", "the path's", source) if "fps" in data else 24.0
    smooth = _number(data, "smoothness_value", "the path's", source, positive=False) if "smoothness_value" in data else 0.0
    return CameraPath(cams, _keyframes(data, source), fps, bool(data.get("is_cycle", False)), smooth)


def read_camera_path(path: "str | Path") -> CameraPath:
    """Read a ``camera_path.json`` (ours or nerfstudio's; see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise NerfpipeError("no such camera path file", path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise NerfpipeError(f"cannot read the camera path ({type(exc).__name__}: {exc})", path) from exc
    return from_json(data, path)


def write_camera_path(path: "str | Path", camera_path: CameraPath, world_from_input: "Float[Tensor, '4 4'] | None" = None) -> Path:
    """Write a ``camera_path.json`` atomically; returns its path."""
    from nerfpipe.util.atomic import write_json

    write_json(Path(path), to_json(camera_path, world_from_input))
    return Path(path)


__all__ = [
    "CameraPath", "Keyframe", "from_json", "interpolate_keyframes", "matrix_to_wxyz", "path_from_keyframes",
    "read_camera_path", "to_json", "write_camera_path", "wxyz_to_matrix",
]  # fmt: skip
