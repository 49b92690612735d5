"""Packaging: the wheel installs one import name, ``nerfpipe``, and nothing generic (``plugins``,
``data_adapters``, ``benchmarks``) that another distribution's package of the same name could hide or be hidden by."""

import importlib.metadata
import os
import shutil
import subprocess
import sys
from pathlib import Path

from nerfpipe.util.registry import ADAPTER_GROUP, MODEL_GROUP, STAGE_GROUP

REPO = Path(__file__).resolve().parents[1]
BUILTIN_STAGES = {"sfm", "load", "check", "export", "train", "render", "mesh", "report"}


def test_wheel_installs_only_the_nerfpipe_package(tmp_path):
    """The wheel's metadata as setuptools builds it (``top_level.txt``, file list, entry points)."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    shutil.copytree(REPO / "nerfpipe", src / "nerfpipe", ignore=shutil.ignore_patterns("__pycache__"))
    for folder in ("benchmarks", "plugins"):  # present in the checkout, must stay out of the wheel
        shutil.copytree(REPO / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    code = f"from setuptools import build_meta; print(build_meta.prepare_metadata_for_build_wheel({str(tmp_path)!r}))"
    done = subprocess.run([sys.executable, "-c", code], cwd=src, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    dist_info = tmp_path / done.stdout.strip().splitlines()[-1]
    assert (dist_info / "top_level.txt").read_text().split() == ["nerfpipe"]

    sources = (tmp_path / "nerfpipe.egg-info" / "SOURCES.txt").read_text().split()
    assert "nerfpipe/plugins/train.py" in sources and "nerfpipe/data_adapters/npz.py" in sources
    outside = [s for s in sources if s.endswith(".py") and not s.startswith("nerfpipe/")]
    assert outside == []

    entry_points = (dist_info / "entry_points.txt").read_text()
    targets = [line.split("=", 1)[1].strip() for line in entry_points.splitlines() if "=" in line]
    assert len(targets) >= 12 and all(t.startswith("nerfpipe.") for t in targets), targets

    core = [line.split(":", 1)[1].strip() for line in (dist_info / "METADATA").read_text().splitlines()
            if line.startswith("Requires-Dist:") and "extra ==" not in line]  # fmt: skip
    assert _missing_from_core(core) == []


def _missing_from_core(core: "list[str]") -> "list[str]":
    """The optional modules a default ``nerfpipe train`` (and the MP4 of ``nerfpipe render``) imports that no
    core requirement installs: a core install must be able to train."""
    from nerfpipe.outputs.artifacts import SEQUENCE_DEPENDENCIES
    from nerfpipe.training import evaluation
    from nerfpipe.training.trainer import TrainerConfig

    provides = {"imageio_ffmpeg": "imageio[ffmpeg]"}  # module -> the requirement that installs it
    needed = {module for module, _ in evaluation.dependencies(TrainerConfig()) + SEQUENCE_DEPENDENCIES}
    names = {req.split(">")[0].split("=")[0].split("<")[0].strip().lower().replace(" ", "") for req in core}
    return sorted(m for m in needed if provides.get(m, m).lower() not in names)


def test_a_core_install_without_kornia_would_be_caught():
    assert _missing_from_core(["torch>=2.4", "imageio[ffmpeg]>=2.34", "matplotlib>=3.8"]) == ["kornia"]
    assert _missing_from_core(["torch>=2.4", "imageio>=2.34", "kornia>=0.8", "matplotlib>=3.8"]) == ["imageio_ffmpeg"]


def test_installed_entry_points_are_namespaced():
    for group in (STAGE_GROUP, ADAPTER_GROUP, MODEL_GROUP):
        for ep in importlib.metadata.entry_points(group=group):
            if ep.name in BUILTIN_STAGES | {"npz", "transforms", "colmap", "fast", "vanilla"}:
                assert ep.value.startswith("nerfpipe."), f"{group} {ep.name} = {ep.value}"


def test_foreign_generic_packages_cannot_hide_the_builtin_stages(tmp_path):
    """Another distribution's ``plugins`` (or ``data_adapters``, ``benchmarks``) first on sys.path."""
    for name in ("plugins", "data_adapters", "benchmarks"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text("FOREIGN = True\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    code = (
        "import plugins, warnings; assert plugins.FOREIGN\n"
        "warnings.simplefilter('error')\n"
        "from nerfpipe.pipeline.stages import stages\n"
        "from nerfpipe.data_adapters import adapters\n"
        "print(' '.join(sorted(stages())), '|', ' '.join(sorted(adapters())))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    found_stages, found_adapters = (set(part.split()) for part in done.stdout.split("|"))
    assert BUILTIN_STAGES <= found_stages
    assert {"npz", "transforms", "colmap"} <= found_adapters
