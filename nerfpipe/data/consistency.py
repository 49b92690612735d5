"""Independent checks that a scene's cameras follow nerfpipe's conventions (``nerfpipe check``).

Three kinds of evidence, all in float64:

* **kornia**: points made from nerfpipe rays (pixel -> ray -> point at a camera-z depth) are
  projected back with kornia (``PinholeCamera`` + ``distort_points`` / Kannala-Brandt) and must
  land on the pixel they came from; kornia's unprojection (``undistort_points`` +
  ``PinholeCamera.unproject``) must give nerfpipe's point. kornia counts pixels from integer
  centres and nerfpipe from half-integer ones; we hand kornia nerfpipe's own ``K``, and the
  maps are equivariant under a shift of both ``u`` and ``cx``, so both speak nerfpipe pixels.
  The half-pixel convention itself is checked by the COLMAP reprojection below.
* **round trip** through nerfpipe alone: pixel -> ray -> point -> :meth:`Cameras.project`.
* **sparse points** (COLMAP): the model's 3D points reprojected through nerfpipe's cameras in
  the normalised world, against COLMAP's own 2D observations and its reported error.

Glossary:
    probe   one (camera, pixel, depth) triple the checks run on
    px      pixels; unprojection errors are converted to pixels as ``|dp| / z * f``
"""

from dataclasses import asdict, dataclass, field

import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import generate_rays
from nerfpipe.data.scene import SceneData
from nerfpipe.functional.distortion import Distortion
from nerfpipe.util.typing import Float, Int, Tensor

# Thresholds for "conventions are broken" (exit code 1 of ``nerfpipe check``).
MAX_PX = 1e-3
MIN_FACING = 0.8
MIN_IN_FRONT = 0.99
REPROJ_FACTOR, REPROJ_SLACK_PX = 2.0, 0.5
REPROJ_AGREE_PX = 0.05
"""Our per-point mean may differ from pycolmap's recomputed figure by this much; a half-pixel
convention slip moves it by about 0.3 px on colmap_mouse."""


@dataclass
class CheckReport:
    """Figures of :func:`check_scene`; ``None`` where a check does not apply."""

    num_cameras: int
    num_probes: int
    rotation_orthonormality_err: float
    """Max ``|R^T R - I|`` of the stored rotations (removed before the pixel checks)."""
    kornia_max_px: float
    """Max pixel distance between a probe's pixel and kornia's projection of its point."""
    kornia_unproject_max_px: float
    """Max distance between nerfpipe's and kornia's unprojected points, in pixels."""
    roundtrip_max_px: float
    """Max pixel error of pixel -> ray -> point -> pixel through nerfpipe alone."""
    facing_fraction: float
    """Fraction of cameras whose +z points towards the aabb centre."""
    fisheye_checked_by_kornia: "bool | None" = None
    reproj_mean_px: "float | None" = None
    """Mean reprojection error over all observations of the sparse points."""
    reproj_median_px: "float | None" = None
    reproj_point_mean_px: "float | None" = None
    """Mean over points of each track's mean error: COLMAP's definition of its figure."""
    colmap_reported_mean_px: "float | None" = None
    points_in_front_fraction: "float | None" = None
    """Fraction of observations whose point is in front of (z > 0) the observing camera."""
    failures: "list[str]" = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def probe_pixels(cameras: Cameras, samples: int, generator: torch.Generator):
    """Per camera: the four image corners, the centre and ``samples`` random pixels.

    Returns:
        (cam_idx ``[P]``, uv ``[P, 2]``) in float64.
    """
    n = len(cameras)
    w, h = cameras.width.double(), cameras.height.double()
    fixed = torch.tensor([[0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.5]], dtype=torch.float64)
    rand = torch.rand(n, samples, 2, generator=generator, dtype=torch.float64)
    frac = torch.cat([fixed.expand(n, -1, -1), rand], dim=1)
    uv = frac * torch.stack([w, h], dim=-1)[:, None, :]
    cam_idx = torch.arange(n)[:, None].expand(-1, frac.shape[1])
    return cam_idx.reshape(-1), uv.reshape(-1, 2)


def probe_points(
    cameras: Cameras, cam_idx: Int[Tensor, "num_points"], uv: Float[Tensor, "num_points 2"], depths: "list[float]"
):
    """nerfpipe's world points at camera-z ``depths`` along the rays of ``uv``.

    Returns:
        (cam_idx ``[P]``, uv ``[P, 2]``, z ``[P]``, points ``[P, 3]``), one row per pixel and depth.
    """
    rays = generate_rays(cameras, cam_idx, uv)
    d = len(depths)
    z = torch.tensor(depths, dtype=torch.float64).repeat(len(uv))
    rep = lambda x: x.repeat_interleave(d, dim=0)  # noqa: E731
    rays = rays[torch.arange(len(uv)).repeat_interleave(d)]
    points = rays.points_at(z / rays.z_scale)
    return rep(cam_idx), rep(uv), z, points


def _kornia_batch(cams: Cameras):
    from kornia.geometry.camera import PinholeCamera

    k4 = torch.eye(4, dtype=torch.float64).repeat(len(cams), 1, 1)
    k4[:, :3, :3] = cams.K
    return PinholeCamera(k4, cams.cam_from_world, cams.height.double(), cams.width.double())


def _kb_params(cams: Cameras) -> Float[Tensor, "num_points 8"]:
    return torch.cat([torch.stack([cams.fx, cams.fy, cams.cx, cams.cy], dim=-1), cams.dist_params], dim=-1)


def kornia_project(cams: Cameras, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 2"]:
    """World points -> pixels with kornia alone (one camera per point)."""
    from kornia.geometry.calibration import distort_points
    from kornia.geometry.camera import distort_points_kannala_brandt, project_points_z1
    from kornia.geometry.linalg import transform_points

    uv = _kornia_batch(cams).project(points[:, None, :])[:, 0]
    m = cams.distortion == Distortion.OPENCV
    if bool(m.any()):
        uv[m] = distort_points(uv[m][:, None], cams.K[m], cams.dist_params[m])[:, 0]
    m = cams.distortion == Distortion.FISHEYE
    if bool(m.any()):
        p_cam = transform_points(cams.cam_from_world[m], points[m][:, None])[:, 0]
        uv[m] = distort_points_kannala_brandt(project_points_z1(p_cam), _kb_params(cams[m]))
    return uv


def kornia_unproject(
    cams: Cameras, uv: Float[Tensor, "num_points 2"], z: Float[Tensor, "num_points"]
) -> Float[Tensor, "num_points 3"]:
    """Pixels at camera-z depths -> world points with kornia alone (one camera per pixel)."""
    from kornia.geometry.calibration import undistort_points
    from kornia.geometry.camera import undistort_points_kannala_brandt

    uv_u = uv.clone()
    m = cams.distortion == Distortion.OPENCV
    if bool(m.any()):
        uv_u[m] = undistort_points(uv[m][:, None], cams.K[m], cams.dist_params[m], num_iters=200)[:, 0]
    m = cams.distortion == Distortion.FISHEYE
    if bool(m.any()):
        sub = cams[m]
        xy = undistort_points_kannala_brandt(uv[m], _kb_params(sub))
        uv_u[m] = xy * torch.stack([sub.fx, sub.fy], -1) + torch.stack([sub.cx, sub.cy], -1)
    return _kornia_batch(cams).unproject(uv_u[:, None], z[:, None, None])[:, 0]


def orthonormalized(cameras: Cameras) -> "tuple[Cameras, float]":
    """float64 copy with each rotation snapped to the nearest rotation (SVD), and the max
    deviation ``|R^T R - I|`` it removed (float32 storage leaves about 1e-7)."""
    cams = cameras.to(dtype=torch.float64)
    rot = cams.world_from_cam[..., :3, :3]
    eye = torch.eye(3, dtype=torch.float64)
    dev = float((rot.transpose(-1, -2) @ rot - eye).abs().max()) if len(cams) else 0.0
    u, _, vh = torch.linalg.svd(rot)
    w2c = cams.world_from_cam.clone()
    w2c[..., :3, :3] = u @ vh
    cams.world_from_cam = w2c
    return cams, dev


def camera_checks(cameras: Cameras, depths: "list[float]", samples: int = 16, seed: int = 0) -> dict:
    """kornia and round-trip figures over probes of every camera (float64, rotations
    orthonormalised so that the figures measure the maths, not float32 storage)."""
    cams, dev = orthonormalized(cameras)
    gen = torch.Generator().manual_seed(seed)
    cam_idx, uv, z, points = probe_points(cams, *probe_pixels(cams, samples, gen), depths)
    per = cams[cam_idx]
    uv_k = kornia_project(per, points)
    p_k = kornia_unproject(per, uv, z)
    uv_rt, _ = per.project(points)
    f = torch.maximum(per.fx, per.fy)
    return {
        "num_probes": len(uv),
        "rotation_orthonormality_err": dev,
        "kornia_max_px": float((uv_k - uv).norm(dim=-1).max()),
        "kornia_unproject_max_px": float(((p_k - points).norm(dim=-1) / z * f).max()),
        "roundtrip_max_px": float((uv_rt - uv).norm(dim=-1).max()),
    }


def facing_fraction(cameras: Cameras, aabb: Float[Tensor, "2 3"]) -> float:
    """Fraction of cameras whose viewing direction (+z) points towards the aabb centre."""
    centre = aabb.double().mean(0)
    to_centre = centre - cameras.centers.double()
    return float(((cameras.forward.double() * to_centre).sum(-1) > 0).double().mean())


def sparse_reprojection(scene: SceneData, chunk: int = 100_000) -> "dict | None":
    """Reproject the sparse points into the cameras that observed them (COLMAP scenes).

    Uses the points' tracks (:class:`nerfpipe.data.scene.Points3D` ``track_*``); None without them.
    """
    pts = scene.points
    if pts is None or not pts.has_tracks or len(pts.track_point) == 0:
        return None
    cams, _ = orthonormalized(scene.cameras)
    xyz = pts.xyz.double()
    ci, pi, xy = pts.track_camera, pts.track_point, pts.track_xy.double()
    err, depth = [], []
    for s in range(0, len(ci), chunk):
        uv, z = cams[ci[s : s + chunk]].project(xyz[pi[s : s + chunk]])
        err.append((uv - xy[s : s + chunk]).norm(dim=-1))
        depth.append(z)
    err, depth = torch.cat(err), torch.cat(depth)
    n = len(xyz)
    count = torch.bincount(pi, minlength=n).double()
    per_point = torch.zeros(n, dtype=torch.float64).index_add_(0, pi, err)[count > 0] / count[count > 0]
    colmap = scene.meta.get("colmap_mean_reprojection_error")
    scale = scene.meta.get("colmap_image_scale")  # downscaled images: COLMAP's figure in their pixels
    if colmap is not None and scale is not None:
        in_model = torch.zeros(n, dtype=torch.float64).index_add_(0, pi, err / torch.tensor(scale, dtype=torch.float64)[ci])
        colmap = colmap * float(per_point.mean()) / float((in_model[count > 0] / count[count > 0]).mean())
    return {
        "reproj_mean_px": float(err.mean()),
        "reproj_median_px": float(err.median()),
        "reproj_point_mean_px": float(per_point.mean()),
        "colmap_reported_mean_px": colmap,
        "points_in_front_fraction": float((depth > 0).double().mean()),
    }


def _failures(r: CheckReport) -> "list[str]":
    out = []
    if not r.kornia_max_px <= MAX_PX:
        out.append(f"kornia projection disagrees with nerfpipe by {r.kornia_max_px:.3g} px (> {MAX_PX})")
    if not r.kornia_unproject_max_px <= MAX_PX:
        out.append(f"kornia unprojection disagrees with nerfpipe by {r.kornia_unproject_max_px:.3g} px (> {MAX_PX})")
    if not r.roundtrip_max_px <= MAX_PX:
        out.append(f"pixel -> ray -> pixel round trip is off by {r.roundtrip_max_px:.3g} px (> {MAX_PX})")
    if not r.facing_fraction >= MIN_FACING:
        out.append(f"only {r.facing_fraction:.0%} of cameras look towards the scene box (< {MIN_FACING:.0%})")
    if r.points_in_front_fraction is not None and not r.points_in_front_fraction >= MIN_IN_FRONT:
        out.append(f"only {r.points_in_front_fraction:.1%} of sparse observations are in front of their camera")
    ref = r.colmap_reported_mean_px
    if ref is not None and r.reproj_point_mean_px is not None:
        ours = r.reproj_point_mean_px
        if not ours <= REPROJ_FACTOR * ref + REPROJ_SLACK_PX:
            out.append(f"reprojection error {ours:.3g} px is far above COLMAP's {ref:.3g} px")
        elif not abs(ours - ref) <= REPROJ_AGREE_PX:
            out.append(f"reprojection error {ours:.4g} px differs from COLMAP's {ref:.4g} px by > {REPROJ_AGREE_PX} px")
    return out


def check_scene(scene: SceneData, samples: int = 16, seed: int = 0) -> CheckReport:
    """Run every check on a scene; ``report.failures`` lists broken conventions."""
    near = max(scene.near, 0.01 * scene.far)  # a zero near would put probes on the camera centre
    depths = [near, 0.5 * (near + scene.far), scene.far]
    figures = camera_checks(scene.cameras, depths, samples, seed)
    fisheye = bool((scene.cameras.distortion == Distortion.FISHEYE).any())
    report = CheckReport(
        num_cameras=len(scene.cameras),
        facing_fraction=facing_fraction(scene.cameras, scene.aabb),
        fisheye_checked_by_kornia=True if fisheye else None,
        **figures,
        **(sparse_reprojection(scene) or {}),
    )
    report.failures = _failures(report)
    return report
