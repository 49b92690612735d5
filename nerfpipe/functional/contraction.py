"""Scene contraction and disparity-spaced samples for unbounded scenes (pure tensor functions).

The object region is a box; everything outside it (floor, walls, sky) is mapped into a bounded
shell so that a coarse grid can hold it, as in mip-NeRF 360 and MERF:

* the box is mapped to the cube ``[-1, 1]^3`` (per axis);
* a point ``x`` outside it goes to ``x / |x|_inf * (2 - 1 / |x|_inf)`` (the L-infinity version of
  mip-NeRF 360's contraction, as MERF and nerfstudio's ``SceneContraction(order=inf)``), so all of
  space fits in ``[-2, 2]^3`` and infinity lies on its surface.

Samples outside the box are spaced uniformly in disparity ``1 / t`` from where the ray leaves the
box to a far distance: about evenly spaced in contracted space, so the far background costs as
many samples as the near one.

Glossary:
    x_box   points in box coordinates: the box is ``[-1, 1]^3``
    s       fraction of the way from the box exit (0) to ``t_far`` (1) in disparity
"""

import torch

from nerfpipe.util.typing import Float, Tensor


def to_box_coordinates(points: Float[Tensor, "*bs 3"], aabb: Float[Tensor, "2 3"]) -> Float[Tensor, "*bs 3"]:
    """World points in coordinates where ``aabb`` is the cube ``[-1, 1]^3``."""
    center = 0.5 * (aabb[0] + aabb[1])
    half = 0.5 * (aabb[1] - aabb[0])
    return (points - center) / half


def contract(x_box: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
    """L-infinity scene contraction: identity in ``[-1, 1]^3``, everything else into ``[-2, 2]^3``.

    Example:
        >>> contract(torch.tensor([[0.5, 0.0, 0.0], [2.0, 1.0, 0.0], [1e9, 0.0, 0.0]])).tolist()
        [[0.5, 0.0, 0.0], [1.5, 0.75, 0.0], [2.0, 0.0, 0.0]]
    """
    norm = x_box.abs().amax(dim=-1, keepdim=True).clamp(min=1e-12)
    outside = norm > 1.0
    scale = torch.where(outside, (2.0 - 1.0 / norm) / norm, torch.ones_like(norm))
    return x_box * scale


def _contract_reference(x_box: Float[Tensor, "num_points 3"]) -> Float[Tensor, "num_points 3"]:
    """Slow reference of :func:`contract`: one point at a time, written as the formula reads."""
    out = []
    for p in x_box:
        n = float(p.abs().max())
        out.append(p.clone() if n <= 1.0 else p / n * (2.0 - 1.0 / n))
    return torch.stack(out) if out else x_box.clone()


def disparity_to_distance(
    t_start: Float[Tensor, "num_rays"], t_far: float, s: "Float[Tensor, 'n'] | Float[Tensor, 'num_rays n']"
) -> Float[Tensor, "num_rays n"]:
    """Distance along each ray of the points a fraction ``s`` of the way from ``t_start`` (0) to ``t_far``
    (1), linearly in disparity ``1 / t``.

    Example:
        >>> disparity_to_distance(torch.tensor([1.0]), 1e9, torch.tensor([0.0, 0.5])).tolist()
        [[1.0, 2.0]]
    """
    inv0 = 1.0 / t_start.clamp(min=1e-6)[:, None]
    inv1 = 1.0 / max(float(t_far), 1e-6)
    return 1.0 / (inv0 * (1.0 - s) + inv1 * s)


def disparity_samples(
    t_start: Float[Tensor, "num_rays"], t_far: float, num_samples: int, jitter: "Float[Tensor, 'num_rays num_samples'] | None" = None
) -> "tuple[Float[Tensor, 'num_rays num_samples'], Float[Tensor, 'num_rays num_samples']]":
    """``num_samples`` intervals per ray from ``t_start`` to ``t_far``, uniform in disparity.

    Args:
        t_start: where each ray's samples begin (> 0).
        t_far: where they end (``> t_start``; e.g. a thousand scene sizes away).
        num_samples: intervals per ray.
        jitter: uniform ``[0, 1)`` position of each sample inside its interval (training, stratified),
            or None (evaluation: midpoints).

    Returns:
        ``(t_samples, deltas)``: the sample positions and the lengths of the intervals, which tile
        ``[t_start, t_far]`` exactly.

    Example:
        >>> t, d = disparity_samples(torch.tensor([1.0]), 1e9, 2)
        >>> [round(v, 3) for v in t[0].tolist()], round(float(d[0, 0]), 3)
        ([1.5, 500000000.0], 1.0)
    """
    s = torch.linspace(0.0, 1.0, num_samples + 1, device=t_start.device, dtype=t_start.dtype)
    t = disparity_to_distance(t_start, t_far, s)
    t_starts, deltas = t[:, :-1], t[:, 1:] - t[:, :-1]
    u = torch.full_like(deltas, 0.5) if jitter is None else jitter
    return t_starts + u * deltas, deltas
