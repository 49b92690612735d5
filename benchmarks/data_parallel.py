"""What one data-parallel step sends, and how long gloo takes to send it here (the inputs of the
README's paper estimate of multi-GPU scaling).

For a scene and the ``fast`` model's preset it builds the model (no training) and reports:

* the gradient bytes all-reduced every step (every optimised parameter, dense: the grids' too);
* the occupancy-grid bytes broadcast from rank 0 at each refresh (every ``update_every`` steps);

then times, with two processes on this machine (gloo over loopback), the all-reduce of those
gradients as the trainer does it (one asynchronous all-reduce per tensor), and the broadcast of
the grid. Run::

    python -m benchmarks.data_parallel ../shared/data/lego_200x200/lego_200x200.npz --preset small
"""

import argparse
import json
import os
import statistics
import tempfile
import time

import torch


def model_sizes(path: str, preset: "str | None") -> dict:
    from nerfpipe.data_adapters import load
    from nerfpipe.plugins.train import model_config
    from nerfpipe.training.trainer import scene_info

    model = model_config("fast", {"preset": preset} if preset else {}).setup(scene_info(load(path)))
    params = [p for g in model.param_groups() for p in g["params"]]
    grid = [model.grid.density, model.grid.binary]
    return {
        "tensors": [list(p.shape) for p in params],
        "gradient_bytes": sum(p.numel() * p.element_size() for p in params),
        "grid_bytes": sum(t.numel() * t.element_size() for t in grid),
        "grid_shapes": [[t.numel(), str(t.dtype)] for t in grid],
        "update_every": model.cfg.occupancy.update_every,
    }


def step_split(path: str, preset: "str | None", rays: int, steps: int) -> dict:
    """Seconds per training step of one process at ``rays`` and ``rays / 2`` rays per step, and of the
    optimiser's step alone (the part every rank repeats whatever its share of the rays): what the
    ray-proportional part of a step is, on this machine."""
    from nerfpipe.data_adapters import load
    from nerfpipe.plugins.train import model_config
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    scene, out = load(path), {}
    for n in (rays, rays // 2):
        cfg = TrainerConfig(iters=steps, rays_per_step=n, eval_every=0, video_frames=0, write_outputs=False, checkpoint_every=0)
        with tempfile.TemporaryDirectory() as tmp:
            t = Trainer(cfg, scene, "fast", model_config("fast", {"preset": preset} if preset else {}), tmp)
            t.model.train()
            for _ in range(steps // 2):  # past the occupancy warm-up
                t.train_step()
            t0 = time.perf_counter()
            for _ in range(steps - steps // 2):
                t.train_step()
            out[f"step_ms_{n}_rays"] = 1000 * (time.perf_counter() - t0) / (steps - steps // 2)
            t0 = time.perf_counter()
            for _ in range(5):
                t.optimizer.step()
            out["optimizer_step_ms"] = 1000 * (time.perf_counter() - t0) / 5
    return out


def _worker(rank: int, store: str, sizes: dict, repeats: int, result: str) -> None:
    import torch.distributed as dist

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=2)
    grads = [torch.randn(s) for s in sizes["tensors"]]
    numel = sizes["grid_shapes"][0][0]
    grid = [torch.randn(numel), torch.zeros(numel, dtype=torch.bool)]

    def timed(fn) -> float:
        fn()  # warm-up
        out = []
        for _ in range(repeats):
            dist.barrier()
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
        return statistics.median(out)

    def all_reduce():
        for w in [dist.all_reduce(g, async_op=True) for g in grads]:
            w.wait()

    def broadcast():
        for w in [dist.broadcast(t, src=0, async_op=True) for t in grid]:
            w.wait()

    times = {"all_reduce_s": timed(all_reduce), "broadcast_s": timed(broadcast)}
    if rank == 0:
        with open(result, "w") as f:
            json.dump(times, f)
    dist.destroy_process_group()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data")
    ap.add_argument("--preset", default=None, help="fast model preset (default: the model's choice for the scene)")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--rays", type=int, default=4096, help="rays per step of the one-process step timing")
    ap.add_argument("--steps", type=int, default=0, help="also time this many one-process steps at --rays and half of it")
    args = ap.parse_args()
    sizes = model_sizes(args.data, args.preset)
    split = {k: round(v, 1) for k, v in step_split(args.data, args.preset, args.rays, args.steps).items()} if args.steps else {}
    with tempfile.TemporaryDirectory() as tmp:
        store, result = os.path.join(tmp, "store"), os.path.join(tmp, "result.json")
        torch.multiprocessing.spawn(_worker, args=(store, sizes, args.repeats, result), nprocs=2)
        with open(result) as f:
            times = json.load(f)
    mb = sizes["gradient_bytes"] / 2**20
    out = {"gradient_mb": round(mb, 2), "grid_mb": round(sizes["grid_bytes"] / 2**20, 2), "update_every": sizes["update_every"],
           "gloo_all_reduce_ms": round(1000 * times["all_reduce_s"], 1), "gloo_broadcast_ms": round(1000 * times["broadcast_s"], 1),
           "gloo_all_reduce_gb_per_s": round(sizes["gradient_bytes"] / times["all_reduce_s"] / 1e9, 2),
           **split, "threads": torch.get_num_threads(),
           "load": open("/proc/loadavg").read().split()[:3]}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
