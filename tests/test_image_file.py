"""The one image reader hands out arrays torch can take without a copy or a warning."""

import warnings

import numpy as np
import torch

from nerfpipe.data.image_file import read_image_uint8


def test_decoded_images_are_writable(tmp_path):
    import imageio.v3 as iio

    path = tmp_path / "a.png"
    iio.imwrite(path, np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3))
    img = read_image_uint8(path)
    assert img.flags.writeable and img.dtype == np.uint8 and img.shape == (4, 5, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # torch warns on read-only arrays
        assert int(torch.from_numpy(img).sum()) == int(np.arange(60).sum())
