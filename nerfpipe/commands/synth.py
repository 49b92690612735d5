"""``nerfpipe synth``: render a synthetic scene with known geometry (COLMAP or Blender layout)."""

from typing import Annotated, Literal

import tyro


def parse_size(size: str) -> "tuple[int, int]":
    """``"128x96"`` -> ``(128, 96)`` (width, height)."""
    from nerfpipe.util.errors import NerfpipeError

    parts = size.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise NerfpipeError(f"--size must look like WIDTHxHEIGHT (e.g. 128x128), got '{size}'")
    w, h = int(parts[0]), int(parts[1])
    if max(w, h) > 8192:
        raise NerfpipeError(f"--size must be at most 8192x8192, got '{size}'")
    return w, h


def synth(
    out: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")],
    layout: Literal["colmap", "blender"] = "colmap",
    views: int = 48,
    size: str = "128x128",
    scene: Literal["composite", "sphere", "room"] = "composite",
    seed: int = 0,
    min_elevation: "float | None" = None,
    max_elevation: "float | None" = None,
    save_depth: bool = False,
    overwrite: bool = False,
) -> int:
    """Render a synthetic scene (ground-truth mesh included) into a new folder.

    Args:
        out: Output folder (must be empty or absent).
        layout: ``colmap`` (images/ + sparse/0, white background) or ``blender`` (transforms_*.json, RGBA).
        views: Number of cameras, all splits together.
        size: Image size WIDTHxHEIGHT in pixels.
        scene: ``composite`` (box + sphere + torus, patterned), ``sphere`` (radius 0.8) or ``room`` (the composite on
            the floor of a patterned room: an object in its surroundings, as real captures show it).
        seed: Seed of camera azimuths, colour pattern and sparse points.
        min_elevation: Lowest camera elevation in degrees (default: -25, or 10 in the room, above its floor).
        max_elevation: Highest camera elevation in degrees (default: 75, or 60 in the room).
        save_depth: Also write depth/<view>.npy (distance along the ray, 0 on background).
        overwrite: Replace ``out`` if it holds a previous synthetic scene.
    """
    import os
    import time

    from nerfpipe.data.synthetic import ROOM_ELEVATIONS, SynthConfig, generate

    width, height = parse_size(size)
    low, high = ROOM_ELEVATIONS if scene == "room" else (SynthConfig.min_elevation_deg, SynthConfig.max_elevation_deg)
    cfg = SynthConfig(
        scene=scene, layout=layout, views=views, width=width, height=height, seed=seed, save_depth=save_depth,
        min_elevation_deg=low if min_elevation is None else min_elevation, max_elevation_deg=high if max_elevation is None else max_elevation,
    )
    start = time.perf_counter()
    result = generate(out, cfg, overwrite=overwrite)
    seconds = time.perf_counter() - start
    print(
        f"wrote {scene} scene ({layout}, {views} views {width}x{height}, {result.num_points} sparse points) "
        f"to {result.path} in {seconds:.1f} s (load {os.getloadavg()[0]:.1f})"
    )
    return 0
