"""Volume rendering pieces, eq. (1)-(2): closed forms, packed vs dense, gradients."""

from __future__ import annotations

import math

import torch

from plenoctree.nerf.volrend import (composite, composite_packed, deltas_from_t, distortion,
                                     distortion_packed, render_weights, render_weights_packed)


def test_constant_density_closed_form():
    sigma = torch.full((2, 50), 0.7)
    deltas = torch.full((2, 50), 0.1)
    w, trans = render_weights(sigma, deltas)
    torch.testing.assert_close(w.sum(-1), torch.full((2,), 1 - math.exp(-0.7 * 5.0)))
    torch.testing.assert_close(trans[:, 10], torch.full((2,), math.exp(-0.7)))
    rgb = torch.rand(2, 50, 3)
    rgb[:] = torch.tensor([0.2, 0.4, 0.6])
    t = torch.linspace(0, 5, 50).expand(2, 50)
    c, acc, depth = composite(w, rgb, t, torch.ones(3))
    a = 1 - math.exp(-3.5)
    torch.testing.assert_close(c[0], torch.tensor([0.2, 0.4, 0.6]) * a + (1 - a))
    assert (depth > 0).all() and (depth < 5).all()


def test_deltas_last_is_infinite():
    d = deltas_from_t(torch.tensor([[1.0, 1.5, 3.0]]))
    torch.testing.assert_close(d, torch.tensor([[0.5, 1.5, 1e10]]))


def _packed_case(seed=0):
    g = torch.Generator().manual_seed(seed)
    counts = torch.tensor([3, 0, 5, 1, 7])
    ray_idx = torch.repeat_interleave(torch.arange(5), counts)
    offsets = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)])
    sigma = torch.rand(int(counts.sum()), generator=g, dtype=torch.float64) * 5
    return counts, ray_idx, offsets, sigma


def test_packed_matches_dense():
    counts, ray_idx, offsets, sigma = _packed_case()
    w, trans = render_weights_packed(sigma, 0.2, ray_idx, offsets)
    for r in range(5):
        sl = slice(int(offsets[r]), int(offsets[r + 1]))
        if counts[r] == 0:
            continue
        wd, td = render_weights(sigma[sl][None], torch.full((1, int(counts[r])), 0.2,
                                                             dtype=torch.float64))
        torch.testing.assert_close(w[sl].double(), wd[0], atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(trans[sl].double(), td[0], atol=1e-6, rtol=1e-5)
    rgb = torch.rand(len(sigma), 3, dtype=torch.float64)
    out = composite_packed(w.double(), rgb, ray_idx, 5)
    assert out.shape == (5, 3) and (out[1] == 0).all()
    torch.testing.assert_close(out[3], w[offsets[3]].double() * rgb[offsets[3]])


def test_packed_gradcheck_float64():
    counts, ray_idx, offsets, sigma = _packed_case(1)
    rgb = torch.rand(len(sigma), 3, dtype=torch.float64, requires_grad=True)
    sigma = sigma.clone().requires_grad_()

    def f(s, c):
        tau = s * 0.3
        excl = torch.cumsum(tau, 0) - tau
        base = excl[offsets[:-1].clamp(max=len(s) - 1)]
        w = torch.exp(-(excl - base[ray_idx])) * (1 - torch.exp(-tau))
        return composite_packed(w, c, ray_idx, 5)

    torch.autograd.gradcheck(f, (sigma, rgb))
    # the float32 library function has the same gradients as this float64 spec
    s32 = sigma.detach().float().requires_grad_()
    w, _ = render_weights_packed(s32, 0.3, ray_idx, offsets)
    out = composite_packed(w, rgb.detach().float(), ray_idx, 5)
    g32, = torch.autograd.grad(out.sum(), s32)
    g64, = torch.autograd.grad(f(sigma, rgb.detach()).sum(), sigma)
    torch.testing.assert_close(g32.double(), g64, atol=1e-5, rtol=1e-4)


def test_dense_gradients_flow():
    sigma = torch.rand(4, 16, requires_grad=True)
    rgb = torch.rand(4, 16, 3, requires_grad=True)
    w, _ = render_weights(sigma, torch.full((4, 16), 0.1))
    c, acc, _ = composite(w, rgb, None, torch.ones(3))
    c.sum().backward()
    assert sigma.grad.abs().sum() > 0 and rgb.grad.abs().sum() > 0


def test_distortion_golden_values():
    # one sample holding all the weight: only the interval term, δ/3
    d = distortion(torch.tensor([[0.0, 1.0, 0.0]]), torch.tensor([[0.0, 1.0, 2.0]]), 0.3)
    torch.testing.assert_close(d, torch.tensor([0.1]))
    # two halves 2 apart: 2 · ¼ · 2 + δ/3 · (¼ + ¼)
    d = distortion(torch.tensor([[0.5, 0.0, 0.5]]), torch.tensor([[0.0, 1.0, 2.0]]), 0.3)
    torch.testing.assert_close(d, torch.tensor([1.0 + 0.05]))


def test_distortion_packed_matches_dense_and_gradchecks():
    counts, ray_idx, offsets, _ = _packed_case(3)
    g = torch.Generator().manual_seed(4)
    m = int(counts.sum())
    w = torch.rand(m, generator=g, dtype=torch.float64, requires_grad=True)
    t = torch.cat([torch.sort(torch.rand(int(c), generator=g, dtype=torch.float64) * 3).values
                   for c in counts])
    packed = distortion_packed(w, t, 0.05, ray_idx, offsets, len(counts))
    for r, c in enumerate(counts.tolist()):
        sl = slice(int(offsets[r]), int(offsets[r + 1]))
        dense = distortion(w[sl][None], t[sl][None], 0.05)[0] if c else torch.zeros((), dtype=w.dtype)
        torch.testing.assert_close(packed[r], dense)
    assert torch.autograd.gradcheck(
        lambda x: distortion_packed(x, t, 0.05, ray_idx, offsets, len(counts)), (w,))
    empty = distortion_packed(torch.zeros(0), torch.zeros(0), 0.1,
                              torch.zeros(0, dtype=torch.int64), torch.zeros(3, dtype=torch.int64), 2)
    assert empty.tolist() == [0.0, 0.0]
