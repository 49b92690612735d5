"""Stratified and importance sampling along rays, and the RaySamples container."""

import pytest
import torch

from nerfpipe.data.rays import RayBundle
from nerfpipe.data.samples import RaySamples
from nerfpipe.functional.sampling import merge_edges, pdf_samples, stratified_samples
from reference import pdf_samples_loop


@pytest.mark.parametrize("shape", [(), (1,), (2, 3)])
def test_stratified_uniform_at_eval(shape):
    near, far = torch.full(shape, 2.0), torch.full(shape, 6.0)
    edges = stratified_samples(near, far, 64, perturb=False)
    assert edges.shape == (*shape, 65)
    mids = 0.5 * (edges[..., 1:] + edges[..., :-1])
    expected = 2.0 + (torch.arange(64) + 0.5) * (4.0 / 64)
    torch.testing.assert_close(mids, expected.expand(*shape, 64))


def test_stratified_perturbed_stays_in_strata():
    g = torch.Generator().manual_seed(0)
    near, far = torch.full((500,), 2.0), torch.full((500,), 6.0)
    edges = stratified_samples(near, far, 8, perturb=True, generator=g)
    step = 4.0 / 8
    k = torch.arange(9, dtype=torch.float32)
    lo = (2.0 + (k - 0.5) * step).clamp(min=2.0)
    hi = (2.0 + (k + 0.5) * step).clamp(max=6.0)
    assert torch.all(edges >= lo - 1e-6) and torch.all(edges <= hi + 1e-6)
    assert torch.all(edges[:, 0] == 2.0) and torch.all(edges[:, -1] == 6.0)
    assert torch.all(edges[:, 1:] >= edges[:, :-1])
    # the jitter covers each stratum: inner edges spread over most of their range
    spread = edges[:, 1:-1].max(0).values - edges[:, 1:-1].min(0).values
    assert torch.all(spread > 0.9 * step)
    again = stratified_samples(near, far, 8, perturb=True, generator=torch.Generator().manual_seed(0))
    assert torch.equal(edges, again)


def test_pdf_matches_loop_reference():
    g = torch.Generator().manual_seed(1)
    bins = torch.sort(torch.rand(5, 9, generator=g, dtype=torch.float64) * 4 + 2, dim=-1).values
    weights = torch.rand(5, 8, generator=g, dtype=torch.float64)
    weights[0] = 0.0  # empty ray: falls back to uniform
    out = pdf_samples(bins, weights, 16)
    us = [(i + 0.5) / 16 for i in range(16)]
    for r in range(5):
        ref = pdf_samples_loop(bins[r].tolist(), weights[r].tolist(), us)
        torch.testing.assert_close(out[r], torch.tensor(ref, dtype=torch.float64))


def test_pdf_concentrates_on_heavy_bin():
    bins = torch.linspace(2.0, 6.0, 9).expand(3, 9)
    weights = torch.zeros(3, 8)
    weights[:, 5] = 1.0
    out = pdf_samples(bins, weights, 32, perturb=True, generator=torch.Generator().manual_seed(0))
    inside = (out >= bins[0, 5]) & (out <= bins[0, 6])
    assert inside.float().mean() > 0.99
    assert torch.all(out[:, 1:] >= out[:, :-1])
    merged = merge_edges(bins, out)
    assert merged.shape == (3, 41) and torch.all(merged[:, 1:] >= merged[:, :-1])


def test_ray_samples_positions():
    rays = RayBundle(
        origins=torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]),
        directions=torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
        cam_idx=torch.tensor([0, 1]),
        z_scale=torch.ones(2),
    )
    edges = stratified_samples(torch.full((2,), 2.0), torch.full((2,), 6.0), 4)
    s = RaySamples.from_edges(rays, edges)
    assert s.positions.shape == (2, 4, 3) and s.directions.shape == (2, 4, 3)
    torch.testing.assert_close(s.deltas, torch.ones(2, 4))
    torch.testing.assert_close(s.positions[1, :, 0], 1.0 + torch.tensor([2.5, 3.5, 4.5, 5.5]))
    torch.testing.assert_close(s.positions[0, :, 2], torch.tensor([2.5, 3.5, 4.5, 5.5]))
