"""Volume rendering: the course's check, a per-ray loop reference, gradients and extremes."""

import pytest
import torch

import nerfpipe
from nerfpipe.functional.volrend import accumulate, binary_entropy, composite, insert_layer, render_weights, volrend
from reference import render_weights_loop, volrend_loop

# The expected output printed on the CS180 project-4 page (part 2.5) for this exact input.
COURSE_EXPECTED = [
    [0.5006, 0.3728, 0.4728],
    [0.4322, 0.3559, 0.4134],
    [0.4027, 0.4394, 0.4610],
    [0.4514, 0.3829, 0.4196],
    [0.4002, 0.4599, 0.4103],
    [0.4471, 0.4044, 0.4069],
    [0.4285, 0.4072, 0.3777],
    [0.4152, 0.4190, 0.4361],
    [0.4051, 0.3651, 0.3969],
    [0.3253, 0.3587, 0.4215],
]


def course_inputs():
    torch.manual_seed(42)
    return torch.rand((10, 64, 1)), torch.rand((10, 64, 3)), (6.0 - 2.0) / 64


def test_course_reference_check():
    sigmas, rgbs, step = course_inputs()
    out = volrend(sigmas, rgbs, step)
    assert out.shape == (10, 3)
    assert torch.allclose(out, torch.tensor(COURSE_EXPECTED), rtol=1e-4, atol=1e-4)
    slow = volrend_loop(sigmas[..., 0].double(), rgbs.double(), torch.full((10, 64), step, dtype=torch.float64))
    assert torch.allclose(out.double(), slow, atol=1e-6)


def test_volrend_step_forms_agree():
    sigmas, rgbs, step = course_inputs()
    ref = volrend(sigmas, rgbs, step)
    assert torch.allclose(volrend(sigmas, rgbs, torch.full((10, 64, 1), step)), ref)
    assert torch.allclose(volrend(sigmas, rgbs, torch.full((10, 64), step)), ref)


def random_inputs(shape, s=16, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    sig = torch.rand((*shape, s), generator=g, dtype=dtype) * 5
    sig[torch.rand(sig.shape, generator=g) < 0.3] = 0.0
    delta = torch.rand((*shape, s), generator=g, dtype=dtype) * 0.3
    rgb = torch.rand((*shape, s, 3), generator=g, dtype=dtype)
    return sig, delta, rgb


@pytest.mark.parametrize("shape", [(), (1,), (2, 3)])
def test_weights_match_loop(shape, dtype, tol):
    sig, delta, rgb = random_inputs(shape, dtype=dtype)
    w, t = render_weights(sig, delta)
    assert w.shape == sig.shape and t.shape == sig.shape and w.dtype == dtype
    w_ref, t_ref = render_weights_loop(sig.reshape(-1, 16).double(), delta.reshape(-1, 16).double())
    torch.testing.assert_close(w.reshape(-1, 16).double(), w_ref, **tol(dtype))
    torch.testing.assert_close(t.reshape(-1, 16).double(), t_ref, **tol(dtype))
    c_ref = volrend_loop(sig.reshape(-1, 16).double(), rgb.reshape(-1, 16, 3).double(), delta.reshape(-1, 16).double())
    torch.testing.assert_close(accumulate(w, rgb).reshape(-1, 3).double(), c_ref, **tol(dtype))


def test_gradcheck_float64():
    sig, delta, rgb = random_inputs((3,), s=8)
    sig = (sig + 0.1).requires_grad_()  # away from the clamp's kink at 0
    delta = (delta + 0.05).requires_grad_()
    rgb = rgb.requires_grad_()
    assert torch.autograd.gradcheck(lambda s, d: render_weights(s, d)[0], (sig, delta))
    assert torch.autograd.gradcheck(lambda s, c, d: volrend(s[..., None], c, d), (sig, rgb, delta))


def test_composite_background_depth_acc():
    sig, delta, rgb = random_inputs((4,))
    t = torch.cumsum(delta, -1)
    w, _ = render_weights(sig, delta)
    bg = torch.tensor([0.2, 0.5, 1.0], dtype=torch.float64)
    out, depth, acc = composite(w, rgb, t, bg)
    torch.testing.assert_close(out, accumulate(w, rgb) + (1 - w.sum(-1))[:, None] * bg)
    torch.testing.assert_close(depth, (w * t).sum(-1))
    assert torch.all((acc >= 0) & (acc <= 1))
    empty = composite(*[torch.zeros_like(x) for x in (w,)], rgb, t, bg)
    torch.testing.assert_close(empty[0], bg.expand(4, 3))
    assert torch.all(empty[2] == 0)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_extremes_finite_values_and_grads(dtype):
    big = min(1e10, torch.finfo(dtype).max)
    sig_vals = torch.tensor([0.0, 1.0, big], dtype=dtype)
    delta_vals = torch.tensor([0.0, 0.01, 1e3], dtype=dtype)
    sig = sig_vals[torch.tensor([[0, 2, 1, 2], [2, 2, 0, 0], [1, 1, 1, 1], [0, 0, 0, 0]])].requires_grad_()
    delta = delta_vals[torch.tensor([[2, 0, 1, 2], [0, 2, 2, 1], [2, 2, 2, 2], [2, 2, 2, 2]])].requires_grad_()
    rgb = torch.full((4, 4, 3), 0.5, dtype=dtype, requires_grad=True)
    w, t = render_weights(sig, delta)
    out, depth, acc = composite(w, rgb, torch.cumsum(delta.detach().float(), -1).to(dtype), torch.ones(3, dtype=dtype))
    # d(depth)/d(sigma) is t * delta ~ 4e6 here: a true value beyond float16's range, so half
    # precision checks the colour and opacity gradients only
    half = dtype in (torch.float16, torch.bfloat16)
    (out.sum() + acc.sum() + (0 if half else depth.sum())).backward()
    for x in (w, t, out, depth, acc, sig.grad, delta.grad, rgb.grad):
        assert torch.isfinite(x.float()).all()
    # row 0: sigma 0 and delta 0 are transparent, sigma*delta 0.01 stops 1%, the last sample is opaque
    assert float(w[0, :2].abs().sum()) == 0.0
    assert float(w[0, 3]) == pytest.approx(torch.exp(torch.tensor(-0.01)).item(), rel=1e-2)
    assert float(acc[0]) == pytest.approx(1.0, rel=1e-2)
    assert float(acc[3]) == 0.0  # zero density: nothing accumulates


def test_public_names_resolve():
    for name in nerfpipe.__all__:
        assert getattr(nerfpipe, name) is not None, name
    assert nerfpipe.volrend is volrend


def test_binary_entropy_values_and_finite_gradients():
    acc = torch.tensor([0.0, 0.2, 0.5, 0.9, 1.0], requires_grad=True)
    h = binary_entropy(acc)
    a = acc.detach().clamp(1e-3, 1 - 1e-3).double()
    torch.testing.assert_close(h.double(), -(a * a.log() + (1 - a) * (1 - a).log()), rtol=1e-5, atol=1e-6)
    assert float(h[2]) == pytest.approx(torch.log(torch.tensor(2.0)).item(), rel=1e-6)  # a veil costs most
    assert float(h[0]) < 0.01 and float(h[-1]) < 0.01  # a ray that passes or stops costs (almost) nothing
    h.sum().backward()
    assert torch.isfinite(acc.grad).all()
    assert acc.grad[1] > 0 > acc.grad[3]  # the gradient pushes a thin veil to clear and a thick one to close


def _layered_loop(alphas, t, layer_t, layer_alpha):
    """The slow, obvious reference of ``insert_layer``: the layer as one more sample in depth order, weights by a loop."""
    weights, layer_weights = torch.zeros_like(alphas), torch.zeros_like(layer_t)
    for r in range(alphas.shape[0]):
        items = sorted([(float(t[r, i]), i) for i in range(alphas.shape[1])] + [(float(layer_t[r]), -1)],
                       key=lambda x: (x[0], x[1] != -1))  # a sample at the layer's distance lies behind it
        trans = torch.ones((), dtype=alphas.dtype)
        for _, i in items:
            a = layer_alpha[r] if i == -1 else alphas[r, i]
            if i == -1:
                layer_weights[r] = trans * a
            else:
                weights[r, i] = trans * a
            trans = trans * (1 - a)
    return weights, layer_weights


def test_insert_layer_matches_a_sorted_loop_values_and_gradients(device, tol):
    """A layer among a field's samples (the support plane's texture among those of the field behind the box) composites
    as one more sample at its depth: values against a per-ray loop, gradients against the loop's in float64."""
    g = torch.Generator().manual_seed(3)
    alphas = torch.rand(6, 9, generator=g, dtype=torch.float64) * 0.6
    t = torch.sort(torch.rand(6, 9, generator=g, dtype=torch.float64) * 10, dim=-1).values
    layer_t = torch.tensor([-1.0, 0.0, 2.0, 5.0, 11.0, 4.0], dtype=torch.float64)  # in front of all, among, behind all
    layer_t[1] = t[1, 3]  # exactly at a sample: that sample lies behind the layer
    layer_alpha = torch.rand(6, generator=g, dtype=torch.float64)
    layer_alpha[5] = 0.0  # no layer: the field's own weights
    trans = torch.cumprod(torch.cat([torch.ones(6, 1, dtype=torch.float64), 1 - alphas[:, :-1]], -1), -1)
    weights = alphas * trans
    ref_w, ref_l = _layered_loop(alphas, t, layer_t, layer_alpha)
    for dtype in (torch.float64, torch.float32):
        w, lw = insert_layer(*(x.to(device, dtype) for x in (weights, t, layer_t, layer_alpha)))
        torch.testing.assert_close(w.double().cpu(), ref_w, **tol(dtype))
        torch.testing.assert_close(lw.double().cpu(), ref_l, **tol(dtype))
    torch.testing.assert_close(insert_layer(weights, t, layer_t, layer_alpha)[0][5], weights[5])
    assert torch.all(w.sum(-1) + lw <= 1 + 1e-6)
    a, la = alphas.clone().requires_grad_(), layer_alpha.clone().requires_grad_()
    fast = lambda a, la: insert_layer(a * torch.cumprod(torch.cat([torch.ones(6, 1, dtype=a.dtype), 1 - a[:, :-1]], -1), -1), t, layer_t, la)
    weights_out = torch.rand(6, 9, dtype=torch.float64, generator=g)
    gf = torch.autograd.grad((fast(a, la)[0] * weights_out).sum() + fast(a, la)[1].sum(), (a, la))
    gr = torch.autograd.grad((_layered_loop(a, t, layer_t, la)[0] * weights_out).sum() + _layered_loop(a, t, layer_t, la)[1].sum(), (a, la))
    for x, y in zip(gf, gr):
        torch.testing.assert_close(x, y)
