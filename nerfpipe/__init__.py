"""nerfpipe: posed photographs -> neural radiance field -> novel views, depth and meshes.

Layers (lower never imports upper):

1. ``nerfpipe.functional``: pure tensor functions (distortion, rays, sampling, volume rendering);
2. containers and modules: :class:`Cameras`, :class:`RayBundle`, :class:`SceneData`, fields;
3. orchestration: ``nerfpipe.commands``, stages in ``plugins/``, the CLI.
"""

# pycolmap's wheel exports its own zlib symbols; when it is imported before Python's zlib, later
# PNG writes abort the process. Loading zlib first makes the order safe for every nerfpipe user.
import os
import zlib  # noqa: F401  (import-order guard, see above)

# OpenMP threads that spin while waiting (GNU OpenMP's default) make torch 5-20x slower on a machine
# whose cores are shared with other processes (measured: a 4096-ray training step on 2 threads at load
# 4.5 took 4.7 s spinning, 0.21 s passive). Sleeping waits cost little on an idle machine. Only takes
# effect when nerfpipe is imported before torch starts its thread pool; an explicit setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from nerfpipe.malloc import keep_freed_memory  # noqa: E402

keep_freed_memory()  # large per-step tensors reuse freed memory instead of new pages (see nerfpipe.malloc)

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
