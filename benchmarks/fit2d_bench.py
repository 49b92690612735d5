"""Benchmark of ``nerfpipe fit2d``: the course recipe and the fast grid on one image, in one run.

Run: ``python -m benchmarks.fit2d_bench IMAGE --out DIR``. Writes ``fit2d_bench.json``,
``fit2d_bench.md`` and ``psnr_vs_seconds.png`` (both PSNR curves against training seconds) to DIR,
plus each run's own outputs in ``DIR/course`` and ``DIR/fast``. Training seconds exclude the
periodic full-image evaluation; CPU seconds and the load average are recorded next to them
because wall-clock time is inflated on a shared machine.
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import os
from pathlib import Path
from typing import Optional

import tyro


def _summary(name: str, result, target_db: float, budget_s: float) -> dict:
    reach = [s for s, p in zip(result.curve_seconds, result.curve_psnr) if p >= target_db]
    return {
        "run": name,
        "psnr": result.psnr,
        "seconds": result.train_seconds,
        "cpu_seconds": result.train_cpu_seconds,
        "eval_seconds": result.eval_seconds,
        "iterations": result.iterations,
        "params": result.params,
        f"psnr_within_{budget_s:g}s": result.psnr_at_seconds(budget_s),
        f"seconds_to_{target_db:g}dB": reach[0] if reach else None,
    }


def _markdown(rows: "list[dict]", image: str, values: int, load: "tuple[float, ...]") -> str:
    keys = list(rows[0])
    lines = [f"# fit2d benchmark on {image} (H·W·3 = {values})", "",
             f"load average before/after: {load}", "",
             "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in r.values()) + " |")
    return "\n".join(lines) + "\n"


def main(
    image: tyro.conf.Positional[Optional[Path]] = None,
    out: Path = Path("fit2d_bench_out"),
    course_iterations: int = 3000,
    fast_iterations: Optional[int] = None,
    target_db: float = 30.0,
    budget_seconds: float = 20.0,
    course_max_seconds: Optional[float] = None,
    skip_course: bool = False,
    threads: int = 2,
) -> None:
    """Train the course recipe and the fast grid on IMAGE; write PSNR against seconds.

    Args:
        image: image file (default: scikit-image's astronaut).
        out: output folder.
        course_iterations: iterations of the course recipe (the course uses 2000-3000).
        fast_iterations: iterations of the fast preset (default: the preset's).
        target_db: report the training seconds at which each run first reaches this PSNR.
        budget_seconds: report the best PSNR within this many training seconds.
        course_max_seconds: stop the course recipe after this much training time (busy machines).
        skip_course: only run the fast preset.
        threads: torch CPU threads.
    """
    import torch

    from nerfpipe.image_field import fit2d_run, report
    from nerfpipe.image_field.images import load_target

    torch.set_num_threads(threads)
    target = load_target(image)
    load_before = os.getloadavg()
    runs = [("fast", {"iterations": fast_iterations} if fast_iterations else {})]
    if not skip_course:
        course = {"iterations": course_iterations}
        runs.append(("course", course if course_max_seconds is None else {**course, "max_seconds": course_max_seconds}))
    results, rows = {}, []
    for name, overrides in runs:
        cfg = fit2d_run.configure(name, overrides, target.pixels.shape)
        results[name] = fit2d_run.run_single(target, cfg, name, out / name)
        rows.append(_summary(name, results[name], target_db, budget_seconds))
    load = tuple(round(v, 2) for v in load_before + os.getloadavg())
    values = int(target.pixels.size)
    report.save_psnr_plot(results, out / "psnr_vs_seconds.png", title=f"{target.source}: {' vs '.join(reversed(list(results)))}")
    report.write_json(out / "fit2d_bench.json", {"image": target.source, "image_values": values,
                                                "rows": rows, "loadavg_before_after": load,
                                                "machine": fit2d_run.machine()})
    report.write_text(out / "fit2d_bench.md", _markdown(rows, target.source, values, load))
    print(_markdown(rows, target.source, values, load))


if __name__ == "__main__":
    tyro.cli(main)
