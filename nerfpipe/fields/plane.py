"""The plane an object stands on, as a texture with an opacity: what a capture of an object on a table shows of the
table outside the object region.

The field behind the box (:mod:`nerfpipe.fields.background`) is coarse on purpose (finer levels paint the surroundings
onto its shell, each photograph its own way), so the table around the object renders smooth: on colmap_mouse the rays
that meet the table plane outside the object region are 63 % of the held-out pixels and carry 63 % of the squared error
(23.7 dB there, session 35). Its geometry known (the support plane of the sparse points,
:func:`nerfpipe.training.trainer.support_plane_of`), a 2D texture on it is seen consistently from every photograph. It is
a sheet, not a wall: its opacity (nearly 0 at first) lets it go transparent where the photographs show something else
beyond it (the floor past a table's edge, the walls of a room), and the field behind the box shows through.

The plane's coordinates are contracted as mip-NeRF 360 contracts space, in 2D: the disc of the object region's radius
around its centre is linear, everything farther is squeezed into the ring out to twice that radius.
"""

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor, nn


@dataclass
class PlaneTextureConfig:
    """The texture on the support plane (``fast`` model, real captures standing on a table or floor). colmap_mouse side by
    side after 600 / 900 steps (session 35, before ``initial_opacity``): the default then 24.52 / 24.56 dB; 4 features per texel 24.52 / 24.54; a 1,024
    level 24.46 / 24.47; a 64-wide MLP 24.53 / 24.55; learning rate 0.1 / 0.3 24.47 / 24.55 and 24.49 / 24.50 (7 held-out views at 400 px, one ray per pixel).
    Session 44, not kept: a colour that depends on the viewing direction (a second MLP of the texels and the direction code
    added to the colour's logits, starting at zero; the opacity view-independent) 24.48 / 24.23 dB after 600 / 900 steps,
    averaged 24.67, against the default's 24.62 / 24.72, averaged 24.78: the table's brightness that the held-out views
    miss is the light of each photograph (the photographer's shadow in the top-down views), not a sheen."""

    levels: "tuple[int, ...]" = (16, 32, 64, 128, 256, 512)
    """Texels per side of each level over the contracted plane ``[-2, 2]^2`` (the object region's disc is its middle half)."""
    feature_channels: int = 2
    """Features per texel and level."""
    hidden: int = 32
    """Width of the colour MLP."""
    grid_lr: float = 0.03
    """Adam learning rate of the textures."""
    initial_opacity: float = 0.12
    """The texture's opacity everywhere at the start (its MLP's opacity bias): mostly transparent, so that the field
    behind the box keeps what it holds until the photographs agree on the table. Side by side (session 36, 7 views at
    400 px, one ray per pixel) colmap_mouse after 600 / 900 steps: 0.018 (sigmoid(-4), until then) 24.44 / 24.51 dB,
    0.06 24.49 / 24.54, **0.12 24.54 / 24.58**, 0.25 24.49 / 24.57, 0.5 24.45 / 24.55; the room scene after 300 / 600
    27.69 / 30.96 → 27.99 / 31.01; the 23-photo posed cut 23.59 / 23.03 → 23.74 / 22.99 (3 views)."""
    min_views: int = 2
    """Training cameras that must see a point of the plane for the texture to be there (:meth:`PlaneTexture.cover`;
    0: everywhere). Where no photograph shows the table, its texels are never trained, yet the shared MLP and the
    coarse levels give them a colour and an opacity that drift as training goes on; the field behind the box, coarse
    and smooth, extends what it holds there instead. Session 82: COLMAP's poses of the 19 photos that SfM registered
    of a 23-photo folder of colmap_mouse (16 training images, 3 views at 400 px, one ray per pixel): a low held-out
    view whose lower half shows table no training photograph shows fell from 25.47 dB after 300 steps to 16.53 after
    1,200 (a dark smear on the table near the camera); 2 cameras 23.46 after 1,200 (the 3 views 19.97 → **22.32**
    dB; 1 camera 21.59; the texture off 22.77, but 1.1 dB less on another view). Side by side at equal steps (1 thread,
    one ray per pixel, 400 px, the average after 600 / 1,200 steps), none / 1 / **2**: colmap_mouse (7 views)
    24.887 / 24.996, 24.879 / 25.002, **24.863 / 25.013** (no held-out pixel uncovered); the room scene (``nerfpipe
    synth --scene room --views 26 --size 400x300 --seed 3``, 4 views) 26.782 / 27.068, 26.402 / 26.874, **26.821 /
    27.597**."""
    min_incidence: float = 0.0
    """A camera counts for :attr:`min_views` where it sees the plane at least this steeply (the cosine between its ray
    and the plane's normal; 0: at any angle). Seen at a grazing angle, a pixel spans a long strip of the table and the
    texture learns streaks along the camera's rays, but many cameras at grazing angles still agree on it: 0.2 (side by
    side as :attr:`min_views`, with 1 / 2 cameras) gave the room 27.739 / 28.061 and 27.651 / 28.056 dB after 600 /
    1,200 steps, the posed 23-photo cut of colmap_mouse (3 views) 25.042 / 25.088 and 25.025 / 25.171 against 24.970 /
    24.917, the 19 photos SfM registered of that cut's folder (3 views) 23.850 / 22.495 and 23.931 / 22.547 against
    23.489 / 22.388, but colmap_mouse 24.773 / 24.829 and 24.800 / 24.852 against 24.887 / 24.996: 10-24 % of four
    of its held-out views lie where its 49 training cameras see the far table only at grazing angles, and the texture
    they learn there pays."""
    coverage_size: int = 128
    """Cells per side of the coverage grid over the contracted plane (as the textures' ``[-2, 2]^2``)."""


def plane_hits(
    origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"], plane: Float[Tensor, "4"]
) -> "tuple[Float[Tensor, 'num_rays'], torch.Tensor]":
    """Distance along each ray to ``plane`` (``a x + b y + c z + d = 0``, positive on the cameras' side) and whether
    the ray meets it from that side in front of its origin."""
    height = origins @ plane[:3] + plane[3]
    rate = directions @ plane[:3]
    t = -height / torch.where(rate.abs() > 1e-12, rate, torch.full_like(rate, -1e-12))
    return t, (height > 0) & (rate < 0) & (t > 0)


def contract_2d(u: Float[Tensor, "num_points 2"]) -> Float[Tensor, "num_points 2"]:
    """mip-NeRF 360's contraction in the plane: identity inside the unit disc, ``(2 - 1/|u|) u/|u|`` outside."""
    r = u.norm(dim=-1, keepdim=True).clamp(min=1.0)  # 1 inside the disc: no division by a vanishing norm
    return u * (2.0 - 1.0 / r) / r


class PlaneTexture(nn.Module):
    """Colour and opacity on a plane, from multiresolution 2D feature grids and a small MLP.

    Args:
        cfg: sizes.
        plane: ``(a, b, c, d)``, unit normal towards the cameras.
        centre: a point whose projection on the plane is the texture's centre (the object region's centre).
        radius: the plane's linear disc radius (beyond it the coordinates are contracted).
        code_dim: size of a per-ray appearance code appended to the MLP's input (0: none).
    """

    def __init__(self, cfg: PlaneTextureConfig, plane: Float[Tensor, "4"], centre: Float[Tensor, "3"], radius: float, code_dim: int = 0) -> None:
        super().__init__()
        self.cfg, self.code_dim = cfg, code_dim
        plane = plane.detach().float() / plane[:3].norm()  # a unit normal
        normal = plane[:3]
        e1 = torch.linalg.cross(normal, torch.eye(3)[int(normal.abs().argmin())])
        e1 = e1 / e1.norm()
        e2 = torch.linalg.cross(normal, e1)
        origin = centre.detach().float() - (centre.float() @ normal + plane[3]) * normal
        self.register_buffer("plane", plane)
        self.register_buffer("basis", torch.stack([e1, e2]))
        self.register_buffer("origin", origin)
        self.radius = float(radius)
        self.register_buffer("coverage", torch.ones(1, 1, cfg.coverage_size, cfg.coverage_size))
        """Whether the training cameras see each point of the plane (:meth:`cover`), ``[1, 1, n, n]`` over the
        contracted coordinates, 0 to 1; the texture's opacity is multiplied by it (bilinear)."""
        self.textures = nn.ParameterList(
            [nn.Parameter(1e-4 * (2 * torch.rand(1, cfg.feature_channels, n, n) - 1)) for n in cfg.levels]
        )
        self.mlp = nn.Sequential(nn.Linear(cfg.feature_channels * len(cfg.levels) + code_dim, cfg.hidden), nn.ReLU(inplace=True),
                                 nn.Linear(cfg.hidden, 4))
        with torch.no_grad():
            self.mlp[2].bias[3] = math.log(cfg.initial_opacity / (1.0 - cfg.initial_opacity))  # mostly transparent at first (initial_opacity)

    def coordinates(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 2"]:
        """Contracted plane coordinates of ``points`` (on the plane) in ``[-1, 1]^2``."""
        u = (points - self.origin) @ self.basis.T / self.radius
        return 0.5 * contract_2d(u)

    def points_at(self, coordinates: Float[Tensor, "num_points 2"]) -> Float[Tensor, "num_points 3"]:
        """Points on the plane at contracted ``coordinates`` in ``[-1, 1]^2`` (the inverse of :meth:`coordinates`;
        the rim, infinitely far, is brought in to 1,000 radii)."""
        s = (2.0 * coordinates).norm(dim=-1, keepdim=True)
        r = torch.where(s <= 1.0, s, 1.0 / (2.0 - s.clamp(max=2.0 - 1e-3)))  # |u| of contract_2d's input
        u = 2.0 * coordinates * r / s.clamp(min=1e-12)
        return self.origin + self.radius * (u @ self.basis)

    @torch.no_grad()
    def cover(self, cameras, chunk: int = 16) -> None:
        """Set :attr:`coverage` from ``cameras`` (``project(points) -> (pixels, depth)`` with ``width`` and ``height``,
        e.g. the training :class:`~nerfpipe.data.cameras.Cameras`): the share of ``cfg.min_views`` of them that see the
        plane's point from its side, in front of them and inside their image, at least as steeply as
        ``cfg.min_incidence`` (at most 1; read bilinearly, so it fades over one cell); occlusion is not checked.
        ``cfg.min_views`` 0: 1 everywhere."""
        n = self.cfg.coverage_size
        if self.cfg.min_views <= 0 or len(cameras) == 0:
            self.coverage.fill_(1.0)
            return
        axis = torch.linspace(-1.0, 1.0, n, device=self.origin.device)
        ys, xs = torch.meshgrid(axis, axis, indexing="ij")  # grid_sample's (x, y) order, align_corners=True
        points = self.points_at(torch.stack([xs, ys], dim=-1).reshape(-1, 2))
        cameras = cameras.to(self.origin.device)
        count = torch.zeros(len(points), device=points.device)
        for start in range(0, len(cameras), chunk):
            cams = cameras[start : start + chunk]
            pix, depth = cams[:, None].expand(len(cams), len(points)).project(points[None].expand(len(cams), -1, -1))
            w, h = cams.width.reshape(-1, 1).to(pix), cams.height.reshape(-1, 1).to(pix)
            seen = (depth > 0) & (pix[..., 0] >= 0) & (pix[..., 0] <= w) & (pix[..., 1] >= 0) & (pix[..., 1] <= h)
            to_cam = cams.world_from_cam[:, None, :3, 3] - points[None]
            cosine = (to_cam @ self.plane[:3]) / to_cam.norm(dim=-1).clamp(min=1e-12)  # > 0: the camera above the plane
            count += (seen & (cosine > 0) & (cosine >= self.cfg.min_incidence)).sum(0)
        self.coverage.copy_((count.view(1, 1, n, n) / self.cfg.min_views).clamp(max=1.0))

    def rgba(self, points: Float[Tensor, "num_points 3"], codes: "Float[Tensor, 'num_points code_dim'] | None" = None) -> Float[Tensor, "num_points 4"]:
        """Colour and opacity at ``points`` on the plane (``codes``: per-point appearance codes when built with ``code_dim``)."""
        grid = self.coordinates(points)[None, :, None, :]  # [1, n, 1, 2] for grid_sample
        feats = [nn.functional.grid_sample(t, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, :, :, 0].T for t in self.textures]
        if self.code_dim:
            feats.append(codes)
        out = torch.sigmoid(self.mlp(torch.cat(feats, dim=-1)))  # colour and opacity
        seen = nn.functional.grid_sample(self.coverage, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, 0, :, 0]
        return torch.cat([out[:, :3], out[:, 3:] * seen[:, None]], dim=-1)

    def layer(
        self, origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"],
        codes: "Float[Tensor, 'num_rays code_dim'] | None" = None,
    ) -> "tuple[Float[Tensor, 'num_rays'], Float[Tensor, 'num_rays'], Float[Tensor, 'num_rays 3']]":
        """Where each ray meets the plane (0 where it does not), the texture's opacity there (0 where it does not)
        and its colour: a layer to composite at its distance among a field's samples
        (:func:`nerfpipe.functional.volrend.insert_layer`)."""
        t, hit = plane_hits(origins, directions, self.plane)
        t = torch.where(hit, t, torch.zeros_like(t))
        out = self.rgba(origins + t[:, None] * directions, codes)
        return t, torch.where(hit, out[:, 3], torch.zeros_like(out[:, 3])), out[:, :3]

    def forward(
        self, origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"], background: Float[Tensor, "num_rays 3"],
        codes: "Float[Tensor, 'num_rays code_dim'] | None" = None,
    ) -> Float[Tensor, "num_rays 3"]:
        """The plane's colour composited with its opacity over ``background`` where the rays meet the plane from the
        cameras' side (the others keep ``background``)."""
        _, alpha, rgb = self.layer(origins, directions, codes)
        return alpha[:, None] * rgb + (1.0 - alpha[:, None]) * background
