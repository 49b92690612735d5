"""torch's process-wide state, used for one block and handed back as it was found.

A library must leave its host process as it found it (a pipeline that imports nerfpipe keeps its
own seed, random stream and thread count). Two pieces of torch state have no local form:

* **module initialisers** (``nn.Linear``, ``nn.init.*``) draw from torch's global CPU stream and
  take no generator. :func:`seeded_init` seeds that stream for the call that builds a model and
  puts the caller's state back after it. What the call leaves in the stream is returned: it is
  where the run's own stream continues (:func:`continued_generator`), so a run draws the very
  numbers it drew when it seeded the global stream itself (same PSNR at the same steps);
* **the thread count** (``torch.set_num_threads``): :func:`torch_threads` sets it for a block.

Neither is safe against another thread changing the same state at the same time (torch offers no
per-thread stream or thread count); one training per process at a time is the supported use.
"""

import contextlib
from collections.abc import Callable, Iterator
from typing import TypeVar

import torch

T = TypeVar("T")


def seeded_init(build: "Callable[[], T]", seed: int) -> "tuple[T, torch.Tensor]":
    """``build()`` with torch's global CPU stream seeded with ``seed``, then the caller's stream back.

    Returns what ``build`` returned and the stream's state as ``build`` left it.

    Example:
        >>> before = torch.get_rng_state()
        >>> layer, after = seeded_init(lambda: torch.nn.Linear(2, 2), 0)
        >>> bool(torch.equal(torch.get_rng_state(), before)), bool(torch.equal(after, before))
        (True, False)
    """
    saved = torch.get_rng_state()
    try:
        torch.default_generator.manual_seed(seed)  # the CPU stream only: CUDA streams are not touched
        return build(), torch.get_rng_state()
    finally:
        torch.set_rng_state(saved)


def continued_generator(device: "str | torch.device", seed: int, cpu_state: torch.Tensor) -> torch.Generator:
    """A generator on ``device`` for a run's random draws after :func:`seeded_init`.

    On the CPU it continues the global stream from ``cpu_state`` (the numbers a run drew from
    ``torch.manual_seed(seed)`` before it kept a stream of its own); on another device it is that
    device's stream from ``seed``, as ``torch.manual_seed`` seeded it.
    """
    device = torch.device(device)
    gen = torch.Generator(device=device)
    if device.type == "cpu":
        gen.set_state(cpu_state)
    else:
        gen.manual_seed(seed)
    return gen


@contextlib.contextmanager
def torch_threads(num_threads: "int | None") -> Iterator[None]:
    """torch's CPU thread count set to ``num_threads`` for the block (None: left as it is), then restored."""
    before = torch.get_num_threads()
    if num_threads:
        torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)
