"""Data-parallel training over ``torch.distributed``: the process group torchrun describes, and the
few collectives the trainer needs.

``torchrun --nproc-per-node N -m nerfpipe train DATA`` starts N copies of the command; each finds
its place in the environment torchrun sets (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``,
``MASTER_ADDR``/``MASTER_PORT``) and :func:`world` joins the group: backend gloo on the CPU, NCCL on
CUDA (one GPU per process, ``cuda:LOCAL_RANK``). Outside torchrun (``WORLD_SIZE`` unset or 1)
:func:`world` is :data:`SINGLE` and every collective below returns at once, so the one-process trainer
runs exactly as before.

What a data-parallel step is (:class:`nerfpipe.training.trainer.Trainer`):

* every rank draws its own ``rays_per_step / N`` rays from its own stream (:func:`rank_seed`);
* after the backward pass, :func:`all_reduce_gradients` sums the gradients weighted by each rank's
  share of the rays, so every rank holds the gradient of the loss over the union of the N batches
  (the mean of a mean-squared error over all rays), and the N optimisers take the same step;
  parameters stay identical without ever being sent again. The grids of the ``fast`` model are dense
  tensors (all of their gradients are sent); DDP is not used: it cannot follow parameters that a
  model resizes during training (the ``fast`` model's box tightening) and it would have to search
  for unused parameters (coarse-to-fine levels, the field behind the box before it is switched on);
* whatever a model changes outside the optimiser (the occupancy grid, its bounding box, step
  counters, grids resampled to a tightened box) is broadcast from rank 0 by :class:`BufferSync`
  after the model's hooks ran, so every rank marches the same grid;
* rank 0 alone writes (checkpoints, metrics, plots, the run folder's lock); the checkpoint keeps the
  random streams of every rank, so a resumed run draws what an uninterrupted one would, and a run
  resumed with another number of processes gives new ranks fresh streams.

Glossary:
    rank      this process's index in the group, 0 .. size - 1; rank 0 writes
    size      the number of processes (torchrun's ``WORLD_SIZE``)
    share     the rays one rank draws per step
"""

import datetime
import os
import sys
from dataclasses import dataclass

import torch

TIMEOUT = datetime.timedelta(hours=2)
"""How long a rank waits for the others at a collective (rank 0 validates and writes alone meanwhile)."""


@dataclass(frozen=True)
class World:
    """This process's place in a data-parallel group."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    restarts: int = 0
    """How often torchrun restarted the group (``TORCHELASTIC_RESTART_COUNT``): after a restart the
    trainer resumes from the run folder's checkpoint."""

    @property
    def active(self) -> bool:
        return self.size > 1

    @property
    def writer(self) -> bool:
        """Whether this process writes files (rank 0)."""
        return self.rank == 0


SINGLE = World()
"""One process: no group, no collectives."""


def env_world() -> World:
    """The place torchrun's environment gives this process (:data:`SINGLE` outside torchrun)."""
    env = os.environ
    size = int(env.get("WORLD_SIZE", "1"))
    if size <= 1:
        return SINGLE
    return World(rank=int(env.get("RANK", "0")), size=size, local_rank=int(env.get("LOCAL_RANK", "0")),
                 restarts=int(env.get("TORCHELASTIC_RESTART_COUNT", "0")))


def device_for(device: str, world: World) -> str:
    """The device of this rank: ``cuda`` becomes ``cuda:LOCAL_RANK`` in a group (one GPU per process)."""
    if world.active and device == "cuda":
        return f"cuda:{world.local_rank}"
    return device


def world(device: str = "cpu") -> World:
    """Join the group torchrun describes, once per process (gloo on the CPU, NCCL on CUDA)."""
    place = env_world()
    if not place.active:
        return place
    import torch.distributed as dist

    if not dist.is_initialized():
        cuda = torch.device(device).type == "cuda"
        if cuda:
            torch.cuda.set_device(place.local_rank)
        dist.init_process_group("nccl" if cuda else "gloo", timeout=TIMEOUT, store=_store(place), rank=place.rank, world_size=place.size)
    return place


def leave(clean: bool = True) -> bool:
    """Leave the torchrun group this process joined; returns whether it had joined one.

    Args:
        clean: the command succeeded: wait for every rank first (a barrier), so no rank tears down
            the group while another still talks to it. After an error, leave at once: the other
            ranks may be inside a collective this rank will never join.

    The process that owns the group (the CLI) ends at once after this, without the interpreter's
    finalisation (:func:`os._exit`): gloo's worker threads outlive ``destroy_process_group`` (torch
    keeps references to the group, e.g. from the fused Adam's import), and one of them freeing a
    finished collective's tensors during finalisation aborts the rank ("terminate called without an
    active exception", seen on a loaded 2-core machine with torch 2.13) after all its work succeeded.
    """
    import torch.distributed as dist

    if not dist.is_initialized():
        return False
    if clean:
        dist.barrier()
    dist.destroy_process_group()
    return True


def end_process(code: int = 0) -> None:
    """In a torchrun group: leave it (a barrier first when ``code`` is 0) and end the process with
    ``code`` at once (see :func:`leave`); outside one, return. The last call of a script that trains
    under torchrun (the CLI makes it)."""
    if leave(clean=code == 0):
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        os._exit(code)


def _store(place: World):
    """The rendezvous store of this attempt: torchrun's (or rank 0's) TCP store under an attempt prefix.

    torchrun restarts a failed group in the same store; without the prefix a rank of the new group
    can read the address a dead rank of the old one left (gloo then fails with "Connection refused"
    whenever the new ranks do not arrive together: seen with torch 2.13)."""
    from torch.distributed import PrefixStore, TCPStore

    agent = os.environ.get("TORCHELASTIC_USE_AGENT_STORE") == "True"  # torchrun's agent serves the store
    store = TCPStore(os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"]), place.size,
                     is_master=not agent and place.rank == 0, timeout=TIMEOUT)
    return PrefixStore(f"nerfpipe/attempt_{place.restarts}", store)


def rank_seed(seed: int, rank: int) -> int:
    """Seed of rank ``rank``'s streams: rank 0 keeps ``seed`` (one process draws what it always drew).

    Within 32 bits: torch's CPU generator (mt19937) keeps only the low 32 bits of a seed, so
    ``seed + (rank << 32)`` would give every rank the same rays."""
    return seed if rank == 0 else (seed + rank * 0x9E3779B9) & 0xFFFFFFFF


def _comm_device() -> torch.device:
    import torch.distributed as dist

    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else torch.device("cpu")


def all_reduce_gradients(params: "list[torch.nn.Parameter]", share: float, scalars: "list[float]") -> "list[float]":
    """Replace every gradient by the share-weighted sum over the ranks; returns ``scalars`` summed too.

    ``share`` is this rank's fraction of the step's rays (the shares sum to 1), so the result is the
    gradient of the loss over the union of the ranks' batches. A parameter no rank's loss reached
    keeps ``grad = None`` (Adam leaves it alone, as one process would); one that only some reached
    gets zeros on the others first. ``scalars`` (e.g. share-weighted losses) travel in the same
    small message as the flags saying which parameters have gradients.
    """
    import torch.distributed as dist

    dev = _comm_device()
    flags = torch.tensor([float(p.grad is not None) for p in params] + list(scalars), dtype=torch.float64, device=dev)
    dist.all_reduce(flags)
    has = flags[: len(params)].tolist()
    work = []
    for p, h in zip(params, has):
        if not h:
            continue
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        p.grad.mul_(share)
        work.append(dist.all_reduce(p.grad, async_op=True))
    for w in work:
        w.wait()
    return flags[len(params):].tolist()


def maximum(value: float) -> float:
    """The largest ``value`` over the ranks (e.g. training seconds: the group is as slow as its slowest rank)."""
    import torch.distributed as dist

    t = torch.tensor([value], dtype=torch.float64, device=_comm_device())
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return float(t)


def gather_bytes(state: torch.Tensor) -> torch.Tensor:
    """``[size, n]``: every rank's ``state`` (a generator state, uint8 ``[n]``, same ``n`` on every rank), on the CPU."""
    import torch.distributed as dist

    dev = _comm_device()
    out = [torch.empty_like(state, device=dev) for _ in range(dist.get_world_size())]
    dist.all_gather(out, state.to(dev))
    return torch.stack([t.cpu() for t in out])


def broadcast_object(value: object) -> object:
    """Rank 0's ``value`` on every rank (small picklable objects: decisions, metrics)."""
    import torch.distributed as dist

    box = [value]
    dist.broadcast_object_list(box, src=0, device=_comm_device() if dist.get_backend() == "nccl" else None)
    return box[0]


def broadcast_module(module: torch.nn.Module) -> None:
    """Every parameter and buffer of ``module`` from rank 0 (tensors of the same shapes on every rank)."""
    import torch.distributed as dist

    tensors = [t for _, t in module.named_parameters()] + [t for _, t in module.named_buffers()]
    work = [dist.broadcast(t.data, src=0, async_op=True) for t in tensors]
    for w in work:
        w.wait()


class BufferSync:
    """Broadcasts from rank 0 the tensors of a module that changed outside the optimiser.

    A model changes some tensors in its hooks (the occupancy grid's densities and bits, the march
    box, step counters; parameters resampled to a tightened box). :meth:`mark` notes every tensor
    (after the optimiser's step, which changes the parameters identically on every rank); a call
    after the hooks finds the ones changed since, by identity, storage, shape and torch's in-place
    version counter;
    the ranks agree on the union of their notes (one small all-reduce) and rank 0 sends those
    tensors, so every rank marches the same grid even where the ranks' random refreshes differed.
    Shapes change identically on every rank (a tightened box follows from the synchronised grid).
    """

    def __init__(self, module: torch.nn.Module) -> None:
        self.module = module
        self.mark()

    def mark(self) -> None:
        """Note the tensors as they are now (as identical on every rank)."""
        self.seen = self._signatures()

    def _tensors(self) -> "list[torch.Tensor]":
        return [t for _, t in self.module.named_parameters()] + [t for _, t in self.module.named_buffers()]

    def _signatures(self) -> list:
        return [(id(t), t.data_ptr(), tuple(t.shape), t._version) for t in self._tensors()]

    def __call__(self) -> int:
        """Send the tensors changed since :meth:`mark` from rank 0; returns how many were sent."""
        import torch.distributed as dist

        now, tensors = self._signatures(), self._tensors()
        if len(now) != len(self.seen):  # a module added or dropped a tensor: send them all
            changed = [1.0] * len(now)
        else:
            changed = [float(a != b) for a, b in zip(now, self.seen)]
        mask = torch.tensor(changed, dtype=torch.float32, device=_comm_device())
        dist.all_reduce(mask, op=dist.ReduceOp.MAX)
        send = [t for t, c in zip(tensors, mask.tolist()) if c]
        got = [t.data if dist.get_rank() == 0 else torch.empty_like(t) for t in send]
        work = [dist.broadcast(g, src=0, async_op=True) for g in got]
        for w in work:
            w.wait()
        if dist.get_rank():
            with torch.no_grad():  # copy_ bumps the version counters, so caches keyed on them (the coarse occupancy) see the change
                for t, g in zip(send, got):
                    t.copy_(g)
        self.mark()
        return len(send)
