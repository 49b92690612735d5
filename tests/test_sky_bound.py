"""The sky bound of photo collections' held-out views (``benchmarks/sky_bound.py``)."""

import numpy as np

from benchmarks.sky_bound import sky_mask, view_bound


def _photo() -> np.ndarray:
    photo = np.full((40, 60, 3), 0.3)
    photo[:15] = (0.3, 0.5, 0.9)  # blue sky above
    photo[30:35, 10:20] = (0.2, 0.3, 0.8)  # a blue object below the grey building: not sky
    return photo


def test_sky_is_blue_or_bright_and_connected_to_the_top():
    mask = sky_mask(_photo())
    assert mask[:15].all() and not mask[15:].any()


def test_a_perfect_sky_bounds_the_figure_and_a_right_render_scores_higher():
    photo = _photo()
    render = photo.copy()
    render[:15] += 0.1  # the sky wrong, the rest right
    render[20:25, 30:] -= 0.05  # and part of the right half's building
    strip = np.concatenate([photo, render, np.zeros_like(photo)], axis=1)
    row = view_bound(strip)
    expected = -10 * np.log10(((render[:, 30:] - photo[:, 30:]) ** 2).mean())
    assert abs(row["psnr"] - expected) < 1e-9
    assert row["psnr_perfect_sky"] > row["psnr_smooth_sky"] - 1e-9 and row["psnr_perfect_sky"] > row["psnr"] + 3
    assert abs(row["sky_share"] - 15 / 40) < 1e-9 and 0 < row["sky_error_share"] < 1
