"""A neural field of one 2D image: pixel coordinate -> RGB (the warm-up of the NeRF course)."""

from nerfpipe.image_field.field import ImageField, ImageFieldConfig
from nerfpipe.image_field.presets import PRESETS, Fit2dConfig, preset
from nerfpipe.image_field.train import FitResult, TrainConfig, fit_image, pixel_grid, psnr_from_mse

__all__ = [
    "PRESETS", "Fit2dConfig", "FitResult", "ImageField", "ImageFieldConfig", "TrainConfig",
    "fit_image", "pixel_grid", "preset", "psnr_from_mse",
]
