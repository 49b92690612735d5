"""An average of a model's parameters over the late training steps, which the run evaluates and saves.

On a real capture the held-out views stop improving after a few hundred steps while the training views keep
rising: each step fits the sampled rays' noise and the views' disagreements a little, and the parameters wander
around a better solution (colmap_mouse, 7 held-out views: 24.41 / 24.39 / 24.31 dB after 600 / 800 / 1,000 steps).
Their exponential moving average from step 256 on, uniform over its first ``1 / (1 - decay)`` steps (Polyak
averaging with a warm start), scored 24.53 / 24.54 / 24.49 dB at the same steps with a decay of 0.995, and 24.56 /
24.53 after 800 / 1,000 with 0.998 (the default: uniform up to step 756). The average costs one fused
``lerp`` over the parameters per step and a copy of them; it is saved in checkpoints (a resumed run goes on
exactly) and replaces the parameters when training ends, before the final evaluation, the checkpoint and
everything rendered from it; that checkpoint keeps the last step's parameters too, so a run resumed from it to
train further goes on from them (the occupancy grid it refreshed from the average stays).
"""

import torch
from torch import nn

from nerfpipe.functional.gather import move_rows
from nerfpipe.util.typing import Tensor


def moved_rows(p: Tensor, old: Tensor) -> "Tensor | None":
    """Where ``p``'s rows were before it was re-laid out, as its ``row_source`` mark says (``(former row count, index)``,
    set by :meth:`~nerfpipe.fields.grid.DenseGridEncoding.relayout`: new row ``i`` was row ``index[i]``, -1 for a new
    row), when ``old`` has that former shape; else None (nothing kept for ``old``'s rows is valid any more)."""
    mark = getattr(p, "row_source", None)
    if mark is None or mark[0] != old.shape[0] or len(mark[1]) != p.shape[0] or p.shape[1:] != old.shape[1:]:
        return None
    return mark[1]


class ParameterAverage:
    """The running average of ``model``'s parameters from step ``start`` on.

    Args:
        model: whose parameters are averaged (by name; a parameter whose shape changes, a grid resampled to a
            tightened box, restarts the average, but one whose rows were re-laid out keeps theirs).
        start: the first step (the trainer's count after the step) that enters the average.
        decay: weight of the average so far in each update once past the warm start (``1 - decay`` is the new
            step's weight, never less than ``1 / count``: the first ``1 / (1 - decay)`` steps count alike).
        power: where positive, the new step's weight is ``(power + 1) / step`` instead of ``1 - decay`` (never less
            than ``1 / count``, at most 1): a power-function average (as EDM2's), which spans about the last ``1 / (power + 1)``
            of the steps so far however long the run goes.
    """

    def __init__(self, model: nn.Module, start: int, decay: float, power: float = 0.0) -> None:
        self.start, self.decay, self.power = start, decay, power
        self.params = dict(model.named_parameters())
        self.values: "dict[str, Tensor] | None" = None
        self.count = 0
        self.last: "dict[str, Tensor] | None" = None
        """The last step's parameters once :meth:`apply` replaced them (saved, so training can go on from them)."""

    @torch.no_grad()
    def update(self, step: int) -> None:
        """Add the parameters after training step ``step`` (nothing before :attr:`start`)."""
        if step < self.start:
            return
        if self.values is not None:  # a sparse grid level re-laid out: its rows' average moves with them
            for k, v in self.values.items():
                p = self.params[k]
                source = moved_rows(p, v) if v.shape != p.shape else None
                if source is not None:
                    self.values[k] = move_rows(v, source, p.detach())
        if self.values is None or any(v.shape != self.params[k].shape for k, v in self.values.items()):
            self.values, self.count = {k: p.detach().clone() for k, p in self.params.items()}, 1
            return
        self.count += 1
        weight = min(1.0, max((self.power + 1.0) / max(step, 1) if self.power > 0 else 1.0 - self.decay, 1.0 / self.count))
        torch._foreach_lerp_(list(self.values.values()), [p.detach() for p in self.params.values()], weight)

    @torch.no_grad()
    def apply(self) -> bool:
        """Copy the average into the parameters; False (nothing changed) when there is none yet."""
        if self.values is None:
            return False
        self.last = {k: p.detach().clone() for k, p in self.params.items()}
        for k, v in self.values.items():
            self.params[k].copy_(v)
        return True

    def state(self) -> dict:
        out = {"count": self.count, "values": {} if self.values is None else {k: v.detach() for k, v in self.values.items()}}
        return out if self.last is None else {**out, "last": self.last}

    @torch.no_grad()
    def load_state(self, state: dict) -> None:
        """The average of a checkpoint; one written after :meth:`apply` also puts the last step's parameters back into
        the model (whose saved parameters are the average), so that training goes on where it stopped."""
        values = state["values"]
        for part in (values, state.get("last") or {}):
            if part and set(part) != set(self.params):
                raise KeyError(f"the average's parameters {sorted(set(part) ^ set(self.params))[:3]} do not match the model's")
        self.values = {k: values[k].to(self.params[k]).clone() for k in self.params} if values else None
        self.count = int(state["count"]) if values else 0
        for k, v in (state.get("last") or {}).items():
            self.params[k].copy_(v)
        self.last = None
