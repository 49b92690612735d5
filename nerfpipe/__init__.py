"""nerfpipe: posed photographs -> neural radiance field -> novel views, depth and meshes.

Layers (lower never imports upper):

1. ``nerfpipe.functional``: pure tensor functions (distortion, rays, sampling, volume rendering);
2. containers and modules: :class:`Cameras`, :class:`RayBundle`, :class:`SceneData`, fields;
3. orchestration: ``nerfpipe.commands``, stages in ``plugins/``, the CLI.
"""

# pycolmap's wheel exports its own zlib symbols; when it is imported before Python's zlib, later
# PNG writes abort the process. Loading zlib first makes the order safe for every nerfpipe user.
import zlib  # noqa: F401  (import-order guard, see above)

# Before torch loads OpenMP: sleeping OpenMP waits when the machine is busy, and large freed blocks kept
# by glibc's allocator (both measured and explained in nerfpipe/runtime.py).
from nerfpipe import runtime  # noqa: E402

runtime.apply()

from nerfpipe.cameras import Cameras, invert_rigid, opengl_to_opencv
from nerfpipe.errors import NerfpipeError
from nerfpipe.functional.distortion import Distortion
from nerfpipe.functional.volrend import volrend
from nerfpipe.rays import RayBundle, camera_rays, generate_rays, pixel_centers
from nerfpipe.scene import ImageSet, Points3D, SceneData, Similarity

__version__ = "0.1.0"

__all__ = [
    "Cameras",
    "Distortion",
    "ImageSet",
    "NerfpipeError",
    "Points3D",
    "RayBundle",
    "SceneData",
    "Similarity",
    "camera_rays",
    "generate_rays",
    "invert_rigid",
    "opengl_to_opencv",
    "pixel_centers",
    "volrend",
]
