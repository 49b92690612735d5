"""nerfpipe: posed photographs -> neural radiance field -> novel views, depth and meshes.

Layers (lower never imports upper):

1. ``nerfpipe.functional``: pure tensor functions (distortion, rays, sampling, volume rendering);
2. containers and modules: :class:`Cameras`, :class:`RayBundle`, :class:`SceneData`, fields;
3. orchestration: ``nerfpipe.commands``, stages in ``nerfpipe.plugins``, the CLI.

Importing nerfpipe changes nothing in the host process. The process settings the CLI makes
(OpenMP waiting, glibc's allocator: :mod:`nerfpipe.runtime`) are one explicit call,
``nerfpipe.runtime.apply()``, made before torch is imported. So that the CLI can make it, this
package imports torch lazily: the names below load their module on first access (PEP 562).
"""

# pycolmap's wheel exports its own zlib symbols; when it is imported before Python's zlib, later
# PNG writes abort the process. Loading zlib first makes the order safe for every nerfpipe user.
import zlib  # noqa: F401  (import-order guard, see above)

__version__ = "0.1.0"

_EXPORTS = {
    "Cameras": "nerfpipe.cameras",
    "Distortion": "nerfpipe.functional.distortion",
    "ImageSet": "nerfpipe.scene",
    "NerfpipeError": "nerfpipe.errors",
    "Points3D": "nerfpipe.scene",
    "RayBundle": "nerfpipe.rays",
    "SceneData": "nerfpipe.scene",
    "Similarity": "nerfpipe.scene",
    "camera_rays": "nerfpipe.rays",
    "generate_rays": "nerfpipe.rays",
    "invert_rigid": "nerfpipe.cameras",
    "opengl_to_opencv": "nerfpipe.cameras",
    "pixel_centers": "nerfpipe.rays",
    "volrend": "nerfpipe.functional.volrend",
}
"""Public name -> the module that defines it."""

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> object:
    """Load a public name's module on first access (then cache the name in this module)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'nerfpipe' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def __dir__() -> "list[str]":
    return sorted(set(globals()) | set(__all__))
