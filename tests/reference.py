"""Slow, obviously-correct references for the vectorised code (STYLE habit 10)."""

import math

import torch


def render_weights_loop(sigmas: torch.Tensor, deltas: torch.Tensor) -> "tuple[torch.Tensor, torch.Tensor]":
    """Per-ray, per-sample Python loop of the volume-rendering weights (flat rays ``[N, S]``)."""
    n, s = sigmas.shape
    weights = torch.zeros(n, s, dtype=sigmas.dtype)
    trans = torch.zeros(n, s, dtype=sigmas.dtype)
    for r in range(n):
        t = torch.ones((), dtype=sigmas.dtype)
        for i in range(s):
            alpha = 1 - torch.exp(-sigmas[r, i] * deltas[r, i])
            trans[r, i] = t
            weights[r, i] = t * alpha
            t = t * (1 - alpha)
    return weights, trans


def volrend_loop(sigmas: torch.Tensor, rgbs: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """``sum_i T_i (1 - exp(-sigma_i delta_i)) c_i`` ray by ray (flat rays ``[N, S]``, ``[N, S, 3]``)."""
    weights, _ = render_weights_loop(sigmas, deltas)
    out = torch.zeros(sigmas.shape[0], 3, dtype=rgbs.dtype)
    for r in range(sigmas.shape[0]):
        for i in range(sigmas.shape[1]):
            out[r] = out[r] + weights[r, i] * rgbs[r, i]
    return out


def pdf_samples_loop(bins: list, weights: list, us: list, eps: float = 1e-5) -> list:
    """Inverse CDF of one ray's piecewise-constant density at quantiles ``us`` (plain Python)."""
    w = [x + eps for x in weights]
    total = sum(w)
    cdf = [0.0]
    for x in w:
        cdf.append(min(cdf[-1] + x / total, 1.0))
    out = []
    for u in us:
        j = max(i for i in range(len(cdf)) if cdf[i] <= u)  # last edge with cdf <= u
        j = min(j, len(w) - 1)
        lo, hi = cdf[j], cdf[j + 1]
        frac = 0.0 if hi <= lo else min(max((u - lo) / (hi - lo), 0.0), 1.0)
        out.append(bins[j] + frac * (bins[j + 1] - bins[j]))
    return out


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return -10 * math.log10(float(torch.mean((a - b) ** 2)))


def trilinear_loop(table: torch.Tensor, res: "tuple[int, int, int]", x01: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation point by point and corner by corner (vertex ``(i, j, k)`` at ``(i, j, k) / (res - 1)``)."""
    out = torch.zeros(x01.shape[0], table.shape[1], dtype=table.dtype)
    for n in range(x01.shape[0]):
        pos = [float(x01[n, a].clamp(0, 1)) * (res[a] - 1) for a in range(3)]
        lo = [min(int(math.floor(p)), res[a] - 2) for a, p in enumerate(pos)]
        for di in (0, 1):
            for dj in (0, 1):
                for dk in (0, 1):
                    w = 1.0
                    for a, d in enumerate((di, dj, dk)):
                        f = pos[a] - lo[a]
                        w *= f if d else 1 - f
                    row = ((lo[0] + di) * res[1] + lo[1] + dj) * res[2] + lo[2] + dk
                    out[n] = out[n] + w * table[row]
    return out


def distortion_loop(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360 distortion loss of one ray by its double sum definition."""
    mids = 0.5 * (t_starts + t_ends)
    total = torch.zeros((), dtype=weights.dtype)
    for i in range(len(weights)):
        for j in range(len(weights)):
            total = total + weights[i] * weights[j] * (mids[i] - mids[j]).abs()
        total = total + weights[i] ** 2 * (t_ends[i] - t_starts[i]) / 3
    return total
