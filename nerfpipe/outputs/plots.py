"""Figures of a run: PSNR curves, validation progress, cameras with rays and samples (matplotlib, lazily)."""

from pathlib import Path

import torch

from nerfpipe.util.atomic import atomic_write
from nerfpipe.util.errors import require


PLOT_DEPENDENCIES = (("matplotlib", "plot"),)
"""What the figures need beyond the core (checked before training by :func:`nerfpipe.training.evaluation.dependencies`)."""


def _pyplot():
    mpl = require(*PLOT_DEPENDENCIES[0])
    mpl.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    plt = _pyplot()
    atomic_write(path, lambda p: fig.savefig(p, dpi=100, format="png", bbox_inches="tight"))
    plt.close(fig)


def plot_psnr(history: dict, path: Path, appearance_fitted: "tuple[int, float, float, int] | None" = None) -> None:
    """Train and val PSNR against iterations (left) and training seconds (right).

    ``appearance_fitted``: ``(iteration, seconds, psnr, views)`` of the final evaluation's appearance-fitted figure, for
    a model with per-image appearance (photo collections): drawn as a star, and the val curves, rendered with the
    mean appearance, say so (on Sacre Coeur they sit near 11 dB and the scored figure near 16)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    train, val = history["train"], history["val"]
    mean = ", mean appearance" if appearance_fitted is not None else ""
    for ax, col, label in ((axes[0], 0, "iteration"), (axes[1], 1, "training seconds")):
        if train:
            ax.plot([r[col] for r in train], [r[2] for r in train], lw=0.8, alpha=0.7, label="train (batch)")
        for n in sorted({r[4] if len(r) > 4 else 0 for r in val}):  # one series per number of views
            rows = [r for r in val if (r[4] if len(r) > 4 else 0) == n]
            ax.plot([r[col] for r in rows], [r[2] for r in rows], "o-", label=f"val ({n} view{'s' * (n != 1)}{mean})" if n else f"val{mean}")
        if appearance_fitted is not None:
            step, seconds, psnr, views = appearance_fitted
            ax.plot([(step, seconds)[col]], [psnr], "*", ms=14, label=f"final, appearance fitted ({views} view{'s' * (views != 1)}): {psnr:.2f} dB")
        ax.set_xlabel(label)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:  # one legend under both plots: inside, it covered the val curve under the train curve (Sacre Coeur)
        fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=min(len(handles), 3), frameon=False)
    fig.suptitle("PSNR")
    _save(fig, path)


def plot_progress(snapshots: "list[Path]", path: Path, max_panels: int = 8) -> None:
    """One validation view at several iterations (evenly chosen snapshots, the last one included)."""
    if not snapshots:
        return
    from nerfpipe.data.image_file import read_image_uint8

    plt = _pyplot()
    idx = torch.linspace(0, len(snapshots) - 1, min(max_panels, len(snapshots))).round().long().unique().tolist()
    fig, axes = plt.subplots(1, len(idx), figsize=(2.6 * len(idx), 2.9), squeeze=False)
    for ax, i in zip(axes[0], idx):
        ax.imshow(read_image_uint8(snapshots[i]))
        ax.set_title(f"iter {int(snapshots[i].stem.split('_')[1])}", fontsize=9)
        ax.axis("off")
    _save(fig, path)


def _frustum_lines(cams, scale: float) -> "list[torch.Tensor]":
    """Five line strips per camera: the four edges to the image corners and the image rectangle."""
    lines = []
    for i in range(len(cams)):
        w, h = float(cams.width[i]), float(cams.height[i])
        uv = torch.tensor([[0, 0], [w, 0], [w, h], [0, h]], dtype=cams.fx.dtype)
        xy = torch.stack([(uv[:, 0] - cams.cx[i]) / cams.fx[i], (uv[:, 1] - cams.cy[i]) / cams.fy[i]], -1)
        pts = torch.cat([xy, torch.ones(4, 1, dtype=xy.dtype)], -1) * scale
        m = cams.world_from_cam[i]
        corners = pts @ m[:3, :3].T + m[:3, 3]
        c = m[:3, 3]
        lines += [torch.stack([c, p]) for p in corners] + [torch.cat([corners, corners[:1]])]
    return lines


def plot_cameras(scene, sampler, path: Path, num_samples: int = 64, num_rays: int = 100, max_cams: int = 100) -> None:
    """Training camera frustums, ``num_rays`` random training rays (from ``sampler``, a
    :class:`~nerfpipe.training.pixel_sampler.PixelSampler`) and their stratified sample points in 3D."""
    from nerfpipe.data.samples import RaySamples
    from nerfpipe.functional.sampling import stratified_samples

    plt = _pyplot()
    cams = scene.split_cameras("train")[: max_cams]
    batch = sampler.sample(num_rays, torch.Generator().manual_seed(0))
    num = num_samples
    near = torch.full((num_rays,), float(scene.near))
    edges = stratified_samples(near, torch.full_like(near, float(scene.far)), num, perturb=True, generator=torch.Generator().manual_seed(0))
    rays = batch.rays.to("cpu")
    samples = RaySamples.from_edges(rays, edges)
    fig = plt.figure(figsize=(8, 8))
    ax = fig.add_subplot(projection="3d")
    for line in _frustum_lines(cams, 0.1 * scene.near):
        ax.plot(*line.T.numpy(), color="tab:blue", lw=0.6)
    o, far_pts = rays.origins, rays.points_at(torch.full((num_rays,), float(scene.far)))
    for a, b in zip(o, far_pts):
        ax.plot(*torch.stack([a, b]).T.numpy(), color="gray", lw=0.3, alpha=0.5)
    p = samples.positions.reshape(-1, 3).numpy()
    ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=0.5, c="tab:red", depthshade=False)
    ax.set_xlabel("x"), ax.set_ylabel("y"), ax.set_zlabel("z (up)")
    ax.set_title(f"{len(cams)} training cameras, {num_rays} rays, {num} samples each (near {scene.near:g}, far {scene.far:g})", fontsize=9)
    ax.set_box_aspect((1, 1, 1))
    _save(fig, path)
