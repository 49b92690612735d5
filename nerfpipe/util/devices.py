"""The ``--device`` a user asks for, resolved and checked before anything runs or is written.

``auto`` (the default of every command, config and stage) is the first CUDA device when torch sees
one, else the CPU. Apple's MPS is never picked by ``auto``: the packed renderer and the occupancy
marching sum optical depths in float64, which MPS does not have (``--device mps`` may still be asked
for; it fails there at the first float64 tensor).

Torch only complains about a device when the first tensor moves there (``RuntimeError: Expected
one of cpu, cuda, ...`` for a typo, ``AssertionError: Torch not compiled with CUDA enabled`` for
a missing GPU), which is after the dataset is loaded and the run folder made; :func:`check_device`
says so first, in one line naming the flag.
"""

import torch

from nerfpipe.util.errors import NerfpipeError

AUTO = "auto"
"""The device name that :func:`check_device` resolves to the best device of this machine."""


def auto_device() -> str:
    """``cuda`` when torch sees a CUDA device, else ``cpu`` (see the module docstring for MPS).

    Example:
        >>> auto_device() in ("cpu", "cuda")
        True
    """
    return "cuda" if torch.cuda.is_available() and torch.cuda.device_count() > 0 else "cpu"


def check_device(device: "str | torch.device", flag: str = "--device") -> str:
    """The device to use for ``device``: ``auto`` resolved (:func:`auto_device`), any other name
    returned as given when torch can use it on this machine, else one line naming ``flag``.

    Example:
        >>> check_device("cpu")
        'cpu'
    """
    name = str(device)
    if name == AUTO:
        return auto_device()
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError, TypeError) as exc:
        raise NerfpipeError(f"{flag} '{name}' is not a torch device (auto, cpu, cuda, cuda:1, mps)") from exc
    if dev.type == "cpu":
        return name
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise NerfpipeError(f"{flag} '{name}': no CUDA device is available on this machine (use auto or cpu)")
        if dev.index is not None and dev.index >= count:
            raise NerfpipeError(f"{flag} '{name}': this machine has {count} CUDA device(s), numbered from 0")
        return name
    if dev.type == "mps":
        if not torch.backends.mps.is_available():
            raise NerfpipeError(f"{flag} '{name}': MPS is not available on this machine (use auto or cpu)")
        return name
    raise NerfpipeError(f"{flag} '{name}': nerfpipe runs on cpu, cuda or mps, not {dev.type}")


def describe(device: "str | torch.device") -> str:
    """One line naming a resolved device, as the commands print it at start.

    Example:
        >>> describe("cpu").startswith("device: cpu")
        True
    """
    dev = torch.device(device)
    if dev.type == "cuda":
        index = dev.index if dev.index is not None else torch.cuda.current_device()
        return f"device: {dev} ({torch.cuda.get_device_name(index)})"
    if dev.type == "cpu":  # how OpenMP's threads wait where the program chose it (1.8x a step's time on an idle machine)
        from nerfpipe.util import runtime

        waits = f", OpenMP waits: {runtime.OMP_WAIT}" if runtime.OMP_WAIT in ("spin", "passive", "user") else ""
        return f"device: cpu ({torch.get_num_threads()} threads{waits})"
    return f"device: {dev}"


def announce(device: "str | torch.device", flag: str = "--device", file=None) -> str:
    """:func:`check_device`, and the resolved device printed as a command's first line of output (stdout by
    default: stderr stays the one line of an error, and a command whose stdout is data passes ``sys.stderr``)."""
    import sys

    resolved = check_device(device, flag)
    print(describe(resolved), file=file or sys.stdout, flush=True)
    return resolved
