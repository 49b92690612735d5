"""Image-quality scores against slow references."""

import math

import pytest
import torch


def test_psnr_matches_the_reference_and_floors_perfect_images():
    from nerfpipe.functional.metrics import MIN_MSE, psnr_from_mse
    from reference import psnr

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(8, 8, 3, generator=g), torch.rand(8, 8, 3, generator=g)
    assert psnr_from_mse(float(torch.mean((a - b) ** 2))) == pytest.approx(psnr(a, b), rel=1e-12)
    assert psnr_from_mse(0.0) == psnr_from_mse(MIN_MSE) == pytest.approx(-10 * math.log10(MIN_MSE))
