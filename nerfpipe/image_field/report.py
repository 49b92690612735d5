"""Outputs of 2D fits: PSNR plots, progress strip, final image, metrics and sweep tables.

Every file is written atomically (temp file in the same folder, then ``os.replace``).
"""

from pathlib import Path

import numpy as np

from nerfpipe.util.atomic import atomic_write, write_json, write_text  # noqa: F401 (used by the fit2d modules)
from nerfpipe.image_field.train import FitResult


def write_png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    atomic_write(path, lambda p: iio.imwrite(p, img, extension=".png"))


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(fig, path: Path) -> None:
    atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=100, bbox_inches="tight"))
    _pyplot().close(fig)


def save_psnr_plot(curves: "dict[str, FitResult]", path: Path, title: str = "") -> None:
    """PSNR against iteration (left) and against training seconds (right), one line per run."""
    plt = _pyplot()
    fig, (ax_it, ax_s) = plt.subplots(1, 2, figsize=(12, 4.5))
    for label, r in curves.items():
        ax_it.plot(r.curve_iterations, r.curve_psnr, marker=".", label=label)
        ax_s.plot(r.curve_seconds, r.curve_psnr, marker=".", label=label)
    for ax, xlabel in ((ax_it, "iteration"), (ax_s, "training seconds (evaluation excluded)")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    ax_s.legend(fontsize=8, loc="lower right")
    if title:
        fig.suptitle(title)
    _save_figure(fig, path)


def save_progress(result: FitResult, original: np.ndarray, path: Path) -> None:
    """The kept reconstructions side by side, ending with the original."""
    plt = _pyplot()
    its = sorted(result.snapshots)
    psnr = dict(zip(result.curve_iterations, result.curve_psnr))
    fig, axes = plt.subplots(1, len(its) + 1, figsize=(3.2 * (len(its) + 1), 3.6))
    for ax, it in zip(axes, its):
        ax.imshow(result.snapshots[it])
        ax.set_title(f"iteration {it}\n{psnr.get(it, float('nan')):.2f} dB", fontsize=10)
    axes[-1].imshow(original)
    axes[-1].set_title("original", fontsize=10)
    for ax in axes:
        ax.axis("off")
    _save_figure(fig, path)


def sweep_markdown(rows: "list[dict]") -> str:
    """A markdown table of the sweep rows (L, lr, final PSNR, seconds, params)."""
    lines = ["| L | lr | PSNR (dB) | train s | iterations | params |", "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['L']} | {r['lr']:g} | {r['psnr']:.2f} | {r['seconds']:.1f} | {r['iterations']} | {r['params']} |"
        )
    return "\n".join(lines) + "\n"
