"""How much of a photo collection's held-out error is its sky: a bound on what any sky model could gain.

Reads the strips of ``nerfpipe eval RUN --pictures`` (photograph | render | error map; for photo collections the
render takes the appearance fitted on the view's left half, and the right half is scored) and reports per view the
right half's PSNR as rendered, with its sky pixels replaced by the photograph's own (a perfect sky: the bound), and by
the photograph's sky blurred (a smooth sky of the right colours, without the clouds' detail).

The sky is found in the photograph (:func:`sky_mask`): blue or bright, unsaturated pixels connected to the top edge.
On white stone under a blue sky (the Sacre Coeur) it takes some of the facade too, so the perfect-sky figure is an
upper bound. The strips are 8-bit PNGs: PSNRs agree with ``nerfpipe eval``'s to about 0.01 dB.

Run: ``nerfpipe eval RUN --max-size 400 --supersample 1 --pictures`` then
``python -m benchmarks.sky_bound RUN/eval`` (``RUN/train/eval`` for a ``nerfpipe run`` folder). Prints one JSON line
per view and one with the means over views (the held-out figure averages views' PSNRs).
"""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from nerfpipe.functional.metrics import psnr_from_mse
from nerfpipe.util.typing import Bool, Float


@dataclass
class SkyBoundConfig:
    pictures: tyro.conf.Positional[Path]
    """The folder of ``nerfpipe eval --pictures`` (``view_NNNN.png``)."""
    blur: float = 15.0
    """Standard deviation, in pixels, of the blur of the smooth-sky figure."""


def sky_mask(photo: Float[np.ndarray, "H W 3"], blue_margin: float = 0.05, bright: float = 0.75) -> Bool[np.ndarray, "H W"]:
    """Pixels of ``photo`` (values in [0, 1]) that are blue (blue over red by ``blue_margin``, blue above 0.4) or
    bright and unsaturated (every channel above ``bright``), and connected to the top edge through such pixels."""
    from scipy.ndimage import label

    r, g, b = photo[..., 0], photo[..., 1], photo[..., 2]
    candidate = ((b > r + blue_margin) & (b > 0.4)) | ((r > bright) & (g > bright) & (b > bright))
    labels, _ = label(candidate)
    top = np.unique(labels[0][labels[0] > 0])
    return np.isin(labels, top)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return psnr_from_mse(float(((a - b) ** 2).mean()))


def _blurred_within(image: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """``image`` blurred over the pixels of ``mask`` only (normalised convolution)."""
    from scipy.ndimage import gaussian_filter

    weight = np.maximum(gaussian_filter(mask.astype(np.float64), sigma), 1e-6)
    return np.stack([gaussian_filter(np.where(mask, image[..., c], 0.0), sigma) / weight for c in range(3)], axis=-1)


def view_bound(strip: Float[np.ndarray, "H 3W 3"], blur: float = 15.0) -> dict:
    """The figures of one strip (photograph | render | error map), scored on the right half of each."""
    w = strip.shape[1] // 3
    photo, render = strip[:, :w], strip[:, w : 2 * w]
    sky = sky_mask(photo)
    right = slice(w // 2, w)
    perfect, smooth = render.copy(), render.copy()
    perfect[sky] = photo[sky]
    smooth[sky] = _blurred_within(photo, sky, blur)[sky]
    err = ((render - photo) ** 2).sum(-1)[:, right]
    return {
        "psnr": _psnr(render[:, right], photo[:, right]),
        "psnr_perfect_sky": _psnr(perfect[:, right], photo[:, right]),
        "psnr_smooth_sky": _psnr(smooth[:, right], photo[:, right]),
        "sky_share": float(sky[:, right].mean()),
        "sky_error_share": float(err[sky[:, right]].sum() / max(float(err.sum()), 1e-12)),
    }


def main(cfg: SkyBoundConfig) -> dict:
    import imageio.v3 as iio

    files = sorted(cfg.pictures.glob("view_*.png"))
    if not files:
        raise SystemExit(f"{cfg.pictures}: no view_*.png (run nerfpipe eval RUN --pictures first)")
    rows = []
    for f in files:
        strip = iio.imread(f)[..., :3].astype(np.float64) / 255.0
        row = {"view": f.stem, **view_bound(strip, cfg.blur)}
        rows.append(row)
        print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    keys = ("psnr", "psnr_perfect_sky", "psnr_smooth_sky")
    summary = {"views": len(rows), **{k: sum(r[k] for r in rows) / len(rows) for k in keys}}
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in summary.items()}), flush=True)
    return {"views": rows, "summary": summary}


if __name__ == "__main__":
    main(tyro.cli(SkyBoundConfig))
