"""Depth and error as colour, with the mapping stated: turbo from near (blue) to far (red) over a fixed range.

One range serves every frame of a sequence (so colours are comparable across frames); pixels whose
accumulated opacity is below ``min_acc`` (background) are drawn black. Errors of a render against its
photograph are drawn on one fixed scale (:data:`ERROR_MAX`), so maps compare across views and runs.
"""

import numpy as np
import torch

from nerfpipe.util.errors import require
from nerfpipe.util.typing import Float, Tensor


def depth_range(depths: "list[Tensor]", accs: "list[Tensor]", min_acc: float = 0.5, q: float = 0.01) -> "tuple[float, float]":
    """Robust ``[lo, hi]`` of surface depths (the q and 1-q quantiles over foreground pixels)."""
    vals = torch.cat([(d / a.clamp(min=1e-6))[a >= min_acc].reshape(-1) for d, a in zip(depths, accs)])
    if vals.numel() == 0:
        return 0.0, 1.0
    if vals.numel() > 1_000_000:  # a fixed subset: the same range every call, torch's global stream untouched
        vals = vals[torch.randperm(vals.numel(), generator=torch.Generator().manual_seed(0))[:1_000_000].to(vals.device)]
    lo, hi = torch.quantile(vals.float(), torch.tensor([q, 1 - q])).tolist()
    return lo, max(hi, lo + 1e-6)


def colorize_depth(depth: Float[Tensor, "H W"], acc: Float[Tensor, "H W"], lo: float, hi: float, min_acc: float = 0.5) -> np.ndarray:
    """uint8 ``[H, W, 3]``: turbo colour of ``(depth/acc - lo) / (hi - lo)``; background black."""
    surface = (depth / acc.clamp(min=1e-6)).cpu().numpy()
    rgb = _turbo(np.clip((surface - lo) / (hi - lo), 0.0, 1.0))
    rgb[acc.cpu().numpy() < min_acc] = 0.0
    return (rgb * 255 + 0.5).astype(np.uint8)


def _turbo(t: np.ndarray) -> np.ndarray:
    """Turbo colours (float RGB in [0, 1], ``[*t.shape, 3]``) of ``t`` in [0, 1]."""
    return require("matplotlib", "plot").colormaps["turbo"](t)[..., :3]


def mapping_text(lo: float, hi: float, min_acc: float = 0.5) -> str:
    return f"turbo colormap of surface depth (depth/acc) from {lo:.3f} (blue) to {hi:.3f} (red) world units; acc < {min_acc} black"


ERROR_MAX = 0.25
"""Root mean square error over a pixel's channels (colours in [0, 1]) drawn red in :func:`error_strip`; 0 is blue."""


def pixel_error(pred: Float[Tensor, "H W 3"], gt: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W"]:
    """Root mean square over the channels of ``pred - gt``: the mean of its square over the pixels is the image's MSE."""
    return ((pred.float() - gt.float().to(pred.device)) ** 2).mean(dim=-1).sqrt()


def error_strip(pred: Float[Tensor, "H W 3"], gt: Float[Tensor, "H W 3"]) -> np.ndarray:
    """uint8 ``[H, 3 W, 3]``: the photograph, the render and the turbo map of :func:`pixel_error` from 0 to
    :data:`ERROR_MAX` (clipped), side by side."""
    heat = _turbo((pixel_error(pred, gt) / ERROR_MAX).clamp(0.0, 1.0).cpu().numpy())
    row = np.concatenate([gt.float().cpu().clamp(0, 1).numpy(), pred.float().cpu().clamp(0, 1).numpy(), heat], axis=1)
    return (row * 255 + 0.5).astype(np.uint8)


def error_text() -> str:
    return f"photograph | render | turbo colormap of the per-pixel RMS colour error from 0 (blue) to {ERROR_MAX} (red)"


def stack_rows(rows: "list[np.ndarray]") -> np.ndarray:
    """uint8 images ``[h_i, w_i, 3]`` one under another, each padded with black on the right to the widest."""
    width = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows], axis=0)
