"""World normalisation and scene bounds shared by all adapters.

Real captures (COLMAP, instant-ngp, nerfstudio) come in arbitrary position, orientation and
scale. :func:`auto_normalization` computes the :class:`~nerfpipe.data.scene.Similarity` that puts the
scene centre at the origin, the world's up (:func:`upright_direction`) on +z, and the cameras at a mean distance
of :data:`TARGET_CAMERA_DISTANCE` from the centre (the distance of the Blender synthetic scenes,
so that default bounds and step sizes carry over). Synthetic Blender scenes keep their frame.
"""

import math

import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.scene import Similarity
from nerfpipe.util.typing import Bool, Float, Tensor

TARGET_CAMERA_DISTANCE = 4.0


def focus_point(cameras: Cameras) -> Float[Tensor, "3"]:
    """The point closest (least squares) to all optical axes."""
    c = cameras.centers.double().reshape(-1, 3)
    d = torch.nn.functional.normalize(cameras.forward.double().reshape(-1, 3), dim=-1)
    proj = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]
    a = proj.sum(0)
    b = (proj @ c[:, :, None]).sum(0)[:, 0]
    if torch.linalg.matrix_rank(a) < 3:  # all axes parallel: fall back to the centroid
        return c.mean(0)
    return torch.linalg.solve(a, b)


def rotation_to_z(up: Float[Tensor, "3"]) -> Float[Tensor, "3 3"]:
    """Rotation that maps the unit vector ``up`` onto +z (Rodrigues)."""
    up = up.double() / up.double().norm()
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    v = torch.linalg.cross(up, z)
    c = float(up @ z)
    if v.norm() < 1e-12:
        return torch.eye(3, dtype=torch.float64) if c > 0 else torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    vx = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + vx + vx @ vx * (1 / (1 + c))


UPRIGHT_MAX_TILT = 60.0
"""Degrees between :func:`upright_direction`'s estimate and the mean image-up beyond which the estimate is not trusted."""


def upright_direction(cameras: Cameras) -> Float[Tensor, "3"]:
    """World up (unit, float64) from how photographs are taken: without roll, so one image axis of every
    camera is horizontal, whatever it looks at: the right axis (+x) of a photo taken upright, the down
    axis (+y) of one turned a quarter (a portrait photo whose pixels are stored sideways, as COLMAP reads
    them). Up is the direction most orthogonal to each camera's horizontal axis (the least eigenvector of
    their scatter), turned towards the mean image-up (-y); which axis is horizontal is chosen per camera
    (the one more orthogonal to the estimate, starting with every camera upright), three times over.

    The mean image-up alone tilts with the views: a camera looking down at a table has its image-up along
    the table. On colmap_mouse the table's normal lies 2.9 degrees from this estimate and 7.5 from the mean
    image-up; on 23 of its photos 3.9 and 9.4; on photos_sceaux_castle's ground 2.3 and 6.7.
    Where the axes do not decide (cameras all facing one way: only a facade) or the estimate strays more
    than :data:`UPRIGHT_MAX_TILT` from the mean image-up, the mean image-up without its component along
    the horizontal axes is used (and the mean image-up itself when that vanishes).
    """
    mean_up = cameras.up.double().reshape(-1, 3).mean(0)
    rot = cameras.world_from_cam[..., :3, :3].double().reshape(-1, 3, 3)
    axes_x, axes_y = rot[:, :, 0], rot[:, :, 1]
    sideways = torch.zeros(len(rot), dtype=torch.bool)  # first every camera upright, then re-chosen
    for _ in range(4):
        decided, vectors = _normal_of_horizontals(axes_x, axes_y, sideways)
        least = vectors[:, 0] * (1.0 if float(vectors[:, 0] @ mean_up) >= 0 else -1.0)
        if not decided:
            break
        sideways = _turned(axes_x, axes_y, least)
    cos = float(least @ mean_up) / max(float(mean_up.norm()), 1e-12)
    if decided and cos > math.cos(math.radians(UPRIGHT_MAX_TILT)):
        return least
    turned = _upright_of_turned(rot, cameras.forward.double().reshape(-1, 3))
    if turned is not None:
        return turned
    plane = vectors[:, :2] @ vectors[:, :2].T @ mean_up
    return plane / plane.norm() if plane.norm() > 1e-6 else mean_up / mean_up.norm().clamp_min(1e-12)


UPRIGHT_ROLL_COST = 0.02
"""The most :func:`_roll_costs` (the mean squared sine of the cameras' roll: each camera's image axis nearer horizontal,
against the direction taken for up) that :func:`_upright_of_turned` accepts: about 8 degrees of roll. colmap_mouse's
cameras 0.014 against their up, with any share of them turned sideways; a reconstruction with half its photos folded
80 degrees 0.03-0.06 at the best direction (not a capture of turned photos: the mean image-up stays)."""

UPRIGHT_SEARCH_DIRECTIONS = 2048
"""Directions of the half sphere tried by :func:`_upright_of_turned`."""


def _normal_of_horizontals(axes_x: Float[Tensor, "n 3"], axes_y: Float[Tensor, "n 3"], sideways: "Tensor") -> "tuple[bool, Tensor]":
    """Whether the cameras' horizontal axes (``+y`` where ``sideways``, else ``+x``) have one clear least direction,
    and the eigenvectors of their scatter (least first: the up they give, unsigned)."""
    horizontal = torch.where(sideways[:, None], axes_y, axes_x)
    values, vectors = torch.linalg.eigh(horizontal.T @ horizontal / len(horizontal))
    return bool(values[1] > 0.02 and values[0] < 0.25 * values[1]), vectors


def _turned(axes_x: Float[Tensor, "n 3"], axes_y: Float[Tensor, "n 3"], up: Float[Tensor, "3"]) -> "Tensor":
    """Per camera, whether its down axis (+y) is the more horizontal one given ``up``: a photo stored sideways."""
    return (axes_y @ up).abs() < (axes_x @ up).abs()


def _roll_costs(rot: Float[Tensor, "n 3 3"], ups: Float[Tensor, "k 3"]) -> Float[Tensor, "k"]:
    """``min((x.up)^2, (y.up)^2)`` averaged over the cameras, for each of ``ups``: 0 where every camera has one image
    axis horizontal."""
    return torch.minimum((rot[:, :, 0] @ ups.T) ** 2, (rot[:, :, 1] @ ups.T) ** 2).mean(0)


def _upright_of_turned(rot: Float[Tensor, "n 3 3"], forward: Float[Tensor, "n 3"]) -> "Float[Tensor, '3'] | None":
    """:func:`upright_direction` where many photographs are stored sideways (a half, or all: a phone held upright whose
    pixels are stored as the sensor reads them), so that neither every camera's right axis nor the mean image-up
    is a start the per-camera choice can recover from. Up is sought as the direction most orthogonal to one image
    axis of every camera (``min((x.u)^2, (y.u)^2)`` summed, over a Fibonacci half sphere), then refined as
    :func:`upright_direction` does from the axes that choice makes horizontal. Trusted only where the mean of the cameras'
    other axes (each turned towards it) lies within :data:`UPRIGHT_MAX_TILT` of it (a facade's one-way views do not: None). Its
    sign: the image-up of the cameras taken upright, where some are; else the one that has the cameras look down
    on average (an object photographed from above)."""
    n = UPRIGHT_SEARCH_DIRECTIONS
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = i / n  # the half sphere z > 0: u and -u are the same axis here
    ring = torch.sqrt(1 - z * z)
    phi = i * math.pi * (3 - math.sqrt(5))
    dirs = torch.stack([ring * torch.cos(phi), ring * torch.sin(phi), z], -1)
    axes_x, axes_y = rot[:, :, 0], rot[:, :, 1]
    u = dirs[int(_roll_costs(rot, dirs).argmin())]
    for _ in range(4):
        decided, vectors = _normal_of_horizontals(axes_x, axes_y, _turned(axes_x, axes_y, u))
        if not decided:
            return None
        u = vectors[:, 0]
    sideways = _turned(axes_x, axes_y, u)
    other = torch.where(sideways[:, None], axes_x, axes_y)  # each camera's image-up axis, up to its sign
    mean_up = (other * torch.sign(other @ u)[:, None]).mean(0)  # each turned towards u, then averaged
    if float(mean_up @ u) < math.cos(math.radians(UPRIGHT_MAX_TILT)) * float(mean_up.norm()):
        return None
    if float(_roll_costs(rot, u[None])[0]) > UPRIGHT_ROLL_COST:  # no direction leaves one axis of every camera level: a fold, not photos turned
        return None
    if bool((~sideways).any()):
        sign = -float((axes_y[~sideways] @ u).sum())  # the upright ones' image-up is -y
    else:
        sign = -float((forward @ u).sum())
    return u if sign >= 0 else -u


def auto_normalization(cameras: Cameras, center: "Float[Tensor, '3'] | None" = None) -> Similarity:
    """Similarity that centres the scene, turns the world's up (:func:`upright_direction`) to +z, and scales."""
    center = focus_point(cameras) if center is None else center.double()
    up = upright_direction(cameras)
    rot = rotation_to_z(up) if up.norm() > 1e-6 else torch.eye(3, dtype=torch.float64)
    dist = (cameras.centers.double().reshape(-1, 3) - center).norm(dim=-1).mean()
    scale = TARGET_CAMERA_DISTANCE / float(dist) if float(dist) > 0 else 1.0
    return Similarity(rot, -scale * (rot @ center), scale)


def bounds_from_cameras(cameras: Cameras, center: "Float[Tensor, '3'] | None" = None):
    """Near/far and a cube around the look-at point, from the cameras alone.

    The cube's half-size is what the mean camera sees at the look-at distance
    (``distance * tan(half fov)``): for the Blender lego this gives about 1.45.

    Returns:
        (near, far, aabb ``[2, 3]``)
    """
    center = focus_point(cameras) if center is None else center.double()
    dist = (cameras.centers.double().reshape(-1, 3) - center).norm(dim=-1)
    half_fov = torch.atan(0.5 * torch.minimum(cameras.width / cameras.fx, cameras.height / cameras.fy).double())
    half = float((dist * torch.tan(half_fov.reshape(-1))).mean())
    radius = math.sqrt(3) * half
    near = max(0.05 * float(dist.min()), float(dist.min()) - radius)
    far = float(dist.max()) + radius
    aabb = torch.stack([center - half, center + half]).float()
    return near, far, aabb


OBJECT_PAD = 0.25
"""Margin of the object region around its points' robust extent, as a fraction of that extent per axis. The
object's texture-less parts have few sparse points: colmap_mouse's plain lilac end lies 0.2 of the points'
extent beyond their 98% quantile, so a margin of 0.1 cut the mouse off in the renders and the mesh. A margin of 0.5
gave 23.16 dB against 24.26 after 600 steps (27.8 samples per ray against 13.4): the table and fog fill the box
(session 75: 0.45 on colmap_mouse 24.84 against 24.96 dB averaged after 900 steps, its depth orbit full of table
pieces)."""

OBJECT_COVER = 0.15
"""Where the outermost points that are not :func:`isolated` (their 0.1 and 99.9 % quantiles) lie beyond a side of the
robust extent's margin, the object region's side moves out to them and by this fraction of its extent further. A plain
part seen by few of the photos carries few points: in a 23-photo cut of colmap_mouse (every 56/23-th registered image,
COLMAP's poses) the mouse's lilac side lay beyond the 2 % quantile of the points and the box cut it flat (straight
edges in the depth orbit, its end rendered coarsely by the field behind the box). Side by side at equal steps (3
held-out views at 400 px, one ray per pixel, the average after 900 steps, seeds 0 / 1): **24.98 / 25.16 dB** against
24.71 / 24.77, the end rounded in the orbit (the side 1.113 out instead of 0.767; a fog slab around the mouse in most
runs of this cut with either box). Tried: 0.1 (24.97, seed 0); the 0.5 % quantile of the points not isolated instead
(24.97 / 25.04, but on 23 of ngp_fox's photos through SfM 26.13 against 26.26: a box of 1.28x the volume). The shared
scenes' reconstructions (colmap_mouse, 23 of ngp_fox's photos, the HEIC and offset cuts through SfM) and the synthetic
scenes keep their region: their points end inside the margin."""

ISOLATED_NEIGHBOURS = 8
ISOLATED_FACTOR = 3.0
"""A point whose :data:`ISOLATED_NEIGHBOURS`-th nearest neighbour lies more than this many times the median such
distance away is isolated (:func:`isolated`): a mismatch, or a speck of the background within reach. Without the test
single points stretch the box where few quantiles are cut (the 0.5 % quantile of a 450-point reconstruction of 11
photos: 1.83x the volume of the 2 % box; of its points not isolated, 1.12x)."""

COVER_QUANTILE = 0.001
"""The outermost points :data:`OBJECT_COVER` holds: this quantile and ``1 -`` it of the points not isolated."""

COVER_ABOVE = 0.1
"""The walls of the object region move out (:data:`OBJECT_COVER`) only for points higher than this quantile of the
points' heights: the 23-photo cut's lilac side lay at 45-58 % of the points' robust height; a table's points lie at the
bottom."""

ISOLATED_MAX_POINTS = 8192
"""Points that :func:`object_region` measures at most (a seeded random subset of larger clouds: :func:`isolated`
compares every pair, 3 s for 20,000 points on 2 busy cores)."""

OBJECT_REACH = 0.75
"""Points farther from the cameras' focus point than this fraction of the median camera distance are
background (floor, walls, a distant skyline), not the object the cameras were aimed at."""


def isolated(xyz: Float[Tensor, "num_points 3"], k: int = ISOLATED_NEIGHBOURS, factor: float = ISOLATED_FACTOR) -> Bool[Tensor, "num_points"]:
    """Whether each point's ``k``-th nearest neighbour (among ``xyz``) lies farther than ``factor`` times the median
    such distance (False for every point where there are ``k`` or fewer)."""
    if len(xyz) <= k:
        return torch.zeros(len(xyz), dtype=torch.bool, device=xyz.device)
    pts = xyz.float()
    kth = torch.cat([torch.cdist(chunk, pts).topk(k + 1, largest=False).values[:, -1] for chunk in pts.split(2048)])
    return kth > factor * kth.median()


def object_region(
    cameras: Cameras,
    xyz: Float[Tensor, "num_points 3"],
    pad: float = OBJECT_PAD,
    quantile: float = 0.02,
    reach: float = OBJECT_REACH,
    cover: "float | None" = OBJECT_COVER,
) -> Float[Tensor, "2 3"]:
    """The object region ``[min, max]`` (float64) of the sparse points within ``reach`` median camera distances of the
    point the cameras look at: their robust extent (``quantile`` to ``1 - quantile`` per axis) grown by ``pad`` times
    that extent, and on a side where the outermost points that are not :func:`isolated` lie beyond that, out to them
    and by ``cover`` times the extent further (:data:`OBJECT_COVER`; None: not). What lies beyond is modelled as
    background (the ``fast`` model's field behind the box), not as fog in the object's box. All points count when
    fewer than 20 are that close.
    """
    xyz = xyz.double()
    focus = focus_point(cameras)
    dist = (cameras.centers.double().reshape(-1, 3) - focus).norm(dim=-1).median()
    near = (xyz - focus).norm(dim=-1) <= reach * dist
    pts = xyz[near] if int(near.sum()) >= 20 else xyz
    lo, hi = torch.quantile(pts, quantile, dim=0), torch.quantile(pts, 1 - quantile, dim=0)
    margin = pad * (hi - lo)
    box = torch.stack([lo - margin, hi + margin])
    return box if cover is None else _cover_outermost(box, pts, cover)


def _cover_outermost(box: Float[Tensor, "2 3"], pts: Float[Tensor, "num_points 3"], cover: float) -> Float[Tensor, "2 3"]:
    """``box`` with each side that the outermost points not :func:`isolated` lie beyond moved out to them, plus ``cover``
    times the box's extent (:data:`OBJECT_COVER`). Only the top and the four walls move (the world's up is +z), the walls
    only for points above the :data:`COVER_ABOVE` quantile of the points' heights: what lies level with the object's base
    or below it (a textured table reaching to the edge of the points' reach, a floor) is the surroundings, not a plain
    part of the object."""
    if len(pts) > ISOLATED_MAX_POINTS:
        pts = pts[torch.randperm(len(pts), generator=torch.Generator().manual_seed(0))[:ISOLATED_MAX_POINTS].to(pts.device)]
    heights = pts[:, 2]
    pts = pts[~isolated(pts)]
    if len(pts) < 20:
        return box
    base = torch.quantile(heights, COVER_ABOVE)
    q = torch.tensor([COVER_QUANTILE, 1 - COVER_QUANTILE], dtype=pts.dtype, device=pts.device)
    reach_out = cover * (box[1] - box[0])
    lo, hi = box[0].clone(), box[1].clone()
    raised = pts[pts[:, 2] > base]
    if len(raised) >= 20:
        first, last = torch.quantile(raised[:, :2], q, dim=0)
        lo[:2] = torch.where(first < box[0, :2], first - reach_out[:2], box[0, :2])
        hi[:2] = torch.where(last > box[1, :2], last + reach_out[:2], box[1, :2])
    top = torch.quantile(pts[:, 2], q[1])
    hi[2] = top + reach_out[2] if top > box[1, 2] else box[1, 2]
    return torch.stack([lo, hi])


def bounds_from_points(cameras: Cameras, xyz: Float[Tensor, "num_points 3"]):
    """Near/far from the depths of sparse points, and the :func:`object_region` of the points as the box.

    Returns:
        (near, far, aabb ``[2, 3]``)
    """
    xyz = xyz.double()
    aabb = object_region(cameras, xyz)
    cfw = cameras.cam_from_world.double().reshape(-1, 4, 4)
    gen = torch.Generator().manual_seed(0)  # reproducible bounds
    sub = xyz[torch.randperm(len(xyz), generator=gen)[:20000]] if len(xyz) > 20000 else xyz
    z = cfw[:, 2, :3] @ sub.T + cfw[:, 2, 3:4]  # camera-z depth of every point in every camera
    z = z[z > 0]
    near = 0.5 * float(torch.quantile(z, 0.01)) if len(z) else 0.05
    far = 1.5 * float(torch.quantile(z, 0.99)) if len(z) else 10.0
    return near, far, aabb.float()
