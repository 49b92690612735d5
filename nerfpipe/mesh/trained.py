"""A mesh of a trained model: the glue between a model, its scene and :func:`build_meshes`.

Shared by ``nerfpipe mesh`` and the ``mesh`` stage. The model is used only through callables
(``density_fn``, ``rgb_fn``, its occupancy grid's ``occupied``) and :func:`nerfpipe.outputs.render.render_cameras`
(depth of training views for the automatic level and for TSDF fusion).
"""

from dataclasses import dataclass

from nerfpipe.mesh.pipeline import MeshConfig, MeshOutputs
from nerfpipe.util.errors import refuse_unless

MIN_CROP_POINTS = 20
"""Fewer sparse points than this do not define an extent to crop to."""


@dataclass
class RenderedViews:
    """Training views rendered for the mesh (the depth level and TSDF fusion)."""

    tsdf_views: int = 48
    """Training views rendered for tsdf (evenly spread)."""
    tsdf_size: int = 256
    """Longer side in pixels of the tsdf depth renders."""
    chunk: "int | None" = None
    """Rays per forward pass when rendering (None: the model's ``render_chunk``)."""
    min_views: int = 8
    """Under a time budget, fewer TSDF views are rendered (evenly spread), but never fewer than this."""
    budget_share: float = 0.6
    """Under a time budget, the TSDF depth renders take at most this share of the time left after ``fixed_seconds``
    (timed on the first view); the rest is the margin of a slow hour and the orbit render's time."""
    fixed_seconds: float = 10.0
    """What the rest of the mesh stage takes under a budget (fusion, cleaning, simplification, metrics) at least; or
    ``fixed_share`` of the time left where that is more. Session 68 on 2 cores: 7.5 s for colmap_mouse (27.5 s in all,
    20.0 s of it the 48 renders), about 5 s for 23 of ngp_fox's photos and for the Sceaux castle, 27 s for the
    synthetic demo (658,000 faces: the simplification 11.7 s, cleaning and colour 4.8 s). Sessions up to 40 reserved
    20 s: with 21.5 s left, 23 of ngp_fox's photos got 8 renders of 84-105 px and 91-92 % of the points near the mesh,
    against 99.4 % with 16 of 143 px under this reserve, while 16 s of the run's 180 went unused."""
    fixed_share: float = 0.3
    """See ``fixed_seconds``: with more time left the reserve grows with it (a mesh of many faces, such as the demo's, takes
    longer to clean and simplify): with 40 s left the renders get what the 20 s reserve gave them (16.8 against 16 s),
    with more they get less (80 s left: 33.6 against 48 s; colmap_mouse's 48 renders took 20 s)."""

    seconds_per_face: float = 40e-6
    """Under a time budget, what the rest of the mesh stage takes per face that fusion gives (cleaning, simplification,
    metrics, writing: the stage's seconds less its renders), used to cap the faces at what fits the reserve
    (:meth:`max_faces`). Measured on 2 cores: 35 and 49 microseconds on the synthetic demo (530,000 and 637,000
    faces), 40 on colmap_mouse (174,000), 35 on 23 of ngp_fox's photos (177,000), 29 and 31 on colmap_mouse's posed
    23-photo cut (186,000) and its stand-in with every other photo stored sideways (277,000)."""

    def reserve(self, seconds: float) -> float:
        """What the stage keeps, of ``seconds`` left, for all but the renders (``fixed_seconds``, or ``fixed_share`` of them)."""
        return max(self.fixed_seconds, self.fixed_share * seconds)

    def render_budget(self, seconds: "float | None") -> "float | None":
        """Seconds the TSDF depth renders may take with ``seconds`` left for the mesh stage (None: no budget)."""
        if seconds is None:
            return None
        return self.budget_share * max(seconds - self.reserve(seconds), 0.0)

    def max_faces(self, seconds: "float | None") -> "int | None":
        """The faces fusion may give with ``seconds`` left for the mesh stage: as many as the reserve has time for
        (None: no budget). The synthetic demo under ``--time-budget 60`` (session 69): with 18.6-19.0 s left, 250,000;
        its 256-voxel fusion of 530,000 faces is fused again at 173 voxels (232,000 faces): the stage took 16.3 s
        instead of 24.2 (the rest 10.4 s instead of 18.7), the run 58.7 s instead of 65.5, F-score@1 % 0.940 against 0.945."""
        if seconds is None:
            return None
        return max(round(self.reserve(seconds) / self.seconds_per_face), 1)

    def __post_init__(self) -> None:
        refuse_unless((
            ("tsdf_views", self.tsdf_views >= 1, "at least 1", self.tsdf_views),
            ("tsdf_size", 8 <= self.tsdf_size <= 8192, "between 8 and 8192 pixels", self.tsdf_size),
            ("budget_share", 0 < self.budget_share <= 1, "in (0, 1]", self.budget_share),
            ("fixed_seconds", self.fixed_seconds >= 0, "0 or more", self.fixed_seconds),
            ("fixed_share", 0 <= self.fixed_share < 1, "in [0, 1)", self.fixed_share),
            ("seconds_per_face", self.seconds_per_face > 0, "positive", self.seconds_per_face),
            ("chunk", self.chunk is None or self.chunk >= 1, "at least 1", self.chunk),
        ))  # fmt: skip


def mesh_model(
    cfg: MeshConfig, model, scene, views: "RenderedViews | None" = None, device: str = "cpu", seconds: "float | None" = None
) -> MeshOutputs:
    """Extract, clean, colour and simplify the mesh of ``model`` trained on ``scene`` (world frame); with
    ``seconds`` (the time left), the TSDF renders as many views as fit :meth:`RenderedViews.render_budget`."""
    import torch

    from nerfpipe.mesh.pipeline import build_meshes

    views = views or RenderedViews()
    aabb, occupancy_fn = box_and_occupancy(model, scene.aabb)
    if cfg.crop_to_points and scene.points is not None and len(scene.points.xyz) >= MIN_CROP_POINTS:
        aabb = crop_to_points(aabb, scene.cameras, scene.points.xyz, cfg.crop_margin)
    train = scene.split_cameras("train")
    frame_fn, tsdf_cams = None, None
    if cfg.method == "tsdf":
        tsdf_cams, frame_fn = tsdf_frames(model, train, views.tsdf_views, views.tsdf_size, views.chunk, device, views.render_budget(seconds),
                                          views.min_views)
    depth_level = cfg.method == "mc" and cfg.level is None and cfg.level_from != "opacity"
    points, origins = surface_points(model, train, views.chunk, device) if depth_level else (None, None)
    from nerfpipe.mesh.reference import sight_lines

    lines = sight_lines(scene, frame="world")
    with torch.no_grad():
        out = build_meshes(cfg, aabb, density_fn=model.density_fn, rgb_fn=model.rgb_fn, occupancy_fn=occupancy_fn, frame_fn=frame_fn,
                            cameras=tsdf_cams if tsdf_cams is not None else train, surface_points=points, surface_origins=origins,
                            sight_lines=lines, support=known_support(model), max_faces=views.max_faces(seconds))
    if tsdf_cams is not None:
        size = int(torch.maximum(tsdf_cams.width, tsdf_cams.height).max())
        out.figures.update(seconds_tsdf_renders=frame_fn.seconds(), tsdf_views=len(tsdf_cams), tsdf_views_requested=views.tsdf_views, tsdf_size=size, tsdf_size_requested=views.tsdf_size, stop_opacity=getattr(getattr(model, "cfg", None), "stop_opacity", None))
    return out


def known_support(model):
    """The plane the model's scene stands on, found in its sparse points, where the cameras surround the object
    (:func:`nerfpipe.models.fast.object_support` of the model's ``SceneInfo``, world frame); None elsewhere (a facade's
    ground, a photo collection's steps: the mesh stage looks in the mesh) and for models that know no scene."""
    from nerfpipe.models.fast import object_support

    info = getattr(model, "info", None)
    return None if info is None else object_support(info)


def crop_to_points(aabb, cameras, xyz, margin: float):
    """``aabb`` intersected with the points' object region (:func:`nerfpipe.data.normalize.object_region`, grown by
    ``margin``); ``aabb`` itself when they do not overlap."""
    import torch

    from nerfpipe.data.normalize import object_region

    region = object_region(cameras, xyz, pad=margin)
    box = torch.stack([torch.maximum(aabb[0].double(), region[0]), torch.minimum(aabb[1].double(), region[1])]).float()
    return box if bool((box[1] > box[0]).all()) else aabb


def box_and_occupancy(model, scene_aabb):
    """The box to mesh: the occupancy grid's occupied box (one cell margin) when the model has one."""
    import torch

    grid = getattr(model, "grid", None)
    if grid is None or not hasattr(grid, "occupied_aabb"):
        return scene_aabb.float(), None
    box = grid.occupied_aabb().float().cpu()
    cell = (grid.aabb[1] - grid.aabb[0]).float().cpu() / grid.cfg.resolution
    box = torch.stack([torch.maximum(box[0] - cell, grid.aabb[0].cpu()), torch.minimum(box[1] + cell, grid.aabb[1].cpu())])
    return box, lambda p: grid.occupied(p.to(grid.aabb.device))


def surface_points(model, train, chunk: "int | None", device: str, views: int = 8, size: int = 128):
    """Where the rays of a few rendered training views end (opaque pixels only, expected depth) and their origins, world frame."""
    import torch

    from nerfpipe.data.rays import camera_rays
    from nerfpipe.outputs.render import render_cameras

    idx = torch.linspace(0, len(train) - 1, min(views, len(train))).round().long().unique()
    cams = resize_each(train[idx], size / torch.maximum(train[idx].width, train[idx].height).double())
    pts, origins = [], []
    for i, view in enumerate(render_cameras(model, cams.to(device), chunk)):
        rays = camera_rays(cams, i)
        opaque = view.acc.cpu() > 0.9
        pts.append(rays.points_at(view.surface_depth.cpu())[opaque])
        origins.append(rays.origins[opaque])
    return torch.cat(pts), torch.cat(origins)


MIN_TSDF_SHRINK = 0.25
"""Under a time budget, TSDF views are rendered at no less than this fraction of their size. Before, views that did
not fit were rendered at half the size at least: beside other jobs (load ~4), the Sacre Coeur's mesh stage began with
18 s left and took 85 s for 8 such views, and `nerfpipe run --time-budget 300` ended after 378 s."""


def tsdf_frames(model, train, views: int, size: int, chunk: "int | None", device: str, seconds: "float | None" = None, min_views: int = 8):
    """Undistorted, resized training cameras (``views`` of them, evenly spread) and a ``frame_fn`` rendering
    their depth and colour. With ``seconds``, the first view is rendered and timed, and only as many views as
    fit in ``seconds`` are kept: when fewer than ``2 min_views`` fit, that many are rendered smaller (down to half
    the size); when fewer than ``min_views / 2`` fit, ``min_views`` are, as small as fits (down to
    :data:`MIN_TSDF_SHRINK` of the size); else at least ``min_views``."""
    import dataclasses
    import time

    import numpy as np
    import torch

    from nerfpipe.data.rays import camera_rays
    from nerfpipe.outputs.render import render_cameras

    def spread(n: int):  # evenly spread training views; the first is always train[0]
        return torch.from_numpy(np.unique(np.linspace(0, len(train) - 1, min(n, len(train))).round().astype(np.int64)))

    base = dataclasses.replace(train, distortion=torch.zeros_like(train.distortion), dist_params=torch.zeros_like(train.dist_params))
    base = resize_each(base, size / torch.maximum(base.width, base.height).double())
    cams, cache, spent = base[spread(views)], {}, [0.0]

    def frame(i: int):
        if i in cache:
            return cache.pop(i)
        start = time.perf_counter()
        view = render_cameras(model, cams[i : i + 1].to(device), chunk)[0]
        depth = stop_depth(view).nan_to_num(0.0).cpu()
        z = depth * camera_rays(cams, i).z_scale
        spent[0] += time.perf_counter() - start
        return z.double().numpy(), (view.rgb.cpu().numpy() * 255 + 0.5).astype(np.uint8)

    frame.seconds = lambda: spent[0]  # type: ignore[attr-defined]  # the renders' time so far (mesh.json's figure)

    if seconds is not None and len(cams) > min_views:
        first = frame(0)
        fit = seconds / max(frame.seconds(), 1e-3)  # full-size views that fit
        want = min(len(cams), 2 * min_views)
        if fit < want:  # rather twice min_views views down to half the size than fewer sharp ones; when not even
            # min_views fit at full size, min_views smaller ones (down to MIN_TSDF_SHRINK): the budget holds
            n = want if fit / want >= 0.25 else min_views
            shrink = max((fit / n) ** 0.5, MIN_TSDF_SHRINK)  # a render costs about its pixel count
            base = resize_each(base, torch.full((len(base),), shrink, dtype=torch.float64))
            cams = base[spread(n)]
        else:
            cams = base[spread(max(min_views, min(int(fit), len(cams))))]
            cache[0] = first  # the same camera: spread() always starts with train[0]
    return cams, frame


def stop_depth(view):
    """Where each pixel's ray stops: the model's stop depth when it gives one, else the expected depth of
    rays more than half opaque; NaN where the ray does not stop."""
    import torch

    if view.stop_depth is not None:
        return view.stop_depth
    return torch.where(view.acc > 0.5, view.surface_depth, torch.full_like(view.depth, float("nan")))


def resize_each(cams, scale):
    """Scale every camera by its own factor (sizes may differ within a scene)."""
    from nerfpipe.data.cameras import Cameras
    from nerfpipe.outputs.render import resize_cameras

    parts = []
    for i in range(len(cams)):
        w = max(1, int(round(float(cams.width[i]) * float(scale[i]))))
        h = max(1, int(round(float(cams.height[i]) * float(scale[i]))))
        parts.append(resize_cameras(cams[i : i + 1], w, h))
    return Cameras.cat(parts)
