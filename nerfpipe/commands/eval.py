"""``nerfpipe eval``: the full evaluation protocol of a trained run, whatever budget it was trained under."""

from pathlib import Path

from tyro.conf import Positional


def eval_run(
    run_dir: Positional[Path],
    views: int = 0,
    scale: float = 1.0,
    max_size: "int | None" = None,
    supersample: int = 2,
    chunk: "int | None" = None,
    device: str = "auto",
    json: bool = False,
    pictures: bool = False,
) -> int:
    """Score a trained run on its held-out views: every view at full resolution by default, PSNR and SSIM,
    and LPIPS (AlexNet) when the lpips package and its weights are on this machine (nothing is downloaded).
    Writes RUN_DIR/eval.json.

    Args:
        run_dir: a run folder of nerfpipe train or nerfpipe run (its train/ folder).
        views: the first this many views of the evaluation split (0: all).
        scale: resolution factor of the renders (ground truth is area-resized to match).
        max_size: longer side of the renders in pixels at most (none: full size).
        supersample: rays per pixel side at most in renders smaller than their photographs, each pixel the mean over its
            area (1: one ray through its centre; full-size renders always take one).
        chunk: rays per forward pass (bounds memory; default: the model's ``render_chunk``).
        device: torch device (auto: CUDA when present, else CPU; printed first, or named in the JSON).
        json: print the result as JSON only.
        pictures: also write each view's photograph, render and error map side by side to RUN_DIR/eval/ (one colour
            scale for every view: where a held-out view goes wrong, at a glance); for photo collections the render
            takes the appearance fitted to the view's left half, as the appearance-fitted figure scores it.
    """
    import json as _json
    import time

    from nerfpipe.outputs.novel_views import RenderConfig, background
    from nerfpipe.training.evaluation import eval_sizes, eval_split, eval_views, fitted_figure_note, lpips_scorer, score_views
    from nerfpipe.training.runs import load_run, model_dir
    from nerfpipe.util.atomic import write_json
    from nerfpipe.util.devices import check_device, describe
    from nerfpipe.util.errors import refuse_unless, require

    refuse_unless([("views", views >= 0, "0 or more", views), ("scale", 0 < scale <= 16, "a positive factor (at most 16)", scale),
                   ("max_size", max_size is None or max_size >= 1, "at least 1", max_size),
                   ("supersample", 1 <= supersample <= 8, "1 to 8", supersample), ("chunk", chunk is None or chunk >= 1, "at least 1", chunk)])
    require("kornia", "kornia")
    folder = model_dir(Path(run_dir))
    device = check_device(device)
    if not json:  # with --json, stdout is the JSON alone (it names the device)
        print(describe(device), flush=True)
    scene, model, cfg = load_run(folder, device)
    idx = eval_views(scene, views)
    sizes = eval_sizes(scene, idx, scale, max_size)
    bg = background(RenderConfig(), cfg, scene)  # the run's evaluation background
    lpips, lpips_note = lpips_scorer(device)
    on_view, pictures_dir = None, folder / "eval"
    if pictures:
        from nerfpipe.outputs.colormap import error_strip
        from nerfpipe.training.evaluation import save_snapshot

        def on_view(i, view, gt):
            save_snapshot(pictures_dir / f"view_{i:04d}.png", error_strip(view.rgb, gt))
    start = time.perf_counter()
    scores = score_views(model, scene, idx, sizes, bg, device, chunk, lpips=lpips, progress=not json, fit_appearance=True,
                         supersample=supersample, on_view=on_view)
    result = {
        "split": eval_split(scene), "views": len(idx), "sizes": sorted({f"{w}x{h}" for w, h in sizes}), "supersample": supersample,
        "psnr": _mean(scores["psnr"]), "ssim": _mean(scores["ssim"]), "psnr_colour_fitted": _mean(scores["fitted_psnr"]),
        "psnr_appearance_fitted": _mean(scores["appearance_fitted_psnr"]) if scores["appearance_fitted_psnr"] else None,
        "lpips": _mean(scores["lpips"]) if lpips is not None else None, "lpips_note": lpips_note,
        "per_view": [{"view": i, "psnr": p, "ssim": s} for i, p, s in zip(idx, scores["psnr"], scores["ssim"])],
        "seconds": time.perf_counter() - start, "device": device,
    }
    if pictures:
        from nerfpipe.outputs.colormap import error_text

        render = ("appearance fitted on its left half (right half scored)" if scores["appearance_fitted_psnr"] else
                  "an affine colour map fitted on its left half (the colour-fitted figure's)" if getattr(model, "appearance", None) is not None
                  else "mean appearance")
        result["pictures"] = {"folder": str(pictures_dir), "files": [f"view_{i:04d}.png" for i in idx], "mapping": error_text(), "render": render}
    write_json(folder / "eval.json", result)
    if json:
        print(_json.dumps(result, indent=2))
    else:
        lp = f", LPIPS {result['lpips']:.4f}" if result["lpips"] is not None else f" (no LPIPS: {lpips_note})"
        fitted = fitted_figure_note({"val_psnr_appearance_fitted": result["psnr_appearance_fitted"],
                                     "val_psnr_colour_fitted": result["psnr_colour_fitted"], "appearance": getattr(model, "appearance", None) is not None})
        print(f"{folder}: {len(idx)} {result['split']} views at {', '.join(result['sizes'])}: "
              f"PSNR {result['psnr']:.2f} dB{fitted}, SSIM {result['ssim']:.4f}{lp} -> {folder / 'eval.json'}")
        if pictures:
            print(f"error maps ({result['pictures']['mapping']}; render: {result['pictures']['render']}): {pictures_dir}")
    return 0


def _mean(values: "list[float]") -> float:
    return sum(values) / len(values)
