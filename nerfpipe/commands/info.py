"""``nerfpipe info``: summarise a dataset as nerfpipe reads it (format, cameras, bounds)."""

from collections import Counter
from typing import Annotated

import tyro

from nerfpipe.data.scene import SPLITS, SceneData

DatasetPath = Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="PATH")]
"""A dataset file or folder given as the positional argument of a command."""


def _range(values) -> "list[float]":
    return [float(values.min()), float(values.max())] if len(values) else []


def summarize(scene: SceneData) -> dict:
    """A JSON-ready summary of a scene."""
    cams = scene.cameras
    sizes = Counter(f"{int(w)}x{int(h)}" for w, h in zip(cams.width.tolist(), cams.height.tolist()))
    models = scene.camera_models or ["unknown"] * len(cams)
    return {
        "path": str(scene.source),
        "format": scene.format,
        "num_cameras": len(cams),
        "splits": {name: len(scene.splits[name]) for name in SPLITS},
        "image_sizes": dict(sizes.most_common()),
        "intrinsics": {k: _range(getattr(cams, k)) for k in ("fx", "fy", "cx", "cy")},
        "camera_models": dict(Counter(models).most_common()),
        "near": float(scene.near),
        "far": float(scene.far),
        "aabb": scene.aabb.tolist(),
        "normalization_scale": float(scene.world_from_input.scale),
        "num_sparse_points": 0 if scene.points is None else len(scene.points.xyz),
        "has_alpha": scene.has_alpha,
    }


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}: {_fmt(v)}" for k, v in value.items())
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def print_table(title: str, rows: dict) -> None:
    """Print ``rows`` as a two-column rich table (shared by ``info`` and ``check``)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, show_header=False)
    table.add_column(style="bold")
    table.add_column()
    for key, value in rows.items():
        table.add_row(key, _fmt(value))
    Console().print(table)


def info(path: DatasetPath, json: bool = False) -> int:
    """Summarise a dataset: format, cameras per split, image sizes, intrinsics, bounds.

    Args:
        path: Dataset file or folder (any format nerfpipe reads).
        json: Print the summary as JSON only.
    """
    import json as _json

    from nerfpipe import data_adapters

    summary = summarize(data_adapters.load(path))
    if json:
        print(_json.dumps(summary, indent=2))
    else:
        print_table(f"nerfpipe info: {path}", summary)
    return 0
