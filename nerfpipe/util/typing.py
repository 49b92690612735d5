"""Axis vocabulary for tensor shapes in type hints (STYLE habit 2).

Every shape annotation in nerfpipe uses these axis names:

* ``*bs``          any leading batch shape (cameras, rays, pixels, ...)
* ``num_cams``     number of cameras in a :class:`~nerfpipe.data.cameras.Cameras` batch
* ``num_rays``     number of rays in a flat batch
* ``num_samples``  samples along each ray
* ``num_points``   points in a flat batch (3D points, pixels)
* ``num_obs``      track observations of sparse points (one row per point seen by one camera)
* ``H W``          image height and width in pixels
* ``C``            channels (3 for RGB, 4 for RGBA)

Shapes are checked at runtime in the test suite by
``pytest --jaxtyping-packages=nerfpipe,beartype.beartype``.
"""

from jaxtyping import Bool, Float, Int, UInt8, Shaped
from torch import Tensor

__all__ = ["Bool", "Float", "Int", "UInt8", "Shaped", "Tensor"]
