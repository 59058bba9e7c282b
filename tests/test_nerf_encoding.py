"""Grid and positional encodings: numba kernels against the torch twin, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from plenoctree.errors import ConfigError
from plenoctree.nerf.encoding import (HashGridEncoding, HashGridLayout, PositionalEncoding,
                                      _hashgrid_encode_torch, hashgrid_levels)


def test_levels_layout():
    res, off, hashed = hashgrid_levels(16, 16, 1024, 18)
    assert res[0] == 16 and res[-1] == 1024 and np.all(np.diff(res) > 0)
    sizes = np.diff(off)
    assert np.all(sizes[hashed] == 1 << 18)
    assert np.all(sizes[~hashed] == (res[~hashed] + 1) ** 3)
    assert np.all((res[~hashed] + 1) ** 3 <= 1 << 18) and np.all((res[hashed] + 1) ** 3 > 1 << 18)
    assert not hashed[0] and hashed[-1]
    with pytest.raises(ConfigError):
        hashgrid_levels(4, 32, 16, 18)


def _points(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand((n, 3), generator=g)
    x[:8] = torch.tensor([0.0, 1.0, 0.5])          # faces of the cube
    x[8:16] = torch.tensor([1.0, 1.0, 1.0])
    return x


@pytest.mark.parametrize("n_features", [2, 3])
def test_numba_matches_torch_twin(n_features):
    enc = HashGridEncoding([[-1.0] * 3, [1.0] * 3],
                           HashGridLayout(n_levels=6, n_features=n_features, base_res=4,
                                          max_res=64, log2_table=10), init_scale=1.0)
    assert enc.hashed.any() and (~enc.hashed).any()
    pts = _points(3000) * 2.4 - 1.2                   # some outside the box: clamped
    enc.backend = "numba"
    a = enc(pts)
    enc.backend = "torch"
    b = enc(pts)
    assert a.shape == (3000, 6 * n_features)
    torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-5)
    g = torch.randn_like(a)
    ga, = torch.autograd.grad(a, enc.table, g)
    enc.backend = "numba"
    gb, = torch.autograd.grad(enc(pts), enc.table, g)
    torch.testing.assert_close(ga, gb, atol=2e-5, rtol=1e-4)
    assert (ga != 0).sum() > 100


def test_numba_kernels_do_not_depend_on_the_thread_count():
    """The level loops deal levels out round-robin by thread count; every level still owns its
    output slice and table rows, so one thread and two give the same bits."""
    import numba

    from plenoctree.nerf import _hashgrid_numba as K

    res, off, hashed = hashgrid_levels(7, 4, 80, 9)
    for t in (1, 2, 3, 7, 16):
        assert sorted(K._levels(res, t).tolist()) == list(range(7))
    assert K._levels(res, 2).tolist() == [0, 2, 4, 6, 1, 3, 5]
    rng = np.random.default_rng(3)
    table = rng.standard_normal((int(off[-1]), 2)).astype(np.float32)
    x = rng.random((500, 3)).astype(np.float32)
    x[:4] = [0.0, 1.0, 0.5]
    g = rng.standard_normal((500, 14)).astype(np.float32)
    outs = []
    for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
        prev = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            out = np.empty((500, 14), np.float32)
            K.hashgrid_forward(x, table, res, off, hashed, out)
            grad = np.zeros_like(table)
            K.hashgrid_backward(x, g, res, off, hashed, grad)
        finally:
            numba.set_num_threads(prev)
        outs.append((out, grad))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])


def test_twin_gradcheck_float64():
    res, off, hashed = hashgrid_levels(3, 2, 9, 6)
    assert hashed.any() and (~hashed).any()
    g = torch.Generator().manual_seed(1)
    table = torch.randn((int(off[-1]), 2), dtype=torch.float64, generator=g, requires_grad=True)
    x = (torch.rand((7, 3), dtype=torch.float64, generator=g) * 0.9 + 0.05).requires_grad_()
    torch.autograd.gradcheck(lambda x, t: _hashgrid_encode_torch(x, t, res, off, hashed),
                             (x, table))


def test_grid_interpolates_trilinearly():
    # a dense single-level grid whose table holds a linear function reproduces it exactly
    enc = HashGridEncoding([[0.0] * 3, [1.0] * 3],
                           HashGridLayout(n_levels=1, n_features=1, base_res=4, max_res=4,
                                          log2_table=10))
    r = 4
    ijk = np.stack(np.meshgrid(*[np.arange(r + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    idx = ijk[:, 0] + ijk[:, 1] * (r + 1) + ijk[:, 2] * (r + 1) ** 2
    vals = np.zeros((r + 1) ** 3, np.float32)
    vals[idx] = (ijk @ np.array([1.0, 2.0, -3.0])) / r
    with torch.no_grad():
        enc.table[:, 0] = torch.from_numpy(vals)
    x = torch.rand(500, 3)
    want = x @ torch.tensor([1.0, 2.0, -3.0])
    for backend in ("numba", "torch"):
        enc.backend = backend
        torch.testing.assert_close(enc(x)[:, 0], want, atol=1e-5, rtol=1e-5)


def test_positional_encoding():
    pe = PositionalEncoding(3, 4)
    x = torch.randn(5, 3)
    y = pe(x)
    assert y.shape == (5, pe.out_dim) == (5, 27)
    torch.testing.assert_close(y[:, :3], x)
    torch.testing.assert_close(y[:, 3 + 3 * 2:3 + 3 * 3], torch.sin(4 * x))
    torch.testing.assert_close(y[:, 15 + 3:15 + 6], torch.cos(2 * x))
    assert PositionalEncoding(3, 0)(x).shape == (5, 3)


def test_in_place_gradient_accumulation_matches_autograd():
    enc = HashGridEncoding([[-1.0] * 3, [1.0] * 3],
                           HashGridLayout(n_levels=4, base_res=4, max_res=32, log2_table=9),
                           init_scale=1.0)
    a, b = _points(700, 1) * 2 - 1, _points(500, 2) * 2 - 1
    ga, gb = torch.randn(700, 8), torch.randn(500, 8)
    (enc(a) * ga).sum().backward()
    (enc(b) * gb).sum().backward()
    want = enc.table.grad.clone()
    enc.table.grad = None
    enc.grad_in_place = True
    loss = (enc(a) * ga).sum() + (enc(b) * gb).sum()
    loss.backward()
    torch.testing.assert_close(enc.table.grad, want, atol=1e-5, rtol=1e-5)
    with torch.no_grad():                       # no side effects outside of backward
        enc(a)
    torch.testing.assert_close(enc.table.grad, want, atol=1e-5, rtol=1e-5)
