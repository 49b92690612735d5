"""Background colours behind a scene's pixels: the named constants, a random colour per ray, RGBA
pixels composited on them, and the rule that picks the training and evaluation backgrounds.

One module for training rays (:mod:`nerfpipe.training.pixel_sampler`), evaluation and every render
of a trained model (:mod:`nerfpipe.outputs.novel_views`), so they all composite the same way.
"""

import torch

from nerfpipe.util.typing import Float, Tensor, UInt8

BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}


def background_colors(mode: str, n: int, generator: "torch.Generator | None" = None, device=None) -> Float[Tensor, "n 3"]:
    """``n`` background colours: a named constant (``black``/``white``) or ``random`` per ray."""
    if mode == "random":
        return torch.rand((n, 3), generator=generator).to(device)
    r, g, b = BACKGROUNDS[mode]
    if r == g == b:  # grey: no tensor built from a list (a blocking upload on CUDA)
        return torch.full((1, 3), r, device=device).expand(n, 3)
    return torch.tensor(BACKGROUNDS[mode], device=device).expand(n, 3)


def composite_pixels(pixels: UInt8[Tensor, "*bs C"], background: Float[Tensor, "*bg 3"]) -> Float[Tensor, "*bs 3"]:
    """uint8 RGB(A) ``[*bs, C]`` -> float RGB in [0, 1], alpha composited on ``background``."""
    rgb = pixels[..., :3].float() / 255.0
    if pixels.shape[-1] == 4:
        a = pixels[..., 3:].float() / 255.0
        rgb = rgb * a + background.to(rgb) * (1.0 - a)
    return rgb


def backgrounds(mode: str, has_alpha: bool) -> "tuple[str, str]":
    """(training, evaluation) background modes for a config value."""
    if mode == "auto":
        return ("random", "white") if has_alpha else ("black", "black")
    if mode == "random":
        return "random", "white"
    return mode, mode
