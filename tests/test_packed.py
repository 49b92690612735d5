"""Packed (ragged) volume rendering against the dense renderer on padded rays, values and gradients."""

import pytest
import torch

from nerfpipe.functional.packed import (
    accumulate_packed,
    composite_packed,
    distortion_loss_packed,
    exclusive_segment_cumsum,
    render_weights_packed,
)
from nerfpipe.functional.volrend import composite, render_weights
from reference import distortion_loop


def ragged(dtype, lengths=(5, 0, 1, 7, 3), seed=0):
    """Random packed samples of rays with ``lengths`` samples, and the same rays zero-padded."""
    g = torch.Generator().manual_seed(seed)
    n = sum(lengths)
    sigmas = torch.rand(n, generator=g, dtype=dtype) * 4
    deltas = torch.rand(n, generator=g, dtype=dtype) * 0.5
    ray_indices = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths))
    smax = max(lengths)
    pos = torch.cat([torch.arange(k) for k in lengths]).long()
    return sigmas, deltas, ray_indices, pos, smax


def pad(values, ray_indices, pos, num_rays, smax):
    out = torch.zeros(num_rays, smax, *values.shape[1:], dtype=values.dtype)
    out[ray_indices, pos] = values
    return out


def test_weights_match_dense_padded(dtype, tol, device):
    sigmas, deltas, ri, pos, smax = ragged(dtype)
    w, t = render_weights_packed(sigmas.to(device), deltas.to(device), ri.to(device))
    w, t = w.cpu(), t.cpu()
    wd, td = render_weights(pad(sigmas, ri, pos, 5, smax), pad(deltas, ri, pos, 5, smax))
    torch.testing.assert_close(w, wd[ri, pos], **tol(dtype))
    torch.testing.assert_close(t, td[ri, pos], **tol(dtype))


def test_gradients_match_dense_padded(dtype, tol, device):
    sigmas, deltas, ri, pos, smax = ragged(dtype, seed=1)
    coef = torch.randn(len(sigmas), dtype=dtype)
    s1 = sigmas.clone().to(device).requires_grad_()
    w, _ = render_weights_packed(s1, deltas.to(device), ri.to(device))
    (w * coef.to(device)).sum().backward()
    s2 = pad(sigmas, ri, pos, 5, smax).requires_grad_()
    wd, _ = render_weights(s2, pad(deltas, ri, pos, 5, smax))
    (wd * pad(coef, ri, pos, 5, smax)).sum().backward()
    torch.testing.assert_close(s1.grad.cpu(), s2.grad[ri, pos], **tol(dtype))


def test_gradcheck_float64():
    sigmas, deltas, ri, _, _ = ragged(torch.float64, lengths=(3, 2, 4), seed=2)
    fn = lambda s, d: render_weights_packed(s, d, ri)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (sigmas.requires_grad_(), deltas.requires_grad_()))


def test_long_batches_keep_per_ray_accuracy():
    """A global float32 cumsum over millions of samples would lose the per-ray sums; ours does not."""
    n_rays, per = 20000, 100
    thick = torch.full((n_rays * per,), 0.05)
    ri = torch.arange(n_rays).repeat_interleave(per)
    excl = exclusive_segment_cumsum(thick, ri).view(n_rays, per)
    expected = torch.arange(per, dtype=torch.float64) * 0.05
    torch.testing.assert_close(excl[-1].double(), expected, rtol=1e-5, atol=1e-6)


def test_composite_matches_dense(tol):
    dtype = torch.float64
    sigmas, deltas, ri, pos, smax = ragged(dtype, seed=3)
    rgbs = torch.rand(len(sigmas), 3, dtype=dtype)
    t_mids = torch.rand(len(sigmas), dtype=dtype) * 5
    bg = torch.rand(5, 3, dtype=dtype)
    w, _ = render_weights_packed(sigmas, deltas, ri)
    rgb, depth, acc = composite_packed(w, rgbs, t_mids, ri, bg)
    wd, _ = render_weights(pad(sigmas, ri, pos, 5, smax), pad(deltas, ri, pos, 5, smax))
    rgb_d, depth_d, acc_d = composite(wd, pad(rgbs, ri, pos, 5, smax), pad(t_mids, ri, pos, 5, smax), bg)
    for a, b in ((rgb, rgb_d), (depth, depth_d), (acc, acc_d)):
        torch.testing.assert_close(a, b, **tol(dtype))
    torch.testing.assert_close(rgb[1], bg[1])  # a ray without samples shows the background
    assert acc[1] == 0


def test_accumulate_counts_per_ray():
    ri = torch.tensor([0, 0, 2, 2, 2])
    out = accumulate_packed(torch.ones(5, 1), ri, 4)
    assert out[:, 0].tolist() == [2.0, 0.0, 3.0, 0.0]


def test_distortion_matches_double_sum(tol):
    dtype = torch.float64
    lengths = (4, 1, 6)
    g = torch.Generator().manual_seed(4)
    n = sum(lengths)
    w = torch.rand(n, generator=g, dtype=dtype)
    edges = [torch.sort(torch.rand(k + 1, generator=g, dtype=dtype) * 3).values for k in lengths]
    t0 = torch.cat([e[:-1] for e in edges])
    t1 = torch.cat([e[1:] for e in edges])
    ri = torch.repeat_interleave(torch.arange(3), torch.tensor(lengths))
    out = distortion_loss_packed(w, t0, t1, ri, 3)
    ref = torch.stack([distortion_loop(w[ri == r], t0[ri == r], t1[ri == r]) for r in range(3)])
    torch.testing.assert_close(out, ref, **tol(dtype))


@pytest.mark.parametrize("sigma", [0.0, 1e10])
def test_extreme_densities_stay_finite(sigma):
    s = torch.full((6,), sigma, requires_grad=True)
    w, t = render_weights_packed(s, torch.ones(6), torch.tensor([0, 0, 0, 1, 1, 1]))
    w.sum().backward()
    assert torch.isfinite(w).all() and torch.isfinite(s.grad).all()
    assert torch.allclose(w.view(2, 3).sum(-1), torch.full((2,), 0.0 if sigma == 0 else 1.0))


def test_quantile_depth_matches_a_fine_scan(device):
    """The median depth equals where a brute-force scan of the piecewise-linear opacity crosses 0.5 (per ray,
    loop over a fine grid of distances); rays that never reach it are NaN; a thin fog in front does not move it."""
    from nerfpipe.functional.packed import quantile_depth_packed

    g = torch.Generator().manual_seed(3)
    lengths = (6, 0, 3, 9)
    w = torch.rand(sum(lengths), generator=g, dtype=torch.float64) * 0.3
    edges = [torch.sort(torch.rand(k + 1, generator=g, dtype=torch.float64) * 4).values for k in lengths]
    t0, t1 = torch.cat([e[:-1] for e in edges]), torch.cat([e[1:] for e in edges])
    ri = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths))
    out = quantile_depth_packed(w.to(device), t0.to(device), t1.to(device), ri.to(device), len(lengths)).cpu()
    for r in range(len(lengths)):
        wr, a, b = w[ri == r], t0[ri == r], t1[ri == r]
        if float(wr.sum()) < 0.5:
            assert torch.isnan(out[r])
            continue
        ts = torch.linspace(0, 4, 40001, dtype=torch.float64)
        opacity = sum(wi * ((ts - ai) / (bi - ai)).clamp(0, 1) for wi, ai, bi in zip(wr, a, b))
        assert abs(float(out[r]) - float(ts[int(torch.nonzero(opacity >= 0.5)[0])])) < 2e-4
    fog = torch.tensor([0.02] * 10 + [0.8]), torch.arange(11.0), torch.arange(11.0) + 1  # fog, then a surface in [10, 11]
    expected = (fog[0] * (fog[1] + 0.5)).sum() / fog[0].sum()
    median = quantile_depth_packed(*fog, torch.zeros(11, dtype=torch.long), 1)
    assert abs(float(median) - 10.375) < 1e-5 and float(expected) < 9.6  # the fog pulls the mean out of the surface, not the median


@pytest.mark.parametrize("capacity", [0, 5, 300, 2000])
def test_pack_static_is_nonzero_in_slots_known_beforehand(capacity, device):
    from nerfpipe.functional.packed import pack_static

    mask = torch.rand(1500, generator=torch.Generator().manual_seed(capacity)).to(device) < 0.3
    ref = mask.nonzero()[:, 0]
    pos, count, pad = pack_static(mask, capacity, fill=7)
    assert pos.shape == pad.shape == (capacity,) and int(count) == len(ref)
    n = min(capacity, len(ref))
    assert torch.equal(pos[:n], ref[:n]) and (pos[n:] == 7).all()
    assert torch.equal(pad, torch.arange(capacity, device=device) >= len(ref))
