"""Camera paths for novel views: a generated orbit around the scene centre, upright, looking at it (or, for a photo
collection taken from near and far, a path along the photographs' own viewpoints).

World up is +z (the Blender/CS180 frame is z-up, and :mod:`nerfpipe.data.normalize` turns real captures
so the mean camera up is +z). Cameras use the OpenCV axes of :mod:`nerfpipe.data.cameras`.
"""

import math

import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.util.typing import Float, Tensor

WORLD_UP = (0.0, 0.0, 1.0)


def look_at(eye: Float[Tensor, "*bs 3"], target: Float[Tensor, "*bs 3"], up: Float[Tensor, "3"]) -> Float[Tensor, "*bs 4 4"]:
    """``world_from_cam`` of cameras at ``eye`` looking at ``target``, image up towards ``up``.

    Example:
        >>> m = look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
        >>> m[:3, :3].T.tolist()  # rows: right, down, forward
        [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    """
    fwd = torch.nn.functional.normalize(target - eye, dim=-1)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, up.expand_as(fwd)), dim=-1)
    down = torch.linalg.cross(fwd, right)
    m = torch.zeros(*eye.shape[:-1], 4, 4, dtype=eye.dtype, device=eye.device)
    m[..., :3, 0], m[..., :3, 1], m[..., :3, 2], m[..., :3, 3] = right, down, fwd, eye
    m[..., 3, 3] = 1.0
    return m


ARC_GAP = math.pi / 2
"""An azimuth gap between the reference cameras wider than this (seen from the centre) means they were not
taken all round: the path sweeps the arc they cover, back and forth, instead of showing the unseen side."""


def covered_arc(azimuths: Float[Tensor, "num_cameras"], gap: float = ARC_GAP) -> "tuple[float, float]":
    """``(start, span)`` in radians of the arc the cameras' ``azimuths`` cover, counter-clockwise from ``start``:
    the full circle (``span`` 2 pi, from the first camera) unless they leave a gap wider than ``gap``."""
    a = torch.sort(torch.remainder(azimuths.double().reshape(-1), 2 * math.pi)).values
    if len(a) < 2:
        return (float(a[0]) if len(a) else 0.0), 2 * math.pi
    gaps = torch.diff(torch.cat([a, a[:1] + 2 * math.pi]))
    widest = int(gaps.argmax())
    if float(gaps[widest]) <= gap:
        return float(a[0]), 2 * math.pi
    return float(a[(widest + 1) % len(a)]), 2 * math.pi - float(gaps[widest])


def azimuths(cameras: Cameras, center: Float[Tensor, "3"]) -> Float[Tensor, "num_cameras"]:
    """Each camera's azimuth about ``center`` (radians, about +z, the world's up)."""
    offsets = cameras.centers.double().reshape(-1, 3) - center.double()
    return torch.atan2(offsets[:, 1], offsets[:, 0])


def camera_arc(cameras: Cameras, center: Float[Tensor, "3"]) -> float:
    """The azimuth arc (radians) ``cameras`` cover about ``center`` (:func:`covered_arc`; ``SceneInfo.arc``): 2 pi
    when they surround it with no gap wider than :data:`ARC_GAP`, 0 for fewer than three."""
    return covered_arc(azimuths(cameras, center))[1] if len(cameras) >= 3 else 0.0


def orbit_azimuths(azimuths: Float[Tensor, "num_cameras"], num_frames: int, gap: float = ARC_GAP) -> Float[Tensor, "num_frames"]:
    """Azimuths of the path's frames: a full circle when the cameras' ``azimuths`` (radians) leave no gap wider
    than ``gap``, else the arc they cover (:func:`covered_arc`), there and back (eased at its ends, so the loop
    is smooth)."""
    frames = torch.arange(num_frames, dtype=torch.float64)
    start, span = covered_arc(azimuths, gap)
    if span >= 2 * math.pi:
        return start + frames * (2 * math.pi / num_frames)
    return start + span * there_and_back(num_frames)


def there_and_back(num_frames: int) -> Float[Tensor, "num_frames"]:
    """Each frame's place in ``[0, 1]`` on a path swept there and back, eased at its ends so the loop is smooth."""
    return 0.5 - 0.5 * torch.cos(torch.arange(num_frames, dtype=torch.float64) * (2 * math.pi / num_frames))


def field_of_view(cameras: Cameras) -> Float[Tensor, "num_cameras"]:
    """Each camera's mean focal length over its image diagonal (float64, flat)."""
    flat = cameras.reshape(-1)
    return (flat.fx.double() + flat.fy.double()).reshape(-1) / torch.hypot(flat.width.double(), flat.height.double()).reshape(-1)


def typical_camera(reference: Cameras) -> Cameras:
    """The reference camera of the median field of view (mean focal length over the image diagonal), a real one (its
    size, principal point and focal lengths kept): a path's frames framed as a typical photograph, not as whichever
    came first (colmap_mouse's first photograph is its widest, focal length 0.47 of its longer side against a median
    of 0.72: through it the mouse showed at two thirds of its size in the photographs)."""
    return reference.reshape(-1)[int(field_of_view(reference).median(0).indices)]


AROUND_ARC = math.radians(120)
"""Azimuth arc about the scene centre that photographs of an object taken from around it cover (the fast model's
``SPARSITY_MIN_ARC``); facades and photo collections cover less (the Sceaux castle 63°, the Sacre Coeur 43°)."""

PHOTO_PATH_SPREAD = 0.5
"""Spread of the photographs' distances to the scene centre (interquartile range over median) above which a capture
that does not surround its object (:data:`AROUND_ARC`) gets the path along its photographs (:func:`photo_path_cameras`)
instead of an orbit at their mean distance: a collection taken from near and far (the Sacre Coeur 2.56), where that
distance is nobody's. Object and facade captures keep the orbit's steady framing (ngp_fox 0.29, the Sceaux castle 0.09,
colmap_mouse 0.14): along ngp_fox's close-ups the fox came and went at the frame's edge."""

PHOTO_PATH_SMOOTHING = 1.0
"""Width (standard deviation, in photographs) of the Gaussian window that smooths :func:`photo_path_cameras`' path."""


def distance_spread(cameras: Cameras, center: Float[Tensor, "3"]) -> float:
    """Interquartile range over median of the cameras' distances to ``center`` (0 for fewer than two)."""
    d = (cameras.centers.reshape(-1, 3).double() - center.double()).norm(dim=-1)
    if len(d) < 2:
        return 0.0
    q = torch.quantile(d, torch.tensor([0.25, 0.5, 0.75], dtype=d.dtype))
    return float((q[2] - q[0]) / q[1].clamp(min=1e-12))


def along_photographs(reference: Cameras, center: Float[Tensor, "3"]) -> bool:
    """Whether :func:`orbit_cameras` passes along the reference cameras' viewpoints (:func:`photo_path_cameras`): three
    or more that cover less than :data:`AROUND_ARC` about ``center`` from distances that spread more than
    :data:`PHOTO_PATH_SPREAD`."""
    return len(reference.reshape(-1)) >= 3 and camera_arc(reference, center) < AROUND_ARC and distance_spread(reference, center) > PHOTO_PATH_SPREAD


def photo_path_cameras(reference: Cameras, center: Float[Tensor, "3"], num_frames: int = 60,
                       smoothing: float = PHOTO_PATH_SMOOTHING) -> Cameras:
    """A path along the reference cameras' own viewpoints, for photo collections taken from near and far that do not
    surround their object: an orbit at their mean distance shows the scene from where no photograph stood, and the
    object region's box with what fills it shows there (the Sacre Coeur as a cube of sky fog). The cameras are taken
    in order of azimuth about ``center``, there and back (eased at the ends, as :func:`orbit_azimuths`); each frame's
    position, viewing direction and field of view (focal length over image diagonal) are the means of the cameras'
    under a Gaussian window of ``smoothing`` photographs around its place in that order, upright (+z up); its image
    size and principal point are the typical camera's (:func:`typical_camera`)."""
    flat = reference.reshape(-1)
    order = torch.argsort(azimuths(flat, center))
    flat = flat[order]
    n = len(flat)
    place = (n - 1) * there_and_back(num_frames)  # [F] in [0, n - 1]
    w = torch.exp(-0.5 * ((place[:, None] - torch.arange(n, dtype=torch.float64)) / max(smoothing, 1e-6)) ** 2)
    w = w / w.sum(-1, keepdim=True)  # [F, n]
    eye = w @ flat.centers.double()
    fwd = torch.nn.functional.normalize(w @ flat.forward.double(), dim=-1)
    zoom = w @ field_of_view(flat)
    m = look_at(eye, eye + fwd, torch.tensor(WORLD_UP, dtype=torch.float64))
    r = typical_camera(reference)
    focal = zoom * math.hypot(float(r.width), float(r.height)) / 2  # the mean of fx and fy, as zoom is
    return Cameras.create(m, focal, focal, r.cx.double().expand(num_frames), r.cy.double().expand(num_frames),
                          r.width.expand(num_frames), r.height.expand(num_frames), dtype=reference.fx.dtype)


def orbit_cameras(reference: Cameras, center: Float[Tensor, "3"], num_frames: int = 60) -> Cameras:
    """Cameras around ``center`` (about +z) at the reference cameras' mean distance and elevation, with the
    intrinsics of the reference camera of the median field of view (:func:`typical_camera`): a full circle, or the
    arc the reference cameras cover (:func:`orbit_azimuths`). Where that arc is under :data:`AROUND_ARC` and the
    cameras' distances spread more than :data:`PHOTO_PATH_SPREAD`, the path along their viewpoints instead
    (:func:`photo_path_cameras`)."""
    if along_photographs(reference, center):
        return photo_path_cameras(reference, center, num_frames)
    offsets = reference.centers.reshape(-1, 3).double() - center.double()
    radius = float(offsets.norm(dim=-1).mean())
    elevation = float(torch.asin((offsets[:, 2] / offsets.norm(dim=-1)).clamp(-1, 1)).mean())
    angles = orbit_azimuths(azimuths(reference, center), num_frames)
    ring = torch.stack([torch.cos(angles), torch.sin(angles), torch.zeros_like(angles)], dim=-1) * math.cos(elevation)
    eye = center.double() + radius * (ring + torch.tensor([0.0, 0.0, math.sin(elevation)], dtype=torch.float64))
    m = look_at(eye, center.double().expand_as(eye), torch.tensor(WORLD_UP, dtype=torch.float64))
    r = typical_camera(reference)
    return Cameras.create(m, r.fx, r.fy, r.cx, r.cy, r.width, r.height, dtype=reference.fx.dtype)


def path_cameras(scene, kind: str = "test", num_frames: int = 60) -> Cameras:
    """Cameras for a novel-view sequence.

    ``test``: the dataset's test poses (evenly subsampled to ``num_frames``), falling back to an
    orbit when the scene has none; ``orbit``: :func:`orbit_cameras` around the aabb centre.
    """
    if kind not in ("test", "orbit"):
        raise ValueError(f"unknown camera path '{kind}' (test or orbit)")
    test = scene.splits.get("test")
    if kind == "test" and test is not None and len(test):
        cams = scene.split_cameras("test")
        idx = torch.linspace(0, len(cams) - 1, min(num_frames, len(cams))).round().long()
        return cams[idx]
    return orbit_cameras(*orbit_reference(scene), num_frames)


def orbit_reference(scene) -> "tuple[Cameras, Float[Tensor, '3']]":
    """The cameras and centre a scene's orbit is made from: its training cameras and its box's centre."""
    return scene.split_cameras("train"), scene.aabb.float().mean(0)
