"""nerfpipe: posed photographs -> neural radiance field -> novel views, depth and meshes.

The subpackages are the layers, lowest first; a lower one never imports a higher one
(``tests/test_layers.py``):

1. ``nerfpipe.util``: errors, atomic writes, path checks, configs as dicts, plugin discovery, devices;
2. ``nerfpipe.functional``: pure tensor functions (distortion, sampling, volume rendering);
3. ``nerfpipe.data``: containers and geometry (:class:`Cameras`, :class:`RayBundle`, :class:`SceneData`);
4. modules: ``encoders``, ``fields``, ``estimators``, ``models`` (and ``data_adapters``, ``image_field``);
5. ``nerfpipe.outputs`` (renders, videos, figures) and ``nerfpipe.mesh``;
6. ``nerfpipe.training``: the trainer, evaluation, checkpoints, the run folder;
7. ``nerfpipe.pipeline`` (stages, :class:`Pipeline`, the report) and ``nerfpipe.viewer``;
8. ``nerfpipe.plugins`` (the built-in stages), ``nerfpipe.commands`` and the CLI.

Importing nerfpipe changes nothing in the host process. The process settings the CLI makes
(OpenMP waiting, glibc's allocator: :mod:`nerfpipe.util.runtime`) are one explicit call,
``nerfpipe.util.runtime.apply()``, made before torch is imported. So that the CLI can make it, this
package imports torch lazily: the names below load their module on first access (PEP 562).
"""

# pycolmap's wheel exports its own zlib symbols; when it is imported before Python's zlib, later
# PNG writes abort the process. Loading zlib first makes the order safe for every nerfpipe user.
import zlib  # noqa: F401  (import-order guard, see above)

__version__ = "0.1.0"

_EXPORTS = {
    "Cameras": "nerfpipe.data.cameras",
    "Distortion": "nerfpipe.functional.distortion",
    "ImageSet": "nerfpipe.data.scene",
    "NerfpipeError": "nerfpipe.util.errors",
    "Pipeline": "nerfpipe.pipeline.stages",
    "Points3D": "nerfpipe.data.scene",
    "RayBundle": "nerfpipe.data.rays",
    "SceneData": "nerfpipe.data.scene",
    "Similarity": "nerfpipe.data.scene",
    "Trainer": "nerfpipe.training.trainer",
    "TrainerConfig": "nerfpipe.training.trainer",
    "camera_rays": "nerfpipe.data.rays",
    "generate_rays": "nerfpipe.data.rays",
    "invert_rigid": "nerfpipe.data.cameras",
    "load_run": "nerfpipe.training.runs",
    "opengl_to_opencv": "nerfpipe.data.cameras",
    "pixel_centers": "nerfpipe.data.rays",
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
