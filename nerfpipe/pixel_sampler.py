"""Training rays: random pixels drawn uniformly across all images of a split.

Images are loaded once and kept as one uint8 tensor of pixels ``[P, C]`` (images may differ in
size); a batch picks pixel indices, finds their camera through per-image offsets and generates
rays with :func:`nerfpipe.rays.generate_rays`. RGBA pixels are composited on the batch's
background colour (random per ray in training when the mode is ``random``).
"""

from dataclasses import dataclass

import numpy as np
import torch

from nerfpipe.rays import RayBundle, generate_rays
from nerfpipe.scene import SceneData
from nerfpipe.typing import Float, Tensor, UInt8

BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}


def background_colors(mode: str, n: int, generator: "torch.Generator | None" = None, device=None) -> Float[Tensor, "n 3"]:
    """``n`` background colours: a named constant (``black``/``white``) or ``random`` per ray."""
    if mode == "random":
        return torch.rand((n, 3), generator=generator).to(device)
    return torch.tensor(BACKGROUNDS[mode], device=device).expand(n, 3)


def composite_pixels(pixels: UInt8[Tensor, "*bs C"], background: Float[Tensor, "*bg 3"]) -> Float[Tensor, "*bs 3"]:
    """uint8 RGB(A) ``[*bs, C]`` -> float RGB in [0, 1], alpha composited on ``background``."""
    rgb = pixels[..., :3].float() / 255.0
    if pixels.shape[-1] == 4:
        a = pixels[..., 3:].float() / 255.0
        rgb = rgb * a + background.to(rgb) * (1.0 - a)
    return rgb


def load_split_pixels(scene: SceneData, split: str) -> "tuple[Tensor, Tensor]":
    """All pixels of a split as uint8 ``[P, C]`` and the offsets ``[n+1]`` of each image."""
    chans = 4 if scene.has_alpha else 3
    flat, offsets = [], [0]
    for i in scene.splits[split]:
        img = np.asarray(scene.images.load(int(i)))
        if img.shape[-1] < chans:
            img = np.concatenate([img, np.full((*img.shape[:2], chans - img.shape[-1]), 255, np.uint8)], axis=-1)
        flat.append(torch.from_numpy(np.ascontiguousarray(img[..., :chans])).reshape(-1, chans))
        offsets.append(offsets[-1] + flat[-1].shape[0])
    return torch.cat(flat), torch.tensor(offsets, dtype=torch.long)


@dataclass
class PixelBatch:
    """Rays with their target colours and the background the targets were composited on."""

    rays: RayBundle
    rgb: Float[Tensor, "num_rays 3"]
    background: Float[Tensor, "num_rays 3"]


class PixelSampler:
    """Uniform random pixels across every image of a split."""

    def __init__(self, scene: SceneData, split: str = "train", background: str = "black", device="cpu") -> None:
        self.cameras = scene.split_cameras(split).to(device)
        self.pixels, self.offsets = load_split_pixels(scene, split)
        self.background = background
        self.device = torch.device(device)

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def sample(self, num_rays: int, generator: "torch.Generator | None" = None) -> PixelBatch:
        idx = torch.randint(len(self), (num_rays,), generator=generator)
        cam = torch.searchsorted(self.offsets, idx, right=True) - 1
        local = idx - self.offsets[cam]
        width = self.cameras.width.cpu()[cam]
        uv = torch.stack([local % width, local // width], dim=-1).float() + 0.5
        bg = background_colors(self.background, num_rays, generator)
        rgb = composite_pixels(self.pixels[idx], bg)
        rays = generate_rays(self.cameras, cam.to(self.device), uv.to(self.device))
        return PixelBatch(rays=rays, rgb=rgb.to(self.device), background=bg.to(self.device))
