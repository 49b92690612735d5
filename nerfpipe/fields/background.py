"""The field outside the object region: coarse grids over contracted space, rendered behind the box.

Real captures show floor, walls and sky around the object. Without a place for them, the object's
field explains them as fog inside its box. This field models them where they are, at a resolution
that falls with distance: points outside the box are contracted into ``[-2, 2]^3``
(:func:`nerfpipe.functional.contraction.contract`) and read from small dense grids there; each ray
gets a fixed number of samples from where it leaves the box to far away, spaced uniformly in
disparity (as NeRF++'s outer volume and mip-NeRF 360's contracted space).

Rendered alone, it gives for each ray the colour seen behind the box and that colour's opacity;
the object's field composites over it (``rgb_inner + (1 - acc_inner) * rgb_behind``).
"""

from dataclasses import dataclass

import math

import torch
from torch import nn

from nerfpipe.fields.grid import DenseGridEncoding, grid_gather
from nerfpipe.functional.contraction import contract, disparity_samples, disparity_to_distance, to_box_coordinates
from nerfpipe.functional.packed import distortion_loss_packed
from nerfpipe.functional.sampling import pdf_samples
from nerfpipe.functional.volrend import insert_layer, render_weights
from nerfpipe.util.typing import Float, Tensor


@dataclass
class BackgroundFieldConfig:
    """The contracted field behind the object region (``fast`` model, real captures)."""

    levels: "tuple[int, ...]" = (6,)
    """Vertices per axis of each grid level over the contracted cube ``[-2, 2]^3``. Coarse on purpose: finer
    levels paint what surrounds the object onto the shell, each photograph its own way. colmap_mouse, val
    PSNR after 600 steps (``python -m benchmarks.steps``-style runs, depth loss on, no colour corrections):
    (16, 32, 64) 22.7 dB, (16, 32) 23.2, (8, 16) 23.6, (8,) 24.2; without the field 22.2. (8,) until session 36;
    since the table's texture lies among its samples, (6,) against (8,) side by side (7 views at 400 px, one ray per
    pixel): colmap_mouse 24.54 / 24.58 → **24.60 / 24.72** after 600 / 900 ((4,) 24.51 / 24.44), the room scene 27.99 /
    31.01 → 28.18 / 31.05 after 300 / 600, the 23-photo posed cut 23.74 / 22.99 → 23.75 / **23.56** (3 views), ngp_fox
    26.71 / 27.88 → 26.70 / 27.87 (9 views), photos_sceaux_castle 14.37 / 14.25 → 14.38 / 14.48 (2 views). Session 44, not
    kept: the grid's linear part grown to 2 / 3 object regions (the backdrop cards behind colmap_mouse inside it) with
    (12,) / (16,) vertices, 24.02 / 23.75 dB after 600 steps against 24.62: finer near the box paints it all the same."""
    feature_channels: int = 2
    """Colour features per vertex and level."""
    hidden: int = 32
    """Width of the colour MLP."""
    num_samples: int = 12
    """Samples per ray from the box exit to ``far_factor`` box sizes away (uniform in disparity). A ray crosses a few
    cells of the coarse grid (``levels``): 24 until session 40; 12 side by side at equal steps (one ray per pixel, 400
    px): colmap_mouse (7 views) 24.54 / 24.70 → 24.61 / 24.70 dB after 600 / 900 steps at 0.91x the seconds per step,
    the 23-photo posed cut (3 views) 23.81 / 23.60 → 23.77 / 23.69 after 300 / 600 at 0.93x, the room scene (``nerfpipe
    synth --scene room``, 7 views) 28.03 / 31.00 → 28.00 / 30.98 at 0.98x; 16 on colmap_mouse 24.56 / 24.66 (session
    13, with the 8³ field then: 12 / 8 lost 0.06 / 0.12 dB after 300 steps)."""
    far_factor: float = 1000.0
    """Where the samples end, in box diagonals from the box centre."""
    view_dependent: bool = False
    """Colour depends on the viewing direction (off: a coarse field seen from few directions per point
    would fit each photograph's view of it on its own and show streaks in between)."""
    grid_lr: float = 0.1
    """Adam learning rate of its grids."""
    distortion_weight: float = 0.0
    """Weight of mip-NeRF 360's distortion loss on its samples (in their disparity-uniform coordinate):
    the opacity along each ray gathers at one depth, so what the photographs share is put at one place
    instead of painted at each view's own depth (0: off)."""
    fine_levels: "tuple[int, ...]" = ()
    """Vertices per axis of a finer field (density and colour, hashed where larger than
    ``2**fine_log2_rows`` rows) read at ``fine_samples`` samples drawn from the weights of the coarse
    density (a proposal, as in mip-NeRF 360 and nerfacto): the fine field renders, the coarse density
    only learns where to sample (its weights must bound the fine ones: :func:`outer_weight_loss`).
    Empty: the coarse grids render, density and colour. Session 77, a synthetic room whose far wall is patterned
    (``nerfpipe synth --scene room --views 26 --size 400x300``, 4 views, the average after 1,000 steps): none 28.93 dB,
    (16, 64) with 16 + 16 samples 29.04 at 1.16x the seconds per step, (32, 128) with 16 + 24 28.91 at 1.24x; a
    second coarse level (``levels`` (6, 16)) 28.87: no gain the time would not buy as steps."""
    fine_samples: int = 32
    """Samples per ray of the fine field."""
    fine_log2_rows: int = 17
    """Rows of each hashed fine level, as a power of two."""
    proposal_weight: float = 1.0
    """Weight of the loss that makes the coarse weights bound the fine ones (fine field only)."""
    front: "bool | None" = None
    """Rays that cross the box also read the field in front of it (:meth:`BackgroundField.front`): at the
    intervals of a ray that misses the box, cut where the ray enters it, composited with what lies behind the box
    (``FastModel._in_front``). Without it the field's haze between the cameras and the table was seen only around
    the box, whose outline showed on the table in every orbit. Default: from the fast model's ``front_min_images``
    training images on (``nerfpipe.models.fast.FRONT_MIN_IMAGES``; with fewer it costs held-out PSNR)."""
    init_density: float = 0.01
    """Density everywhere at the start, per unit of length in contracted space (the whole shell from the box
    to infinity is one unit deep along a ray from the centre): low, so the field starts transparent and
    the colour at infinity (the model's direction-only background) shows through."""


@dataclass
class BehindBox:
    """What lies behind the box along each ray."""

    rgb: Float[Tensor, "num_rays 3"]
    """Colour composited over the given background."""
    acc: Float[Tensor, "num_rays"]
    """Opacity of the background field along the ray (the rest is the given background)."""
    depth: Float[Tensor, "num_rays"]
    """Expected distance ``sum w_i t_i`` of the background field's samples."""
    distortion: "Float[Tensor, 'num_rays'] | None" = None
    """Distortion loss per ray, in training when ``distortion_weight`` is set."""
    proposal: "Float[Tensor, 'num_rays'] | None" = None
    """Proposal loss per ray (:func:`outer_weight_loss`), in training with a fine field."""


def outer_weight_loss(
    edges: Float[Tensor, "num_rays num_fine_edges"], weights: Float[Tensor, "num_rays num_fine"], coarse: Float[Tensor, "num_rays num_coarse"]
) -> Float[Tensor, "num_rays"]:
    """mip-NeRF 360's proposal loss: how much the fine ``weights`` exceed the coarse weights' bound.

    The coarse intervals tile ``[0, 1]`` evenly (``num_coarse`` of them); the fine intervals have the
    sorted ``edges`` in ``[0, 1]``. The bound of a fine interval is the sum of the coarse weights of every
    coarse interval it overlaps; the loss per ray is ``sum max(0, w - bound)^2 / w`` over the fine
    intervals, with the fine weights detached (only the coarse density learns from it).
    """
    s = coarse.shape[-1]
    cdf = torch.cat([torch.zeros_like(coarse[:, :1]), coarse.cumsum(-1)], dim=-1)
    lo = (edges[:, :-1] * s).floor().long().clamp(0, s)
    hi = (edges[:, 1:] * s).ceil().long().clamp(0, s)
    bound = cdf.gather(1, hi) - cdf.gather(1, lo)
    w = weights.detach()
    return ((w - bound).clamp(min=0) ** 2 / (w + 1e-7)).sum(-1)


def _outer_weight_loss_reference(edges, weights, coarse) -> Tensor:
    """Slow reference of :func:`outer_weight_loss`: interval overlaps tested one pair at a time."""
    s = coarse.shape[-1]
    out = []
    for e, w, c in zip(edges.tolist(), weights.detach().tolist(), coarse):
        total = coarse.new_zeros(())
        for i, wi in enumerate(w):
            bound = sum((c[j] for j in range(s) if j / s < e[i + 1] and (j + 1) / s > e[i]), coarse.new_zeros(()))
            total = total + (wi - bound).clamp(min=0) ** 2 / (wi + 1e-7)
        out.append(total)
    return torch.stack(out)


class BackgroundField(nn.Module):
    """Density and colour over contracted space outside ``aabb``.

    Args:
        cfg: sizes and sampling.
        aabb: the object region ``[min, max]`` (maps to ``[-1, 1]^3`` before contraction).
        code_dim: size of a per-ray appearance code appended to the colour MLP's input (0: none).
    """

    def __init__(self, cfg: BackgroundFieldConfig, aabb: Float[Tensor, "2 3"], code_dim: int = 0) -> None:
        super().__init__()
        self.code_dim = code_dim
        self.cfg = cfg
        self.register_buffer("aabb", aabb.detach().clone().float())
        self.t_far = cfg.far_factor * float((aabb[1] - aabb[0]).norm())
        """Where the samples end (``far_factor`` box diagonals), read once (not from the device every step)."""
        resolutions = [(n, n, n) for n in cfg.levels]
        self.density_grid = DenseGridEncoding(resolutions, 1, init_scale=0.0)
        self.fine = bool(cfg.fine_levels)
        if self.fine:  # the coarse grid only proposes; the fine grids render
            fine = [(n, n, n) for n in cfg.fine_levels]
            self.fine_density_grid = DenseGridEncoding(fine, 1, init_scale=0.0, max_rows=1 << cfg.fine_log2_rows)
            self.feature_grid = DenseGridEncoding(fine, cfg.feature_channels, max_rows=1 << cfg.fine_log2_rows)
        else:
            self.feature_grid = DenseGridEncoding(resolutions, cfg.feature_channels)
        self.shift = math.log(math.expm1(cfg.init_density))
        self.mlp = nn.Sequential(
            nn.Linear(self.feature_grid.out_dim + (16 if cfg.view_dependent else 0) + code_dim, cfg.hidden), nn.ReLU(inplace=True), nn.Linear(cfg.hidden, 3)
        )

    def grid_parameters(self) -> "list[nn.Parameter]":
        """The grids' tables (their own learning rate)."""
        grids = [self.density_grid, self.feature_grid] + ([self.fine_density_grid] if self.fine else [])
        return [p for g in grids for p in g.parameters()]

    def _corners(self, points: Float[Tensor, "num_points 3"], grid: "DenseGridEncoding | None" = None) -> list:
        grid = self.density_grid if grid is None else grid
        x01 = 0.25 * (contract(to_box_coordinates(points, self.aabb)) + 2.0)
        return [grid.corners(level, x01) for level in range(len(grid.resolutions))]

    def _contracted_lengths(self, origins, directions, t_start, deltas) -> Float[Tensor, "num_rays num_samples"]:
        """Lengths of the sample intervals in contracted space (chords between their contracted ends)."""
        ends = torch.cat([t_start[:, None], t_start[:, None] + deltas.cumsum(-1)], dim=-1)
        pts = origins[:, None, :] + ends[..., None] * directions[:, None, :]
        c = contract(to_box_coordinates(pts, self.aabb))
        return (c[:, 1:] - c[:, :-1]).norm(dim=-1)

    def _sigma(self, grid: DenseGridEncoding, corners: list) -> Float[Tensor, "num_points"]:
        """Density from ``grid`` at points given by their ``corners`` (:meth:`_corners`)."""
        raw = sum(grid_gather(t, i, w) for t, (i, w) in zip(grid.tables, corners))
        return nn.functional.softplus(raw[:, 0] + self.shift)

    def density(self, points: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points"]:
        """The density that renders (the fine field's, when there is one)."""
        grid = self.fine_density_grid if self.fine else self.density_grid
        return self._sigma(grid, self._corners(points, grid))

    def _colours(self, corners: list, dir_code: Float[Tensor, "num_rays 16"], codes, s: int) -> Float[Tensor, "num_points 3"]:
        """Colour at ``s`` samples per ray given by their ``corners`` (:meth:`_corners`)."""
        feats = [grid_gather(tb, i, w) for tb, (i, w) in zip(self.feature_grid.tables, corners)]
        if self.cfg.view_dependent:
            feats.append(dir_code.repeat_interleave(s, dim=0))
        if self.code_dim:
            feats.append(codes.repeat_interleave(s, dim=0))
        return torch.sigmoid(self.mlp(torch.cat(feats, dim=-1)))

    def front(
        self,
        origins: Float[Tensor, "num_rays 3"],
        directions: Float[Tensor, "num_rays 3"],
        dir_code: Float[Tensor, "num_rays 16"],
        t_start: Float[Tensor, "num_rays"],
        t_end: Float[Tensor, "num_rays"],
        generator: "torch.Generator | None" = None,
        codes: "Float[Tensor, 'num_rays code_dim'] | None" = None,
    ) -> "tuple[Float[Tensor, 'num_rays 3'], Float[Tensor, 'num_rays']]":
        """The field between ``t_start`` and ``t_end`` (where a ray enters the box): its colour (premultiplied by
        its opacity) and the transmittance it leaves.

        The intervals are those :meth:`forward` gives a ray from ``t_start`` (uniform in disparity to far away),
        each cut at ``t_end`` (those beyond it empty, weighing nothing), so a ray that crosses the box sees the
        space in front of it as its neighbour that misses the box does: the same samples, no seam at the box's
        outline. The coarse density renders (the fine field, when there is one, is sampled behind the box only).
        """
        n, s = origins.shape[0], self.cfg.num_samples
        edges = disparity_to_distance(t_start, self.t_far, torch.linspace(0.0, 1.0, s + 1, device=origins.device, dtype=t_start.dtype))
        edges = torch.minimum(edges, torch.maximum(t_end, t_start)[:, None])
        deltas = edges[:, 1:] - edges[:, :-1]
        u = torch.rand((n, s), device=origins.device, generator=generator) if self.training else torch.full_like(deltas, 0.5)
        t = edges[:, :-1] + u * deltas
        lengths = self._contracted_lengths(origins, directions, t_start, deltas)
        points = (origins[:, None, :] + t[..., None] * directions[:, None, :]).reshape(-1, 3)
        corners = self._corners(points)
        sigma = self._sigma(self.density_grid, corners).view(n, s)
        if self.fine:
            corners = self._corners(points, self.fine_density_grid)
        weights, _ = render_weights(sigma, lengths)
        rgb = (weights[..., None] * self._colours(corners, dir_code, codes, s).view(n, s, 3)).sum(-2)
        return rgb, 1.0 - weights.sum(-1)

    def forward(
        self,
        origins: Float[Tensor, "num_rays 3"],
        directions: Float[Tensor, "num_rays 3"],
        dir_code: Float[Tensor, "num_rays 16"],
        t_start: Float[Tensor, "num_rays"],
        background: Float[Tensor, "num_rays 3"],
        generator: "torch.Generator | None" = None,
        codes: "Float[Tensor, 'num_rays code_dim'] | None" = None,
        layer: "tuple[Float[Tensor, 'num_rays'], Float[Tensor, 'num_rays'], Float[Tensor, 'num_rays 3']] | None" = None,
    ) -> BehindBox:
        """Render the field along each ray from ``t_start`` on, composited over ``background``; ``codes``
        (one per ray, when built with ``code_dim``) condition the colour on the ray's image. ``layer``
        (distance, opacity, colour per ray: the support plane's texture) is composited at its distance among
        the samples (:func:`insert_layer`): what the field holds in front of it hides it.

        In training (``self.training``) the samples are stratified (random inside their intervals).
        """
        n, s = origins.shape[0], self.cfg.num_samples
        jitter = torch.rand((n, s), device=origins.device, generator=generator) if self.training else None
        t, deltas = disparity_samples(t_start, self.t_far, s, jitter)
        deltas = self._contracted_lengths(origins, directions, t_start, deltas)
        points = (origins[:, None, :] + t[..., None] * directions[:, None, :]).reshape(-1, 3)
        corners = self._corners(points)
        sigma = self._sigma(self.density_grid, corners).view(n, s)
        proposal = None
        if self.fine:
            coarse, _ = render_weights(sigma, deltas)
            edges = pdf_samples(torch.linspace(0.0, 1.0, s + 1, device=origins.device).expand(n, s + 1), coarse.detach(),
                                self.cfg.fine_samples + 1, perturb=self.training, generator=generator)
            t_edges = disparity_to_distance(t_start, self.t_far, edges)
            t = 0.5 * (t_edges[:, 1:] + t_edges[:, :-1])
            s = self.cfg.fine_samples
            deltas = self._contracted_lengths(origins, directions, t_edges[:, 0], t_edges[:, 1:] - t_edges[:, :-1])
            points = (origins[:, None, :] + t[..., None] * directions[:, None, :]).reshape(-1, 3)
            corners = self._corners(points, self.fine_density_grid)
            sigma = self._sigma(self.fine_density_grid, corners).view(n, s)
        rgbs = self._colours(corners, dir_code, codes, s).view(n, s, 3)
        weights, _ = render_weights(sigma, deltas)
        if self.fine and self.training:
            proposal = outer_weight_loss(edges, weights, coarse)
        field_weights = weights
        if layer is not None:
            weights, layer_weight = insert_layer(weights, t, *layer[:2])
        acc = weights.sum(-1)
        rgb = (weights[..., None] * rgbs).sum(-2) + (1.0 - acc)[:, None] * background
        depth = (weights * t).sum(-1)
        if layer is not None:
            rgb = rgb + layer_weight[:, None] * (layer[2] - background)
            depth, acc = depth + layer_weight * layer[0], acc + layer_weight
        distortion = None
        if self.training and self.cfg.distortion_weight > 0 and not self.fine:
            edges = torch.arange(s + 1, device=origins.device, dtype=weights.dtype) / s  # uniform in disparity
            ray_indices = torch.arange(n, device=origins.device).repeat_interleave(s)
            distortion = distortion_loss_packed(
                field_weights.reshape(-1), edges[:-1].repeat(n), edges[1:].repeat(n), ray_indices, n
            )
        return BehindBox(rgb=rgb, acc=acc, depth=depth, distortion=distortion, proposal=proposal)
