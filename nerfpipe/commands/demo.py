"""``nerfpipe demo``: the README's main command. Needs no data: it renders the default synthetic
scene (COLMAP layout, with its ground-truth mesh) and runs the default chain of ``nerfpipe run``
on it through the same :class:`nerfpipe.pipeline.stages.Pipeline`, with demo-sized options."""

from pathlib import Path


def demo_configs(train_seconds: float, mesh_resolution: int = 256, frames: int = 36) -> dict:
    """Stage options of the demo: a time-capped ``fast`` training on the scene's white background.

    The background must be white: the images have no alpha, so the trainer's ``auto`` mode would
    composite on black, and rays that miss the model's box could never render the white around
    the object (val PSNR near 12 dB instead of above 20 after a minute).
    """
    return {
        # the synthetic scene is bounded (one colour around the objects): no field behind the box, whose cost
        # (519 -> 359 iterations in 90 s) buys nothing here (F-score@1% 0.986 without it at 192^3)
        "train": {"model": "fast", "model_options": {"background_field": False}, "trainer": {"iters": 100_000, "train_budget": train_seconds, "background": "white",
                                               "eval_every": 100}},
        "render": {"frames": frames},
        "mesh": {"mesh": {"resolution": mesh_resolution}},
    }


def demo(out: Path = Path("runs/demo"), time_budget: float = 300.0, train_seconds: float = 90.0, views: int = 48, seed: int = 0, device: str = "auto") -> int:
    """Generate the default synthetic scene, then run the default chain on it (sfm, load, check, train, mesh, render, export, report).

    Prints the stage table, the validation PSNR, the mesh F-score@1% and Chamfer-L1 against the
    scene's gt_mesh.ply, and the path of report.html.

    Args:
        out: run folder; the scene is generated into OUT/synthetic_scene. A fresh run each time.
        time_budget: seconds the whole command may take (the scene's generation included); training gets at most 60% of what is left.
        train_seconds: cap on the training time (validation excluded).
        views: number of cameras of the scene.
        seed: seed of the scene.
        device: torch device (auto: CUDA when present, else CPU; printed at start).
    """
    from nerfpipe.commands.run import _console, _log_to, installed_stages, run_and_print
    from nerfpipe.commands.train import budget_start
    from nerfpipe.data.synthetic import SynthConfig, generate
    from nerfpipe.pipeline.stages import DEFAULT_CHAIN, Pipeline
    from nerfpipe.util.devices import check_device
    from nerfpipe.util.errors import refuse_unless
    from nerfpipe.util.paths import check_output_folder

    device = check_device(device)  # before the scene is rendered into OUT (printed with the chain)
    check_output_folder(out)
    refuse_unless([("time_budget", time_budget > 0, "positive seconds", time_budget),
                   ("train_seconds", train_seconds > 0, "positive seconds", train_seconds)])  # fmt: skip
    console = _console()
    _log_to(console)
    scene = generate(Path(out) / "synthetic_scene", SynthConfig(layout="colmap", views=views, seed=seed), overwrite=True)
    console.print(f"synthetic scene: {scene.path} ({views} views, {scene.num_points} sparse points, gt_mesh.ply)")
    pipe = Pipeline(list(DEFAULT_CHAIN), demo_configs(train_seconds), registry=installed_stages(console))
    run_and_print(pipe, scene.path, Path(out), console, resume=False, device=device, time_budget=time_budget,
                  started=budget_start())  # from the command's start (the scene's generation included) to its exit, as `nerfpipe run`
    return 0
