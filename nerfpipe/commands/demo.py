"""``nerfpipe demo``: the README's main command. Needs no data: it renders the default synthetic
scene, then reads and checks it like any user dataset. Later issues extend it to train + mesh."""

from typing import Optional


def demo(out: Optional[str] = None, views: int = 48, seed: int = 0) -> int:
    """Generate the default synthetic scene (COLMAP layout), then run ``info`` and ``check`` on it.

    Args:
        out: Folder for the scene (default: a new temporary folder, kept and printed).
        views: Number of cameras of the scene.
        seed: Seed of the scene.
    """
    import tempfile

    import data_adapters
    from nerfpipe.commands.info import print_table, summarize
    from nerfpipe.consistency import check_scene
    from nerfpipe.synthetic import SynthConfig, generate

    path = out if out is not None else tempfile.mkdtemp(prefix="nerfpipe-demo-")
    result = generate(path, SynthConfig(layout="colmap", views=views, seed=seed), overwrite=out is not None)
    print(f"synthetic scene: {result.path} ({views} views, {result.num_points} sparse points, gt_mesh.ply)")
    scene = data_adapters.load(result.path)
    print_table(f"info: {result.path}", summarize(scene))
    report = check_scene(scene)
    figures = report.as_dict()
    failures = figures.pop("failures")
    print_table(f"check: {result.path}", {k: v for k, v in figures.items() if v is not None})
    for line in failures:
        print(f"FAILED: {line}")
    print("all checks passed" if not failures else f"{len(failures)} check(s) failed")
    return 1 if failures else 0
