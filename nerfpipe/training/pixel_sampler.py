"""Training rays: random pixels drawn uniformly across all images of a split.

Images are loaded once and kept as one uint8 tensor of pixels ``[P, C]`` (images may differ in
size); a batch picks pixel indices, finds their camera through per-image offsets and generates
rays with :func:`nerfpipe.data.rays.generate_rays`. RGBA pixels are composited on the batch's
background colour (random per ray in training when the mode is ``random``). With a ``max_side``,
images larger than that are area-downscaled once at load and rays come from the matching cameras
(:meth:`nerfpipe.data.cameras.Cameras.capped`).
"""

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from nerfpipe.data.background import background_colors, composite_pixels
from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import RayBundle, generate_rays
from nerfpipe.data.scene import SceneData
from nerfpipe.util.typing import Float, Int, Tensor, UInt8


def load_split_pixels(scene: SceneData, split: str, cameras: "Cameras | None" = None) -> "tuple[Tensor, Tensor]":
    """All pixels of a split as uint8 ``[P, C]`` and the offsets ``[n+1]`` of each image; with ``cameras``
    (the split's, possibly :meth:`~nerfpipe.data.cameras.Cameras.capped`), each image area-resized to its size."""
    chans = 4 if scene.has_alpha else 3
    flat, offsets = [], [0]
    for k, i in enumerate(scene.splits[split]):
        img = np.asarray(scene.images.load(int(i)))
        if img.shape[-1] < chans:
            img = np.concatenate([img, np.full((*img.shape[:2], chans - img.shape[-1]), 255, np.uint8)], axis=-1)
        img = torch.from_numpy(np.ascontiguousarray(img[..., :chans]))
        if cameras is not None and (int(cameras.height[k]), int(cameras.width[k])) != tuple(img.shape[:2]):
            img = area_resize(img, int(cameras.width[k]), int(cameras.height[k]))
        flat.append(img.reshape(-1, chans))
        offsets.append(offsets[-1] + flat[-1].shape[0])
    return torch.cat(flat), torch.tensor(offsets, dtype=torch.long)


def area_resize(img: UInt8[Tensor, "H W C"], width: int, height: int) -> UInt8[Tensor, "h w C"]:
    """``img`` resized to ``width x height`` by area averaging (each pixel the mean of what it covers), rounded to uint8."""
    x = img.permute(2, 0, 1)[None].float()
    return F.interpolate(x, size=(height, width), mode="area")[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8)


@dataclass
class PixelBatch:
    """Rays with their target colours and the background the targets were composited on."""

    rays: RayBundle
    rgb: Float[Tensor, "num_rays 3"]
    background: Float[Tensor, "num_rays 3"]
    depth: "Float[Tensor, 'num_rays'] | None" = None
    """Distance along the ray at which a sparse 3D point was seen (NaN for rays without one); None
    when the batch has no such rays."""


class TrackRays:
    """Rays through the keypoints of the sparse points' track observations (COLMAP), with the distance
    of the observed point along each ray and the keypoint's pixel colour.

    This is the evidence SfM already has about where rays stop (as in DS-NeRF): the space in front
    of each observed point is empty. Uses the points' tracks (:class:`nerfpipe.data.scene.Points3D`
    ``track_*``); observations of cameras outside the split, with keypoints outside the image or
    points behind the camera are dropped.
    """

    def __init__(self, scene: SceneData, split: str, pixels: UInt8[Tensor, "P C"], offsets: Tensor, cameras: "Cameras | None" = None) -> None:
        """``cameras``: the split's cameras the ``pixels`` were taken at (default the scene's; smaller ones scale the keypoints)."""
        pts = scene.points
        local = torch.full((len(scene.cameras),), -1, dtype=torch.long)
        local[torch.as_tensor(scene.splits[split], dtype=torch.long)] = torch.arange(len(scene.splits[split]))
        cam = local[pts.track_camera]
        uv = pts.track_xy.double()
        xyz = pts.xyz.double()[pts.track_point]
        full = scene.split_cameras(split)
        cameras = full if cameras is None else cameras
        keep = cam >= 0
        cam, uv, xyz = cam[keep], uv[keep], xyz[keep]
        scale = torch.stack([cameras.width.double() / full.width.double(), cameras.height.double() / full.height.double()], -1).reshape(-1, 2)
        uv = uv * scale[cam]
        w, h = cameras.width[cam].double(), cameras.height[cam].double()
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
        cam, uv, xyz = cam[inside], uv[inside], xyz[inside]
        rays = generate_rays(cameras, cam, uv.to(cameras.fx.dtype))
        t = ((xyz.to(rays.origins) - rays.origins) * rays.directions).sum(-1)
        front = t > 0
        self.rays = rays[front].to(dtype=torch.float32)
        self.t = t[front].float()
        col, row = uv[front, 0].long(), uv[front, 1].long()
        cam = cam[front]
        self.pixels = pixels[offsets[cam] + row * cameras.width[cam].long() + col]

    def __len__(self) -> int:
        return len(self.t)

    def sample(self, num_rays: int, generator: "torch.Generator | None") -> "tuple[RayBundle, Tensor, Tensor]":
        """``(rays, uint8 pixels, distances)`` of ``num_rays`` observations drawn uniformly."""
        i = torch.randint(len(self), (num_rays,), generator=generator)
        return self.rays[i], self.pixels[i], self.t[i]


class ErrorMap:
    """Where the field is still wrong, image by image (after instant-ngp's error map): every image is cut
    into square tiles, each holding a running mean of the squared colour error of the training rays drawn
    in it. :meth:`draw` picks pixels from tiles in proportion to that error capped at the mean error of
    all rays, so rays leave what the field has already learnt (the white background around an object) and
    spread evenly over the rest. Without the cap, rays crowd on what the field cannot explain (far
    background, reflections): with half the rays from the map colmap_mouse lost 1.0 dB at 300 steps, capped
    it was even (+0.02 dB), while lego_200 gained 0.7 dB (1.0 dB with 0.8 of the rays; figures at equal
    steps: :attr:`~nerfpipe.training.trainer.TrainerConfig.error_sampling` says where it is on by default).
    A tile no ray has visited yet counts the mean (not more: on a capture of 12 MP photos most tiles would
    otherwise be drawn once before any measured error steers the draws).

    The map lives on ``device`` and neither drawing nor updating reads anything back: tiles are drawn by
    inverting the weights' cumulative sum at uniform numbers drawn on the host (with the run's generator,
    uploaded without blocking), and an update folds every tile's sum of errors in at once (no boolean masks:
    issue 13's sync-free step).
    """

    def __init__(self, widths: Tensor, heights: Tensor, offsets: Tensor, tiles: int = 16384, decay: float = 0.5,
                 device="cpu") -> None:
        """``widths``, ``heights``: each image's size; ``offsets``: its first pixel in the flat pixels; ``tiles``:
        about how many tiles in all (square, at least 4 pixels wide); ``decay``: the weight of a step's error
        against what a tile held; ``device``: where the map lives (the pixel indices it draws are there)."""
        self.device = torch.device(device)
        widths, heights, offsets = widths.long().cpu(), heights.long().cpu(), offsets.long().cpu()
        self.tile = max(4, round(math.sqrt(int(offsets[-1]) / tiles)))
        self.decay = decay
        cols = (widths + self.tile - 1) // self.tile
        rows = (heights + self.tile - 1) // self.tile
        tile_offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(cols * rows, 0)])
        cam = torch.repeat_interleave(torch.arange(len(widths)), cols * rows)
        local = torch.arange(int(tile_offsets[-1])) - tile_offsets[cam]
        x0, y0 = (local % cols[cam]) * self.tile, (local // cols[cam]) * self.tile
        w, h = (widths[cam] - x0).clamp_max(self.tile), (heights[cam] - y0).clamp_max(self.tile)  # an image's last tiles may be cut
        self.table = torch.stack([offsets[cam] + y0 * widths[cam] + x0, w, h, widths[cam]], -1).to(self.device)
        """Each tile's first pixel (flat index), width, height and its image's width ``[n, 4]``."""
        area = torch.cumsum(w * h, 0).double()
        self.area_cdf = (area / area[-1]).to(self.device)
        """The share of all pixels up to each tile: uniform pixels are tiles drawn by their area."""
        self.tile_offsets, self.cols = tile_offsets.to(self.device), cols.to(self.device)
        self.error = torch.ones(len(w), device=self.device)
        self.visited = torch.zeros(len(w), dtype=torch.bool, device=self.device)
        self.mean = torch.ones((), device=self.device)
        """Running mean squared error of all rays, what unvisited tiles count."""

    def draw(self, num: int, generator: "torch.Generator | None", uniform: int = 0) -> "tuple[Tensor, Tensor]":
        """``(pixel indices [num], tile indices [num])`` on the map's device: tiles in proportion to their error, uniform
        inside each; the last ``uniform`` of them uniform over all pixels (tiles in proportion to their pixels)."""
        pick, across, down = upload(torch.rand(3, num, generator=generator, dtype=torch.float64), self.device)
        n = num - uniform
        cdf = torch.cumsum(torch.where(self.visited, self.error.minimum(self.mean), self.mean), 0, dtype=torch.float64)
        tiles = torch.cat([torch.searchsorted(cdf, pick[:n] * cdf[-1:], right=True),
                           torch.searchsorted(self.area_cdf, pick[n:], right=True)])
        first, w, h, width = self.table[tiles.clamp_max_(len(cdf) - 1)].unbind(-1)
        col = (across * w).long().minimum(w - 1)  # (a product may round up to w)
        row = (down * h).long().minimum(h - 1)
        return first + row * width + col, tiles

    def tiles_of(self, cam: Tensor, col: Tensor, row: Tensor) -> Tensor:
        """The tile of pixel ``(col, row)`` of image ``cam``."""
        return self.tile_offsets[cam] + (row // self.tile) * self.cols[cam] + col // self.tile

    def update(self, tiles: Tensor, errors: Tensor) -> None:
        """Fold the squared errors ``[n]`` of rays drawn in ``tiles`` ``[n]`` into their tiles' running means
        (a map on the host reads a device's errors back: the sampler keeps the map where its batches are drawn)."""
        errors = errors.detach().float().to(self.device)
        sums = torch.zeros(len(self.error), 2, device=self.device).index_add_(0, tiles, torch.stack([errors, torch.ones_like(errors)], -1))
        total, count = sums.unbind(-1)
        hit = count > 0
        mean = total / count.clamp_min(1)  # a running mean of each tile hit; a first visit sets it
        self.error.copy_(torch.where(hit, torch.where(self.visited, self.error.lerp(mean, self.decay), mean), self.error).clamp_(min=1e-6))
        self.visited.logical_or_(hit)
        self.mean.lerp_(errors.mean(), self.decay)

    def state(self) -> Float[Tensor, "n"]:
        """Everything the map holds, as one float tensor on the host (a checkpoint's, gathered over ranks as bytes)."""
        return torch.cat([self.error, self.visited.float(), self.mean[None]]).cpu()

    def load_state(self, state: Tensor) -> None:
        """Go on from :meth:`state`; a map of another size (other images, another tiling) is a ``ValueError``."""
        n = len(self.error)
        if state.numel() != 2 * n + 1:
            raise ValueError(f"error map of {(state.numel() - 1) // 2} tiles, this run's has {n}")
        state = state.float().reshape(-1).to(self.device)
        self.error.copy_(state[:n]), self.visited.copy_(state[n : 2 * n] > 0), self.mean.copy_(state[-1])


class PixelSampler:
    """Uniform random pixels across every image of a split, optionally a share of them from an :class:`ErrorMap`."""

    def __init__(self, scene: SceneData, split: str = "train", background: str = "black", device="cpu", track_rays: int = 0,
                 max_side: "int | None" = None, error_share: float = 0.0, error_tiles: int = 16384,
                 cache_rays: "bool | None" = None) -> None:
        """``max_side``: the longer side of the images rays are drawn from, at most (larger ones are area-downscaled);
        ``error_share``: the share of the pixel rays drawn from the error map (0: none, all uniform); ``cache_rays``:
        every pixel's ray generated once and kept on the device with the pixels (:meth:`_cache`; None: on CUDA where
        they fit :data:`CACHE_MAX_BYTES` and a quarter of the free memory)."""
        cameras = scene.split_cameras(split).capped(max_side)
        self.cameras = cameras.to(device)
        self._models = cameras.distortion_models()
        """Which distortion models the cameras have, read on the host once (not from the device with every batch's rays)."""
        self.widths = cameras.width.clone()
        """Width of each image, on the host (indexing the device's copy would read it back every step)."""
        self.pixels, self.offsets = load_split_pixels(scene, split, cameras)
        self.num_pixels = int(self.offsets[-1])
        self.background = background
        self.device = torch.device(device)
        has_tracks = scene.points is not None and scene.points.has_tracks
        self.tracks = TrackRays(scene, split, self.pixels, self.offsets, cameras) if track_rays and has_tracks else None
        self.track_rays = track_rays if self.tracks is not None and len(self.tracks) else 0
        """Rays per batch through sparse points (the rest are uniform pixels)."""
        if cache_rays is None:
            cache_rays = self.device.type == "cuda" and _fits(self.num_pixels * (_RAY_FLOATS * 4 + self.pixels.shape[1]), self.device)
        self.cached: "tuple[Tensor, Tensor, Tensor] | None" = self._cache() if cache_rays else None
        """Every pixel's ray ``[P, 7]`` (origin, direction, z scale), the pixels ``[P, C]`` and the offsets on the device,
        or None: rays generated per batch."""
        self.error_share = error_share
        self.errors = ErrorMap(cameras.width, cameras.height, self.offsets, error_tiles,
                               device=self.device if self.cached is not None else "cpu") if error_share > 0 else None
        """The error map, where the batches' pixel indices are drawn: on the device with cached rays, else on the host."""
        self.last_tiles: "Tensor | None" = None
        """The error-map tile of each pixel ray of the latest batch (its first rays), for :meth:`update_errors`."""

    def __len__(self) -> int:
        return self.num_pixels

    def sample(self, num_rays: int, generator: "torch.Generator | None" = None) -> PixelBatch:
        """``num_rays`` rays: uniform pixels, and ``track_rays`` of them through sparse points."""
        k = min(self.track_rays, num_rays // 2)
        batch = self._uniform(num_rays - k, generator)
        if not k:
            return batch
        rays, pixels, t = self.tracks.sample(k, generator)
        bg = background_colors(self.background, k, generator)
        nan = torch.full((num_rays - k,), float("nan"))
        return PixelBatch(
            rays=_cat_rays(batch.rays, rays.to(self.device)),
            rgb=torch.cat([batch.rgb, self._upload(composite_pixels(pixels, bg))]),
            background=torch.cat([batch.background, self._upload(bg)]),
            depth=self._upload(torch.cat([nan, t])),
        )

    def update_errors(self, errors: Tensor) -> None:
        """The squared colour errors of the latest batch's rays (its pixel rays first) into the error map."""
        if self.errors is not None and self.last_tiles is not None:
            self.errors.update(self.last_tiles, errors[: len(self.last_tiles)])

    def _uniform(self, num_rays: int, generator: "torch.Generator | None") -> PixelBatch:
        if self.errors is not None:  # on the map's device: the sampler's with cached rays, else the host
            idx, self.last_tiles = self.errors.draw(num_rays, generator, uniform=num_rays - round(num_rays * self.error_share))
        else:
            idx = torch.randint(len(self), (num_rays,), generator=generator)
        if self.cached is None:
            cam, col, row = self._pixel_coords(idx)
        bg = background_colors(self.background, num_rays, generator)
        if self.cached is not None:  # one upload of the indices, three gathers on the device
            table, pixels, offsets = self.cached
            idx = self._upload(idx)
            ray = table[idx]
            rays = RayBundle(origins=ray[:, :3], directions=ray[:, 3:6], z_scale=ray[:, 6],
                             cam_idx=torch.searchsorted(offsets, idx, right=True) - 1)
            bg = self._upload(bg) if self.background == "random" else background_colors(self.background, num_rays, device=self.device)
            return PixelBatch(rays=rays, rgb=composite_pixels(pixels[idx], bg), background=bg)
        uv = torch.stack([col, row], dim=-1).float() + 0.5
        rgb = composite_pixels(self.pixels[idx], bg)
        rays = generate_rays(self.cameras, self._upload(cam), self._upload(uv), self._models)
        return PixelBatch(rays=rays, rgb=self._upload(rgb), background=self._upload(bg))

    def _pixel_coords(self, idx: Int[Tensor, "n"]) -> "tuple[Tensor, Tensor, Tensor]":
        """The image, column and row of flat pixel indices (on the host)."""
        cam = torch.searchsorted(self.offsets, idx, right=True) - 1
        local = idx - self.offsets[cam]
        width = self.widths[cam]
        return cam, local % width, local // width

    def _cache(self, chunk: int = 1 << 18) -> "tuple[Tensor, Tensor, Tensor]":
        """Every pixel's ray as one ``[P, 7]`` table on the device (what :meth:`_uniform` would generate for it), the
        pixels and the offsets there too: a batch is then one upload of its pixel indices and three gathers instead of
        the rays generated from its cameras (on CUDA ~40 launches and four uploads a step, the sampler's 1.2 ms of a
        3.7 ms host step; session 34's profile on an H200)."""
        table = torch.empty(self.num_pixels, _RAY_FLOATS, device=self.device)
        for start in range(0, self.num_pixels, chunk):
            end = min(start + chunk, self.num_pixels)
            cam, col, row = self._pixel_coords(torch.arange(start, end))
            uv = torch.stack([col, row], dim=-1).float() + 0.5
            rays = generate_rays(self.cameras, cam.to(self.device), uv.to(self.device), self._models)
            table[start:end] = torch.cat([rays.origins, rays.directions, rays.z_scale[:, None]], -1)
        return table, self.pixels.to(self.device), self.offsets.to(self.device)

    def _upload(self, t: Tensor) -> Tensor:
        """A batch tensor drawn on the host, on the sampler's device (:func:`upload`)."""
        return upload(t, self.device)


_RAY_FLOATS = 7
"""Floats of a cached ray: origin, direction, z scale."""

CACHE_MAX_BYTES = 4 << 30
"""The most device memory :class:`PixelSampler` caches every pixel's ray in (by default, on CUDA)."""


def upload(t: Tensor, device: torch.device) -> Tensor:
    """``t`` on ``device``: a tensor drawn on the host goes to CUDA through pinned memory without blocking (a copy
    from pageable memory makes the host wait for the stream, once per tensor and step); one already there is
    returned as it is. An expanded tensor (one background colour for every ray) is made contiguous first:
    ``pin_memory`` refuses tensors whose elements share memory."""
    if t.device == device or device.type != "cuda" or t.device.type != "cpu":
        return t.to(device)
    return t.contiguous().pin_memory().to(device, non_blocking=True)


def _fits(nbytes: int, device: torch.device) -> bool:
    """Whether ``nbytes`` fit :data:`CACHE_MAX_BYTES` and a quarter of ``device``'s free memory."""
    return nbytes <= CACHE_MAX_BYTES and nbytes <= torch.cuda.mem_get_info(device)[0] // 4


def _cat_rays(a: RayBundle, b: RayBundle) -> RayBundle:
    return RayBundle(
        origins=torch.cat([a.origins, b.origins]), directions=torch.cat([a.directions, b.directions]),
        cam_idx=torch.cat([a.cam_idx, b.cam_idx]), z_scale=torch.cat([a.z_scale, b.z_scale]),
    )
