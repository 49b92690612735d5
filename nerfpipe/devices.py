"""The ``--device`` a user asks for, checked before anything runs or is written.

Torch only complains about a device when the first tensor moves there (``RuntimeError: Expected
one of cpu, cuda, ...`` for a typo, ``AssertionError: Torch not compiled with CUDA enabled`` for
a missing GPU), which is after the dataset is loaded and the run folder made.
"""

import torch

from nerfpipe.errors import NerfpipeError


def check_device(device: "str | torch.device", flag: str = "--device") -> str:
    """``device`` when torch can use it on this machine, else one line naming ``flag``.

    Example:
        >>> check_device("cpu")
        'cpu'
    """
    name = str(device)
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError, TypeError) as exc:
        raise NerfpipeError(f"{flag} '{name}' is not a torch device (cpu, cuda, cuda:1, mps)") from exc
    if dev.type == "cpu":
        return name
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise NerfpipeError(f"{flag} '{name}': no CUDA device is available on this machine (use cpu)")
        if dev.index is not None and dev.index >= count:
            raise NerfpipeError(f"{flag} '{name}': this machine has {count} CUDA device(s), numbered from 0")
        return name
    if dev.type == "mps":
        if not torch.backends.mps.is_available():
            raise NerfpipeError(f"{flag} '{name}': MPS is not available on this machine (use cpu)")
        return name
    raise NerfpipeError(f"{flag} '{name}': nerfpipe runs on cpu, cuda or mps, not {dev.type}")
