"""Image-quality scores as pure functions (the one PSNR of nerfpipe: training curves, validation, the 2D warm-up)."""

import math

MIN_MSE = 1e-12
"""Mean squared errors are floored here: a perfect reconstruction scores 120 dB, a finite number JSON can hold."""


def psnr_from_mse(mse: float) -> float:
    """Peak signal-to-noise ratio in dB of images with values in [0, 1], from their mean squared error.

    Example:
        >>> psnr_from_mse(0.01), psnr_from_mse(0.0)
        (20.0, 120.0)
    """
    return -10.0 * math.log10(max(float(mse), MIN_MSE))
