"""Op ``composite`` (nerf/composite.py): the fused forward and analytic backward against the
torch twin (volrend's packed functions under autograd), gradchecked in float64, and the
same numbers as the unfused path on a real ray layout (empty rays, slots of no ray)."""

from __future__ import annotations

import pytest
import torch

from plenoctree.nerf.composite import _composite_torch, composite_rays
from plenoctree.nerf.volrend import distortion


def _batch(seed: int, n_rays: int = 40, max_len: int = 30, spare: int = 7,
           dtype=torch.float32):
    """Packed samples of ``n_rays`` rays (some empty, some opaque), then ``spare`` slots of no
    ray; ``offsets [R + 1]``."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, max_len, (n_rays,), generator=g)
    counts[::7] = 0
    offsets = torch.zeros(n_rays + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(counts, 0)
    m = int(offsets[-1]) + spare
    sigma = torch.rand(m, generator=g, dtype=dtype) * 40.0
    sigma[torch.rand(m, generator=g) < 0.3] = 0.0
    sigma[5] = 3e3                                   # an opaque sample: T ~ 0 behind it
    color = torch.rand(m, 3, generator=g, dtype=dtype)
    t = torch.empty(m, dtype=dtype)
    for r in range(n_rays):
        a, b = int(offsets[r]), int(offsets[r + 1])
        t[a:b] = torch.sort(torch.rand(b - a, generator=g, dtype=dtype) * 4.0).values
    t[int(offsets[-1]):] = 0.5
    return sigma, color, t, offsets


def _grads(backend: str, sigma, color, t, offsets, step, up, dist=True):
    s = sigma.detach().clone().requires_grad_(True)
    c = color.detach().clone().requires_grad_(True)
    r = composite_rays(s, c, t, offsets, step, distortion=dist, backend=backend)
    out = torch.cat([r["rgb"], r["acc"][:, None], r["dsum"][:, None],
                     r["distortion"][:, None]], 1)
    (out * up).sum().backward()
    return out.detach(), s.grad, c.grad


@pytest.mark.parametrize("seed", [0, 1])
def test_numba_composite_matches_the_twin_forward_and_backward(seed):
    sigma, color, t, offsets = _batch(seed)
    up = torch.randn(offsets.shape[0] - 1, 6, generator=torch.Generator().manual_seed(9))
    a = _grads("numba", sigma, color, t, offsets, 0.02, up)
    b = _grads("torch", sigma, color, t, offsets, 0.02, up)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, atol=2e-5, rtol=1e-5)
    m = int(offsets[-1])
    assert not a[1][m:].any() and not a[2][m:].any()      # slots of no ray: no gradient


def test_composite_distortion_is_the_dense_definition():
    sigma, color, t, offsets = _batch(3, n_rays=6, max_len=12, spare=0, dtype=torch.float64)
    r = composite_rays(sigma, color, t, offsets, 0.05, distortion=True, backend="numba")
    for k in range(6):
        a, b = int(offsets[k]), int(offsets[k + 1])
        tau = sigma[a:b] * 0.05
        trans = torch.exp(-(torch.cumsum(tau, 0) - tau))
        w = trans * (1 - torch.exp(-tau))
        ref = distortion(w[None], t[a:b][None], 0.05)[0]
        assert abs(float(r["distortion"][k]) - float(ref)) < 1e-5 * (1 + abs(float(ref)))


def test_numba_composite_gradcheck():
    """The analytic backward of the numba kernels against finite differences (float64
    inputs; the kernels accumulate in float64 and round the outputs to float32, hence the
    loose tolerance)."""
    sigma, color, t, offsets = _batch(4, n_rays=5, max_len=8, spare=2, dtype=torch.float64)
    sigma = sigma.clamp(max=30.0)
    up = torch.randn(5, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(2))

    def f(s, c):
        r = composite_rays(s, c, t, offsets, 0.05, distortion=True, backend="numba")
        out = torch.cat([r["rgb"], r["acc"][:, None], r["dsum"][:, None],
                         r["distortion"][:, None]], 1).double()
        return (out * up).sum()

    s = sigma.clone().requires_grad_(True)
    c = color.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (s, c), eps=1e-3, atol=2e-3, rtol=2e-3)


def test_composite_without_distortion_and_the_twin_layout():
    """``distortion=False`` leaves the loss out (and its gradient); the twin's handling of
    slots outside ``offsets`` equals a twin run on the trimmed buffers."""
    sigma, color, t, offsets = _batch(5)
    r = composite_rays(sigma, color, t, offsets, 0.02, backend="numba")
    assert "distortion" not in r
    m = int(offsets[-1])
    full = _composite_torch(sigma, color, t, offsets, 0.02, False)
    trimmed = _composite_torch(sigma[:m], color[:m], t[:m], offsets, 0.02, False)
    torch.testing.assert_close(full, trimmed)
    torch.testing.assert_close(r["rgb"], full[:, :3], atol=2e-6, rtol=1e-5)
