"""Where a trained run's held-out error lies: each held-out view's squared error split by what its rays meet (the
object region, the support plane outside it, the rest), and a bound on what a per-image exposure model could gain:
the PSNR after an affine colour map fitted to the whole photograph (an oracle: the view's own pixels choose it).

Run: ``python -m benchmarks.held_out_regions RUN [--max-size 400] [--pictures DIR]``. Prints one JSON line per view
and one for the totals; ``--pictures`` writes per view the photograph, the render and the signed error (red where
the render is brighter, blue where darker, 4x), which shows lighting that no model of the scene can predict (a
photographer's shadow) apart from what it misses.
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import json
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

from nerfpipe.functional.metrics import psnr_from_mse
from nerfpipe.util.typing import Bool, Float, Tensor


@dataclass
class RegionsConfig:
    run: tyro.conf.Positional[Path]
    """A trained run (its folder or its ``train`` folder)."""
    max_size: "int | None" = 400
    """Longer side of the renders at most (None: full resolution)."""
    supersample: int = 1
    """Rays per pixel side at most for views smaller than their photographs."""
    views: int = 0
    """Held-out views scored (0: all of the split)."""
    pictures: "Path | None" = None
    """Write ``view_NNNN.png`` (photograph | render | signed error, as ``nerfpipe eval --pictures`` orders its strips) here."""
    threads: int = 2


REGIONS = ("box", "plane", "rest")


def ray_regions(
    origins: Float[Tensor, "num_rays 3"], directions: Float[Tensor, "num_rays 3"], box: Float[Tensor, "2 3"],
    plane: "Float[Tensor, '4'] | None" = None,
) -> "dict[str, Bool[Tensor, 'num_rays']]":
    """Each ray's region, one of :data:`REGIONS`: it crosses ``box`` (in front of its origin), else it meets ``plane``
    (``a x + b y + c z + d = 0`` with the cameras on its positive side) from above, else neither."""
    from nerfpipe.estimators.occupancy import ray_aabb_intersect
    from nerfpipe.fields.plane import plane_hits

    t_in, t_out = ray_aabb_intersect(origins, directions, box)
    inside = (t_out >= t_in) & (t_out > 0)
    hit = plane_hits(origins, directions, plane)[1] if plane is not None else torch.zeros_like(inside)
    return {"box": inside, "plane": hit & ~inside, "rest": ~hit & ~inside}


def oracle_affine_mse(pred: Float[Tensor, "num_pixels 3"], gt: Float[Tensor, "num_pixels 3"]) -> float:
    """Mean squared error after the affine colour map (3 x 3 and an offset) that best maps ``pred`` to ``gt`` (least
    squares on all the pixels): at most the plain error, since the identity is one such map."""
    from nerfpipe.training.evaluation import affine_colour, fit_affine_colour

    return float(((affine_colour(pred, fit_affine_colour(pred, gt)) - gt.double()) ** 2).mean())


def main(cfg: RegionsConfig) -> dict:
    from nerfpipe.data.rays import camera_rays
    from nerfpipe.outputs.novel_views import RenderConfig, background
    from nerfpipe.outputs.render import render_cameras, resize_cameras
    from nerfpipe.training.evaluation import eval_sizes, eval_views, ground_truth, view_supersample
    from nerfpipe.training.runs import load_run, model_dir

    torch.set_num_threads(cfg.threads)
    scene, model, run_cfg = load_run(model_dir(cfg.run), "cpu")
    idx = eval_views(scene, cfg.views)
    sizes = eval_sizes(scene, idx, 1.0, cfg.max_size)
    bg = background(RenderConfig(), run_cfg, scene)
    box = getattr(model, "object_box", scene.aabb)
    plane = model.plane.plane if getattr(model, "plane", None) is not None else None
    cams = scene.cameras[torch.tensor(idx, dtype=torch.long)]
    totals = {k: [0, 0.0] for k in REGIONS}
    rows = []
    for i, (w, h) in enumerate(sizes):
        cam = resize_cameras(cams[i : i + 1], w, h)
        view = render_cameras(model, cam, None, bg, view_supersample(cams, i, (w, h), cfg.supersample))[0]
        gt = ground_truth(scene, idx[i], bg, (w, h))
        pred, target = view.rgb.reshape(-1, 3).float(), gt.reshape(-1, 3).float()
        err = ((pred - target) ** 2).mean(-1)
        rays = camera_rays(cam, 0).reshape(-1)
        masks = ray_regions(rays.origins, rays.directions, box.to(rays.origins), None if plane is None else plane.to(rays.origins))
        row = {"view": idx[i], "psnr": psnr_from_mse(float(err.mean())), "psnr_oracle_affine": psnr_from_mse(oracle_affine_mse(pred, target))}
        for k, m in masks.items():
            totals[k][0] += int(m.sum())
            totals[k][1] += float(err[m].sum())
            row[f"{k}_share"] = float(m.float().mean())
            row[f"{k}_psnr"] = psnr_from_mse(float(err[m].mean())) if bool(m.any()) else None
        rows.append(row)
        print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        if cfg.pictures is not None:
            _picture(cfg.pictures / f"view_{idx[i]:04d}.png", view.rgb.reshape(h, w, 3), gt.reshape(h, w, 3))
    pixels, error = sum(c for c, _ in totals.values()), sum(e for _, e in totals.values())
    summary = {
        "views": len(rows), "psnr": sum(r["psnr"] for r in rows) / len(rows),
        "psnr_oracle_affine": sum(r["psnr_oracle_affine"] for r in rows) / len(rows),
        **{f"{k}_pixel_share": c / pixels for k, (c, _) in totals.items()},
        **{f"{k}_error_share": (e / error if error > 0 else 0.0) for k, (_, e) in totals.items()},
        **{f"{k}_psnr": (psnr_from_mse(e / c) if c else None) for k, (c, e) in totals.items()},
    }
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in summary.items()}), flush=True)
    return {"views": rows, "summary": summary}


def _picture(path: Path, pred: Float[Tensor, "H W 3"], gt: Float[Tensor, "H W 3"]) -> None:
    from nerfpipe.outputs.render import to_uint8
    from nerfpipe.training.evaluation import save_snapshot

    path.parent.mkdir(parents=True, exist_ok=True)
    signed = (pred.float() - gt.float()).mean(-1, keepdim=True) * 4.0
    grey = torch.full_like(signed, 0.5)
    heat = torch.cat([grey + signed.clamp(min=0), grey - signed.abs() * 0.5, grey - signed.clamp(max=0)], dim=-1).clamp(0, 1)
    save_snapshot(path, to_uint8(torch.cat([gt.float().clamp(0, 1), pred.float().clamp(0, 1), heat], dim=1)))


if __name__ == "__main__":
    main(tyro.cli(RegionsConfig))
