"""Differentiable rendering: numba forward/analytic backward vs the renderer and the torch twin."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from plenoctree.errors import ConfigError
from plenoctree.octree import dense_tree, tree_from_grid
from plenoctree.optim import OctreeRenderFunction, render_rays_differentiable
from plenoctree.optim._render_grad import (SparseGrad, backward_numba, forward_numba, fused_mse_numba,
                                    kernel_args)
from plenoctree.render import RenderOptions, render_rays

FORMATS = ["SH1", "SH4", "SH9", "SH16", "SH25", "SG3", "SG30", "RGBA"]


def random_tree(fmt: str, seed: int, depth: int = 2, occupancy: float = 0.5):
    """A sparse tree (random occupied cells of a ``2^(depth+1)`` grid, empty space as big
    leaves); colours ~ N(0, 1), σ ~ |N| * 3 with a fifth of the occupied cells at σ = 0."""
    rng = np.random.default_rng(seed)
    res = 1 << (depth + 1)
    b = 1 if fmt == "RGBA" else int(fmt[2:])
    dim = 4 if fmt == "RGBA" else 3 * b + 1
    mask = rng.random((res, res, res)) < occupancy
    values = rng.normal(size=(res, res, res, dim)).astype(np.float32)
    sig = np.abs(rng.normal(size=(res, res, res))) * 3.0
    sig[rng.random((res, res, res)) < 0.2] = 0.0
    values[..., -1] = sig
    extra = None
    if fmt.startswith("SG"):
        axes = rng.normal(size=(b, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        extra = np.concatenate([rng.uniform(1, 5, (b, 1)), axes], axis=1).astype(np.float32)
    return tree_from_grid(values, mask, center=[0.1, -0.2, 0.05], radius=[1.0, 1.2, 0.9],
                          data_format=fmt, extra_data=extra)


def random_rays(n: int, seed: int):
    """Rays from a sphere of radius 3 towards the box, plus misses, axis-aligned rays and
    rays starting inside the box."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.7, 0.7, size=(n, 3)) - o
    d[: n // 10] = -d[: n // 10] + rng.normal(size=(n // 10, 3)) * 0.1   # pointing away: miss
    d[n // 10: n // 10 + 3] = [[-1, 0, 0], [0, 1, 0], [0, 0, -1]]          # axis-aligned
    o[n // 10: n // 10 + 3] = [[2, 0.1, 0.2], [0.3, -2, 0.1], [0.1, 0.2, 2]]
    o[-3:] = rng.uniform(-0.5, 0.5, size=(3, 3))                          # inside the box
    return o.astype(np.float32), d.astype(np.float32)


def grads(tree, o, d, opts, backend, dtype, g):
    data = torch.tensor(tree.data, dtype=dtype, requires_grad=True)
    rgb = render_rays_differentiable(data, tree, o, d, opts, backend=backend)
    (rgb * g.to(dtype)).sum().backward()
    return rgb.detach(), data.grad


@pytest.mark.parametrize("stop", [0.0, 0.01])
@pytest.mark.parametrize("fmt", FORMATS)
def test_forward_equals_renderer(fmt, stop):
    tree = random_tree(fmt, seed=FORMATS.index(fmt))
    o, d = random_rays(300, seed=1)
    opts = RenderOptions(stop_thresh=stop, background=(0.2, 0.5, 0.9))
    ref = render_rays(tree, o, d, opts, backend="numba").rgb.numpy()
    data2 = tree.data.reshape(-1, tree.data_dim)
    out = forward_numba(kernel_args(tree, opts), data2, o, d)
    np.testing.assert_allclose(out, ref, rtol=0, atol=2e-6)


@pytest.mark.parametrize("stop", [0.0, 0.05])
@pytest.mark.parametrize("fmt", FORMATS)
def test_gradients_match_twin(fmt, stop):
    tree = random_tree(fmt, seed=10 + FORMATS.index(fmt))
    o, d = random_rays(400, seed=2)
    opts = RenderOptions(stop_thresh=stop, background=(1.0, 0.3, 0.0))
    g = torch.from_numpy(np.random.default_rng(3).normal(size=(400, 3)))
    rgb_t, g_twin = grads(tree, o, d, opts, "torch", torch.float64, g)
    rgb_64, g_64 = grads(tree, o, d, opts, "numba", torch.float64, g)
    rgb_32, g_32 = grads(tree, o, d, opts, "numba", torch.float32, g)
    assert g_64.shape == g_32.shape == tree.data.shape
    # float64 kernel vs float64 twin: same maths to rounding (the basis is evaluated in float64
    # by both).
    np.testing.assert_allclose(rgb_64.numpy(), rgb_t.numpy(), atol=1e-9)
    np.testing.assert_allclose(g_64.numpy(), g_twin.numpy(), atol=1e-8 * float(g_twin.abs().max()))
    # float32 kernel: element-wise to float32 accuracy, plus direction and norm.
    scale = float(g_twin.abs().max())
    assert scale > 0
    np.testing.assert_allclose(g_32.numpy(), g_twin.numpy(), atol=2e-5 * scale)
    a, b = g_32.double().reshape(-1), g_twin.reshape(-1)
    assert torch.dot(a, b) / (a.norm() * b.norm()) > 1 - 1e-9
    assert abs(float(a.norm() / b.norm()) - 1) < 1e-5
    # structure: internal cells and cells with σ <= 0 get exactly zero gradient
    internal = tree.child != 0
    assert not g_32.numpy()[internal].any()
    dead = (tree.child == 0) & (tree.data[..., -1] <= 0)
    assert not g_32.numpy()[dead].any()


@pytest.mark.parametrize("stop", [0.0, 0.3])
@pytest.mark.parametrize("fmt", ["SH4", "SG2", "RGBA"])
def test_gradcheck_numba_float64(fmt, stop):
    tree = dense_tree(1, fmt, center=0.0, radius=1.0, seed=4)
    o, d = random_rays(12, seed=5)
    opts = RenderOptions(stop_thresh=stop, background=(0.3, 0.6, 0.9))
    args = kernel_args(tree, opts)
    data = torch.tensor(tree.data, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: OctreeRenderFunction.apply(x, args, o, d), (data,),
                                    eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_twin_float64():
    tree = dense_tree(1, "SH4", center=0.0, radius=1.0, seed=6)
    o, d = random_rays(8, seed=7)
    data = torch.tensor(tree.data, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x: render_rays_differentiable(x, tree, o, d, RenderOptions(stop_thresh=0.0),
                                             backend="torch"), (data,), eps=1e-6, atol=1e-6)


def test_scatter_is_race_free_and_chunk_independent():
    tree = random_tree("SH9", seed=20, depth=3)
    o, d = random_rays(3000, seed=8)
    opts = RenderOptions()
    args = kernel_args(tree, opts)
    data2 = tree.data.reshape(-1, tree.data_dim)
    g = np.random.default_rng(9).normal(size=(3000, 3))
    one = backward_numba(args, data2, o, d, g, SparseGrad(*data2.shape, np.float32, n_chunks=1))
    four = backward_numba(args, data2, o, d, g, SparseGrad(*data2.shape, np.float32, n_chunks=4))
    np.testing.assert_allclose(four.grad, one.grad, atol=1e-5 * np.abs(one.grad).max())
    assert sorted(one.touched_cells()) == sorted(four.touched_cells())
    assert len(set(four.touched_cells().tolist())) == len(four.touched_cells())
    # the slabs are clean after the merge
    assert not four.grad3.any() and (four.slot == -1).all() and not four.n_touched.any()
    # every cell with a gradient is listed, and nothing else
    nz = np.flatnonzero(np.abs(one.grad).sum(1))
    assert set(nz.tolist()) <= set(one.touched_cells().tolist())


def test_fused_mse_gradient_equals_autograd_of_the_loss():
    tree = random_tree("SH16", seed=30)
    o, d = random_rays(500, seed=10)
    opts = RenderOptions()
    tgt = np.random.default_rng(11).uniform(0, 1, size=(500, 3)).astype(np.float32)
    scale = 1.0 / 777.0
    data = torch.tensor(tree.data, requires_grad=True)
    rgb = render_rays_differentiable(data, tree, o, d, opts, backend="numba")
    loss = ((rgb.double() - torch.from_numpy(tgt).double()) ** 2).sum()
    (loss * scale).backward()
    data2 = tree.data.reshape(-1, tree.data_dim).copy()
    buf = SparseGrad(*data2.shape, np.float32)
    sse = fused_mse_numba(kernel_args(tree, opts), data2, o, d, tgt, scale, buf)
    assert sse == pytest.approx(float(loss.detach()), rel=1e-5)
    ref = data.grad.numpy().reshape(data2.shape)
    np.testing.assert_allclose(buf.grad, ref, atol=1e-6 * np.abs(ref).max())


def test_edge_rays_empty_opaque_and_no_rays():
    tree = random_tree("SH4", seed=40)
    opts = RenderOptions(stop_thresh=0.01, background=(0.1, 0.2, 0.3))
    # no rays at all
    data = torch.tensor(tree.data, requires_grad=True)
    rgb = render_rays_differentiable(data, tree, np.zeros((0, 3)), np.ones((0, 3)), opts)
    assert rgb.shape == (0, 3)
    rgb.sum().backward()
    assert not data.grad.any()
    # rays that miss the box: background colour, zero gradient
    o = np.array([[5.0, 5.0, 5.0], [0.0, 9.0, 0.0]], np.float32)
    d = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], np.float32)
    data = torch.tensor(tree.data, requires_grad=True)
    rgb = render_rays_differentiable(data, tree, o, d, opts)
    np.testing.assert_allclose(rgb.detach().numpy(), [[0.1, 0.2, 0.3]] * 2, atol=1e-7)
    rgb.sum().backward()
    assert not data.grad.any()
    # fully opaque: the first cell takes everything; only it gets a (colour) gradient
    opaque = tree.copy()
    occ = opaque.child == 0
    opaque.data[occ, -1] = 1e6
    o = np.array([[0.1, -0.2, 3.0]], np.float32)
    d = np.array([[0.0, 0.0, -1.0]], np.float32)
    for backend in ("numba", "torch"):
        data = torch.tensor(opaque.data, dtype=torch.float64, requires_grad=True)
        rgb = render_rays_differentiable(data, opaque, o, d, opts, backend=backend)
        rgb.sum().backward()
        touched = np.flatnonzero(np.abs(data.grad.numpy()).reshape(-1, tree.data_dim).sum(1))
        assert len(touched) == 1, backend
        assert np.isfinite(data.grad.numpy()).all()


def test_basis_range_and_tiny_record_capacity():
    tree = random_tree("SH9", seed=50, depth=3)
    o, d = random_rays(200, seed=12)
    opts = RenderOptions(stop_thresh=0.0, sh_min=1, sh_max=3)
    g = torch.from_numpy(np.random.default_rng(13).normal(size=(200, 3)))
    _, g_twin = grads(tree, o, d, opts, "torch", torch.float64, g)
    _, g_fast = grads(tree, o, d, opts, "numba", torch.float64, g)
    np.testing.assert_allclose(g_fast.numpy(), g_twin.numpy(), atol=1e-9)
    coef = g_fast.numpy()[..., :-1].reshape(*tree.child.shape, 3, 9)
    assert not coef[..., 0].any() and not coef[..., 4:].any() and coef[..., 1:4].any()
    # a record far too small for the rays grows on the fly and gives the same result
    args = kernel_args(tree, opts)
    small = dataclasses.replace(args, cap0=1)
    data2 = tree.data.reshape(-1, tree.data_dim)
    a = backward_numba(args, data2, o, d, g.numpy()).grad
    b = backward_numba(small, data2, o, d, g.numpy()).grad
    np.testing.assert_array_equal(a, b)


def test_bad_arguments():
    from plenoctree.errors import BackendError, ConfigError

    tree = random_tree("SH1", seed=60)
    o, d = random_rays(4, seed=14)
    with pytest.raises(ConfigError, match="expected shape"):
        render_rays_differentiable(torch.zeros(3, 4), tree, o, d)
    with pytest.raises(ConfigError, match="torch tensor"):
        render_rays_differentiable(tree.data, tree, o, d)
    with pytest.raises(BackendError, match="unknown backend"):
        render_rays_differentiable(torch.tensor(tree.data), tree, o, d, backend="cuda-magic")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_tensors_use_the_twin():
    tree = random_tree("SH4", seed=70)
    o, d = random_rays(100, seed=15)
    g = torch.from_numpy(np.random.default_rng(16).normal(size=(100, 3)))
    _, ref = grads(tree, o, d, RenderOptions(), "numba", torch.float32, g)
    data = torch.tensor(tree.data, device="cuda", requires_grad=True)
    rgb = render_rays_differentiable(data, tree, torch.from_numpy(o).cuda(),
                                     torch.from_numpy(d).cuda(), RenderOptions())
    assert rgb.device.type == "cuda"
    (rgb * g.float().cuda()).sum().backward()
    np.testing.assert_allclose(data.grad.cpu().numpy(), ref.numpy(), atol=1e-4)


def test_full_slabs_grow_and_the_batch_runs_again():
    """Slabs far too small for the batch: the kernels' wrapper grows them (once) and reruns the
    batch, and the gradient and the step equal those of slabs large enough from the start."""
    tree = random_tree("SH4", seed=21, depth=3)
    o, d = random_rays(2000, seed=12)
    args = kernel_args(tree, RenderOptions())
    data2 = tree.data.reshape(-1, tree.data_dim)
    g = np.random.default_rng(13).normal(size=(2000, 3))
    big = backward_numba(args, data2, o, d, g, SparseGrad(*data2.shape, np.float32, n_chunks=2))
    small = SparseGrad(*data2.shape, np.float32, n_chunks=2, capacity=3)
    backward_numba(args, data2, o, d, g, small)
    assert small.regrown == 1 and small.cap >= len(big.touched_cells()) and big.regrown == 0
    np.testing.assert_allclose(small.grad, big.grad, atol=1e-5 * np.abs(big.grad).max())
    np.testing.assert_array_equal(small.touched_cells(), big.touched_cells())
    assert not small.need.any() and (small.slot == -1).all()
    # a step with slabs that must grow equals one with slabs that need not
    from plenoctree.optim._steppers import NumbaStepper

    tgt = np.random.default_rng(14).uniform(size=(2000, 3)).astype(np.float32)
    a = NumbaStepper(data2.copy(), args, "adam", 1e-2, n_chunks=2)
    b = NumbaStepper(data2.copy(), args, "adam", 1e-2, n_chunks=2)
    b.buf = SparseGrad(*data2.shape, np.float32, n_chunks=2, capacity=1)
    for _ in range(2):
        sa, _ = a.step(o, d, tgt, 1e-3)
        sb, _ = b.step(o, d, tgt, 1e-3)
        assert sa == pytest.approx(sb, rel=1e-6)
    assert b.buf.regrown >= 1
    np.testing.assert_allclose(b.values(), a.values(), atol=1e-6)
    with pytest.raises(ConfigError, match="still hold a batch"):
        b.accumulate(o, d, tgt, 1e-3)
        b.accumulate(o, d, tgt, 1e-3)


@pytest.mark.parametrize("optimizer", ["adam", "rmsprop"])
def test_optimiser_kernel_steps_as_torch_in_float32(optimizer):
    """``step_touched`` on hand-filled slabs (two chunks sharing a cell) equals torch's own
    optimiser on the summed gradient, float32, σ (last column) at its own rate and kept ≥ 0."""
    from plenoctree.optim import _render_grad_numba as k

    rng = np.random.default_rng(7)
    n_cells, dim, lr, lr_sig = 10, 5, 1e-2, 3e-2
    rows = [np.array([3, 7]), np.array([7, 9])]          # cell 7 is in both chunks' lists
    data = rng.normal(size=(n_cells, dim)).astype(np.float32)
    data[:, -1] = np.abs(data[:, -1]) + 0.05
    data[9, -1] = 1e-4                                   # its σ step ends below 0: clamped
    m1, m2, sig = np.zeros_like(data), np.zeros_like(data), data[:, -1].copy()
    start = data.copy()
    colour = torch.tensor(data[:, :-1], requires_grad=True)
    sigma = torch.tensor(data[:, -1:], requires_grad=True)
    groups = [{"params": [colour], "lr": lr}, {"params": [sigma], "lr": lr_sig}]
    ref = (torch.optim.Adam(groups, betas=(0.9, 0.999), eps=1e-8) if optimizer == "adam"
           else torch.optim.RMSprop(groups, alpha=0.99, eps=1e-8))
    opt = k.OPT_ADAM if optimizer == "adam" else k.OPT_RMSPROP
    beta1 = 0.9 if optimizer == "adam" else 0.0
    beta2 = 0.999 if optimizer == "adam" else 0.99
    for step in range(1, 4):
        grad3 = np.zeros((2, 4, dim), np.float32)
        slot = np.full((2, n_cells), -1, np.int32)
        touched = np.zeros((2, 4), np.int64)
        dense = np.zeros((n_cells, dim), np.float32)
        for c, cells in enumerate(rows):
            for j, cell in enumerate(cells):
                grad3[c, j] = rng.normal(size=dim)
                if cell == 9:
                    grad3[c, j, -1] = 1.0                # pushes its σ below 0
                slot[c, cell], touched[c, j] = j, cell
                dense[cell] += grad3[c, j]
        bad = k.step_touched(data, sig, grad3, slot, touched, np.array([2, 2], np.int64), opt,
                             lr, lr_sig, m1, m2, beta1, beta2, 1e-8, float(step))
        assert bad == 0 and not grad3.any() and (slot == -1).all()
        ref.zero_grad()
        colour.grad, sigma.grad = torch.tensor(dense[:, :-1]), torch.tensor(dense[:, -1:])
        ref.step()
        with torch.no_grad():
            sigma.clamp_(min=0.0)
        want = torch.cat([colour, sigma], 1).detach().numpy()
        np.testing.assert_allclose(data, want, rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(sig, data[:, -1])
    untouched = [0, 1, 2, 4, 5, 6, 8]
    assert data[9, -1] == 0.0 and (data[untouched] == start[untouched]).all()
    assert (m1[untouched] == 0).all() and (m2[untouched] == 0).all()
