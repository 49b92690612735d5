"""Background colours behind a scene's pixels: the named constants, a random colour per ray, RGBA
pixels composited on them, and the rule that picks the training and evaluation backgrounds.

One module for training rays (:mod:`nerfpipe.training.pixel_sampler`), evaluation and every render
of a trained model (:mod:`nerfpipe.outputs.novel_views`), so they all composite the same way.
"""

import torch

from nerfpipe.util.typing import Float, Tensor, UInt8

BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "grey": (0.5, 0.5, 0.5)}
"""The named constant backgrounds."""


def background_colors(mode: str, n: int, generator: "torch.Generator | None" = None, device=None) -> Float[Tensor, "n 3"]:
    """``n`` background colours: a named constant (``black``/``white``/``grey``) or ``random`` per ray."""
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


def backgrounds(mode: str, has_alpha: bool, surroundings: bool = False) -> "tuple[str, str]":
    """(training, evaluation) background modes for a config value; ``auto``: random in training and white at
    evaluation for RGBA data; grey for photographs that show the object's surroundings
    (``SceneData.shows_surroundings``), black otherwise.

    Grey for real captures: what the learned layers (the colour behind the box and the field there) leave
    transparent is this colour, in training and in every render. A held-out view sees some of the surroundings that
    no training photograph shows (photos_sacre_coeur's steps and balustrade in its two held-out views): black there
    is the worst guess for a photograph's colours, mid-grey about the mean one."""
    if mode == "auto":
        return ("random", "white") if has_alpha else ("grey", "grey") if surroundings else ("black", "black")
    if mode == "random":
        return "random", "white"
    return mode, mode
