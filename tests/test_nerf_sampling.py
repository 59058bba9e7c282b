"""Ray samplers: box intersection, stratified / importance samples, occupancy marching."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from plenoctree.nerf.sampling import (MarchGrid, MarchRays, march_rays, pdf_samples, ray_aabb,
                                      stratified_samples)

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_ray_aabb():
    o = torch.tensor([[-3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t0, t1 = ray_aabb(o, d, BOX)
    torch.testing.assert_close(t0[:2], torch.tensor([2.0, -1.0]))
    torch.testing.assert_close(t1[:2], torch.tensor([4.0, 1.0]))
    assert t1[2] <= t0[2]                      # misses


def test_stratified():
    near, far = torch.full((4,), 2.0), torch.full((4,), 6.0)
    t = stratified_samples(near, far, 5, perturb=False)
    torch.testing.assert_close(t[0], torch.linspace(2, 6, 5))
    g = torch.Generator().manual_seed(0)
    t = stratified_samples(near, far, 64, perturb=True, generator=g)
    assert t.shape == (4, 64) and (t >= 2).all() and (t <= 6).all()
    assert (t[:, 1:] >= t[:, :-1]).all()


def test_pdf_samples_follow_weights():
    bins = torch.linspace(0, 1, 11).expand(3, 11).contiguous()
    w = torch.zeros(3, 10)
    w[:, 7] = 1.0                               # all mass in [0.7, 0.8]
    g = torch.Generator().manual_seed(0)
    t = pdf_samples(bins, w, 200, perturb=True, generator=g)
    assert t.shape == (3, 200) and (t[:, 1:] >= t[:, :-1]).all()
    inside = ((t >= 0.7) & (t <= 0.8)).float().mean()
    assert inside > 0.95
    t = pdf_samples(bins, torch.ones(3, 10), 11, perturb=False)
    torch.testing.assert_close(t[0], torch.linspace(0, 1, 11), atol=1e-3, rtol=0)


def _rays(n, seed):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn((n, 3), generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    target = torch.rand((n, 3), generator=g) - 0.5
    d = target - o
    d = d / d.norm(dim=-1, keepdim=True)
    t0, t1 = ray_aabb(o, d, BOX)
    return o, d, t0.clamp(min=0.5), t1, torch.rand(n, generator=g), g


def _assert_same(a, b):
    for name in ("ray_idx", "offsets", "k_next", "done"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    torch.testing.assert_close(a.t, b.t, atol=0, rtol=0)
    torch.testing.assert_close(a.points, b.points, atol=0, rtol=0)


def _march(o, d, t0, t1, jit, step, mask, bbox, k_start=None, **kw):
    """``march_rays`` of these rays through ``mask`` over ``bbox`` at ``step``."""
    return march_rays(MarchRays(o, d, t0, t1, jit, k_start), MarchGrid(step, mask, bbox), **kw)


def _numba_equals_twin(*args, **kw):
    """``_march(*args, **kw)`` with the numba kernels, checked equal to the torch twin's."""
    a = _march(*args, **kw, backend="numba")
    _assert_same(a, _march(*args, **kw, backend="torch"))
    return a


@pytest.mark.parametrize("cap", [0, 3])
def test_march_numba_matches_torch(cap):
    o, d, t0, t1, jit, g = _rays(300, 1)
    mask = torch.rand((16, 16, 16), generator=g) < 0.3
    k0 = torch.randint(0, 5, (300,), generator=g)
    a = _numba_equals_twin(o, d, t0, t1, jit, 0.05, mask, BOX, k_start=k0, max_per_ray=cap)
    assert len(a) > 300
    # every sample lies in an occupied cell and on the ray's lattice
    c = ((a.points - BOX[0]) / 2.0 * 16).floor().long()
    assert mask[c[:, 0], c[:, 1], c[:, 2]].all()
    k = (a.t - t0[a.ray_idx]) / 0.05 - jit[a.ray_idx]
    torch.testing.assert_close(k, k.round(), atol=2e-3, rtol=0)
    if cap:
        assert int(a.counts.max()) <= cap


def _shell_mask(g):
    """A thick spherical shell and a small cube: large empty cubes around and inside."""
    ijk = torch.stack(torch.meshgrid(*[torch.arange(g)] * 3, indexing="ij"), -1).float()
    r = ((ijk + 0.5) / g - 0.5).norm(dim=-1)
    mask = (r > 0.2) & (r < 0.28)
    mask[2:4, 20:23, 5:7] = True
    return mask


def test_empty_levels_are_the_largest_empty_aligned_cubes():
    from plenoctree.nerf import _march_numba as K

    mask = _shell_mask(32)
    levels = np.empty((32, 32, 32), np.uint8)
    K.empty_levels(mask.numpy(), levels)
    m = mask.numpy()
    assert np.all((levels == K.OCCUPIED) == m)
    for lev in range(6):
        s = 1 << lev
        blocks = m.reshape(32 // s, s, 32 // s, s, 32 // s, s).any(axis=(1, 3, 5))
        empty = np.repeat(np.repeat(np.repeat(~blocks, s, 0), s, 1), s, 2)
        # a cell's level is >= lev exactly when its aligned 2^lev cube is empty
        assert np.array_equal((levels >= lev) & ~m, empty), lev
    assert levels[~m].max() >= 3                     # the corners' empty 8-cell cubes
    cs = K.coarse_shift(32)
    coarse = np.empty((32 >> cs,) * 3, np.uint8)
    K.coarse_levels(levels, cs, coarse)
    up = np.repeat(np.repeat(np.repeat(coarse, 1 << cs, 0), 1 << cs, 1), 1 << cs, 2)
    assert cs == 3 and (up != K.MIXED).any() and (up == K.MIXED).any()
    assert np.array_equal(up[up != K.MIXED], levels[up != K.MIXED])   # one value per cube
    # MIXED exactly where the 8-cell cube holds an occupied cell
    assert np.array_equal(coarse == K.MIXED, m.reshape(4, 8, 4, 8, 4, 8).any(axis=(1, 3, 5)))
    assert K.coarse_shift(12) == 2 and K.coarse_shift(7) == 0


@pytest.mark.parametrize("cap", [0, 2])
def test_march_jumps_over_empty_cubes_with_the_twins_samples(cap):
    """Rays through large empty cubes, many lattice steps per cell, some axis-parallel or
    grazing cube faces: the numba kernels (which jump) emit exactly the twin's samples."""
    o, d, t0, t1, jit, g = _rays(400, 5)
    d[:40] = torch.tensor([1.0, 0.0, 0.0])             # axis-parallel, along cell faces
    o[:40] = torch.tensor([-2.0, 0.0, 0.0]) + (torch.arange(40)[:, None] % 8) * torch.tensor(
        [0.0, 2.0 / 32, 2.0 / 32]) - torch.tensor([0.0, 0.5, 0.5])
    d[40:80] = torch.nn.functional.normalize(torch.tensor([1.0, 1e-6, 0.3]), dim=0)
    o[40:80] = torch.tensor([-2.0, 2.0 / 32 * 3, -0.5]) + torch.randn((40, 3), generator=g) * 1e-3
    t0, t1 = ray_aabb(o, d, BOX)
    t0 = t0.clamp(min=0.0)
    mask = _shell_mask(32)
    k0 = torch.randint(0, 3, (400,), generator=g)
    a = _numba_equals_twin(o, d, t0, t1, jit, 0.004, mask, BOX, k_start=k0, max_per_ray=cap)
    assert len(a) > 400
    # the same mask object marched again after an in-place change: the jumps follow it
    mask[:, :, :] = ~mask
    assert len(_numba_equals_twin(o, d, t0, t1, jit, 0.004, mask, BOX, max_per_ray=cap)) > 400


def test_march_in_waves_equals_one_march():
    o, d, t0, t1, jit, g = _rays(200, 2)
    mask = torch.rand((12, 12, 12), generator=g) < 0.5
    full = _march(o, d, t0, t1, jit, 0.04, mask, BOX)
    k = torch.zeros(200, dtype=torch.int64)
    parts = [[] for _ in range(200)]
    active = torch.arange(200)
    while active.numel():
        s = _march(o[active], d[active], t0[active], t1[active], jit[active], 0.04, mask,
                   BOX, k_start=k[active], max_per_ray=4)
        for j, r in enumerate(active.tolist()):
            parts[r].append(s.t[s.offsets[j]:s.offsets[j + 1]])
        k[active] = s.k_next
        active = active[~s.done]
    waves = torch.cat([torch.cat(p) for p in parts])
    torch.testing.assert_close(waves, full.t, atol=0, rtol=0)


def test_march_empty_and_full_grid():
    o, d, t0, t1, jit, _ = _rays(50, 3)
    empty = _march(o, d, t0, t1, jit, 0.05, torch.zeros((8, 8, 8), dtype=torch.bool), BOX)
    assert len(empty) == 0 and empty.done.all() and empty.offsets.shape == (51,)
    full = _march(o, d, t0, t1, jit, 0.05, torch.ones((8, 8, 8), dtype=torch.bool), BOX)
    expect = torch.clamp(torch.ceil((t1 - t0) / 0.05 - jit), min=0).long()
    assert (full.counts - expect).abs().max() <= 1      # boundary samples may fall just outside
