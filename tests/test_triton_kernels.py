"""The Triton GPU kernels against their torch twins, run in Triton's CPU interpreter.

Without a GPU these tests execute the GPU kernels' logic in Triton's interpreter
(``TRITON_INTERPRET=1``, set by ``conftest.py`` before triton is imported, plus
``PLENOCTREE_TRITON_CPU=1``, set by an autouse fixture for this module only, so that no other
test sees Triton as usable on the CPU) on tiny inputs: the interpreter runs every block op in
NumPy, so a few hundred rays take seconds. With a CUDA device the same tests run the compiled kernels on the GPU.
"""

from __future__ import annotations

import os

import pytest
import torch

ON_GPU = torch.cuda.is_available()
pytest.importorskip("triton")

import numpy as np  # noqa: E402

from plenoctree.octree import Octree  # noqa: E402
from plenoctree.render import RenderOptions, render_rays  # noqa: E402

pytestmark = pytest.mark.gpu_sim
DEV = torch.device("cuda" if ON_GPU else "cpu")


@pytest.fixture(autouse=True, scope="module")
def _interpreter():
    """Triton on CPU tensors while this module's tests run (no GPU: the interpreter)."""
    old = os.environ.get("PLENOCTREE_TRITON_CPU")
    if not ON_GPU:
        if os.environ.get("TRITON_INTERPRET") != "1":
            pytest.skip("TRITON_INTERPRET=1 must be set before triton is imported (conftest.py)")
        os.environ["PLENOCTREE_TRITON_CPU"] = "1"
    yield
    if old is None:
        os.environ.pop("PLENOCTREE_TRITON_CPU", None)
    else:
        os.environ["PLENOCTREE_TRITON_CPU"] = old


def _random_tree(fmt, seed, res=8, occupancy=0.3):
    rng = np.random.default_rng(seed)
    if fmt == "RGBA":
        dim, b = 4, 1
    else:
        b = int(fmt[2:])
        dim = 3 * b + 1
    values = rng.normal(size=(res, res, res, dim)).astype(np.float32)
    values[..., -1] = np.abs(values[..., -1]) * 6.0
    values[..., -1][rng.random((res, res, res)) < 0.15] = 0.0        # some σ = 0 leaves
    mask = rng.random((res, res, res)) < occupancy
    extra = None
    if fmt.startswith("SG"):
        mu = rng.normal(size=(b, 3))
        mu /= np.linalg.norm(mu, axis=1, keepdims=True)
        extra = np.c_[rng.uniform(0.5, 8.0, b), mu].astype(np.float32)
    return Octree.from_grid(values, mask, rng.normal(size=3) * 0.3,
                            rng.uniform(0.6, 1.6, size=3), fmt, extra)


def _random_rays(tree, n, seed):
    rng = np.random.default_rng(seed)
    center, radius = tree.center, tree.radius
    target = center + rng.uniform(-1.1, 1.1, size=(n, 3)) * radius
    start = center + rng.normal(size=(n, 3)) * 3.0 * radius.max()
    inside = rng.random(n) < 0.2
    start[inside] = center + rng.uniform(-0.9, 0.9, size=(inside.sum(), 3)) * radius
    d = target - start
    d[inside] = rng.normal(size=(inside.sum(), 3))
    return (torch.from_numpy(start.astype(np.float32)).to(DEV),
            torch.from_numpy(d.astype(np.float32)).to(DEV))


def _axis_rays(tree, n, seed):
    """Axis-aligned rays starting on grid planes (leaf lookups exactly on voxel faces)."""
    rng = np.random.default_rng(seed)
    c, r = tree.center, tree.radius
    o = c + (rng.integers(0, 9, size=(n, 3)) / 4.0 - 1.0) * r
    axis, sign = rng.integers(0, 3, n), rng.choice([-1.0, 1.0], n)
    d = np.zeros((n, 3))
    d[np.arange(n), axis] = sign
    o[np.arange(n), axis] = c[axis] - 3.0 * sign * r[axis]
    return (torch.from_numpy(o.astype(np.float32)).to(DEV),
            torch.from_numpy(d.astype(np.float32)).to(DEV))


# ------------------------------------------------------------------------------ rendering
@pytest.mark.parametrize("fmt,stop", [("SH4", 0.0), ("SH9", 0.01), ("SG3", 0.01),
                                      ("RGBA", 0.0)])
def test_render_kernel_matches_twin(fmt, stop):
    tree = _random_tree(fmt, seed=sum(map(ord, fmt)))
    o, d = _random_rays(tree, 160, seed=7)
    opts = RenderOptions(stop_thresh=stop, background=(0.3, 0.6, 0.9))
    fast = render_rays(tree, o, d, opts, backend="triton")
    ref = render_rays(tree, o, d, opts, backend="torch")
    assert fast.rgb.device.type == DEV.type and fast.rgb.dtype == torch.float32
    assert float(ref.alpha.max()) > 0.5 and float(ref.alpha.min()) == 0.0   # a real test
    assert float((fast.rgb - ref.rgb).abs().max()) <= 1e-5
    assert float((fast.alpha - ref.alpha).abs().max()) <= 1e-5
    assert float(((fast.depth - ref.depth).abs() / ref.depth.clamp(min=1)).max()) <= 1e-5


def test_render_kernel_on_voxel_faces_and_basis_range():
    tree = _random_tree("SH4", seed=3)
    o, d = _axis_rays(tree, 120, seed=1)
    for opts in (RenderOptions(), RenderOptions(sh_min=1, sh_max=2, stop_thresh=0.0)):
        fast = render_rays(tree, o, d, opts, backend="triton")
        ref = render_rays(tree, o, d, opts, backend="torch")
        assert float(ref.alpha.mean()) > 0.2
        assert float((fast.rgb - ref.rgb).abs().max()) <= 1e-5


def test_render_kernel_float64_and_empty_batch():
    tree = _random_tree("SH1", seed=5)
    tree64 = Octree(tree.child, tree.data.astype(np.float64), tree.offset, tree.invradius,
                    tree.data_format, tree.extra_data)
    o, d = _random_rays(tree, 64, seed=2)
    fast = render_rays(tree64, o, d, backend="triton")
    ref = render_rays(tree64, o, d, backend="torch")
    assert fast.rgb.dtype == torch.float64
    assert float((fast.rgb - ref.rgb).abs().max()) <= 1e-12
    empty = render_rays(tree, o[:0], d[:0], backend="triton")
    assert empty.rgb.shape == (0, 3)


# ------------------------------------------------------------------------------ fine-tuning
@pytest.mark.parametrize("fmt", ["SH4", "SG3", "RGBA"])
def test_finetune_kernel_gradient_matches_twin_autograd(fmt):
    from plenoctree.optim.autograd import render_rays_differentiable

    tree = _random_tree(fmt, seed=11 + len(fmt))
    o, d = _random_rays(tree, 100, seed=4)
    opts = RenderOptions(stop_thresh=0.01, background=(0.3, 0.6, 0.9))
    target = torch.rand(100, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    res = {}
    for backend in ("triton", "torch"):
        data = torch.tensor(tree.data.astype(np.float64), device=DEV, requires_grad=True)
        rgb = render_rays_differentiable(data, tree, o, d, opts, backend=backend)
        ((rgb - target.to(DEV)) ** 2).sum().backward()
        res[backend] = (rgb.detach().cpu(), data.grad.cpu())
    (rgb_k, g_k), (rgb_t, g_t) = res["triton"], res["torch"]
    assert float(g_t.abs().max()) > 1e-3 and int((g_t[..., -1] != 0).sum()) > 20  # a real test
    assert float((rgb_k - rgb_t).abs().max()) <= 1e-12
    assert float((g_k - g_t).abs().max()) <= 1e-12 * max(1.0, float(g_t.abs().max()))


def test_finetune_kernel_gradcheck_float64():
    from plenoctree.optim.autograd import render_rays_differentiable

    tree = _random_tree("SH1", seed=2, res=4, occupancy=0.6)
    o, d = _random_rays(tree, 24, seed=9)
    data = torch.tensor(tree.data.astype(np.float64), device=DEV, requires_grad=True)
    # σ away from the relu kink so finite differences are valid
    with torch.no_grad():
        data[..., -1] = data[..., -1].abs() + 0.5
    opts = RenderOptions(stop_thresh=0.0)
    assert torch.autograd.gradcheck(
        lambda x: render_rays_differentiable(x, tree, o, d, opts, backend="triton"), (data,),
        eps=1e-6, atol=1e-6, fast_mode=True)


def test_triton_stepper_matches_torch_stepper():
    from plenoctree.optim._steppers import make_stepper

    tree = _random_tree("SH4", seed=21)
    o, d = _random_rays(tree, 96, seed=3)
    o_np, d_np = o.cpu().numpy(), d.cpu().numpy()
    target = np.random.default_rng(0).random((96, 3)).astype(np.float32)
    opts = RenderOptions()
    data2 = np.ascontiguousarray(tree.data.reshape(-1, tree.data_dim))
    out = {}
    for backend in ("triton", "torch"):
        st = make_stepper(backend, data2.copy(), tree, opts, "adam", 1e-2, device=str(DEV))
        assert st.backend == backend
        for _ in range(2):
            sse, bad = st.step(o_np, d_np, target, 1.0 / 96)
        out[backend] = (sse, st.values().copy(), st.render(o_np, d_np))
    assert out["triton"][0] == pytest.approx(out["torch"][0], rel=1e-5)
    np.testing.assert_allclose(out["triton"][1], out["torch"][1], atol=1e-5)
    np.testing.assert_allclose(out["triton"][2], out["torch"][2], atol=1e-5)


# ------------------------------------------------------------------------------ NeRF-SH
def test_hashgrid_kernel_matches_twin_forward_and_backward():
    from plenoctree.nerf.encoding import HashGridEncoding, HashGridLayout

    gen = torch.Generator().manual_seed(0)
    enc = HashGridEncoding([[-1, -1, -1], [1, 1, 1]],
                           HashGridLayout(n_levels=4, n_features=2, base_res=2, max_res=32,
                                          log2_table=8), init_scale=1.0, generator=gen).to(DEV)
    assert enc.hashed.any() and (~enc.hashed).any()               # dense and hashed levels
    pts = (torch.rand(300, 3, generator=gen) * 2.4 - 1.2).to(DEV)  # some outside the box
    pts[:10] = torch.tensor([1.0, -1.0, 0.5]).to(DEV)              # exactly on faces
    w = torch.randn(300, enc.out_dim, generator=gen).to(DEV)
    res = {}
    for backend in ("triton", "torch"):
        enc.backend = backend
        enc.table.grad = None
        out = enc(pts)
        (out * w).sum().backward()
        res[backend] = (out.detach().cpu(), enc.table.grad.detach().cpu())
    assert float(res["torch"][1].abs().max()) > 0.1
    torch.testing.assert_close(res["triton"][0], res["torch"][0], atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(res["triton"][1], res["torch"][1], atol=1e-5, rtol=1e-5)
    # in-place table gradient (the trainer's mode) adds into table.grad
    enc.backend, enc.grad_in_place = "triton", True
    enc.table.grad = torch.ones_like(enc.table)
    (enc(pts) * w).sum().backward()
    torch.testing.assert_close(enc.table.grad.cpu(), res["torch"][1] + 1.0, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("max_per_ray", [0, 3])
def test_march_kernel_matches_twin(max_per_ray):
    from plenoctree.nerf.sampling import MarchGrid, MarchRays, march_rays

    gen = torch.Generator().manual_seed(1)
    n, g = 150, 8
    bbox = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    mask = torch.rand(g, g, g, generator=gen) < 0.3
    o = torch.randn(n, 3, generator=gen) * 2.5
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen) * 0.3 - o, dim=-1)
    t_min = torch.full((n,), 0.5)
    t_max = torch.full((n,), 6.0)
    jitter = torch.rand(n, generator=gen)
    k0 = torch.randint(0, 4, (n,), generator=gen)
    rays = MarchRays(*[x.to(DEV) for x in (o, d, t_min, t_max, jitter, k0)])
    grid = MarchGrid(0.07, mask.to(DEV), bbox.to(DEV))
    fast = march_rays(rays, grid, max_per_ray=max_per_ray, backend="triton")
    ref = march_rays(rays, grid, max_per_ray=max_per_ray, backend="torch")
    assert len(ref) > 100                                          # a real test
    assert bool(ref.done.all()) == (max_per_ray == 0)              # the cap stops some rays
    for name in ("ray_idx", "offsets", "k_next", "done"):
        assert torch.equal(getattr(fast, name).cpu(), getattr(ref, name).cpu()), name
    assert torch.equal(fast.t.cpu(), ref.t.cpu()) and torch.equal(fast.points.cpu(),
                                                                  ref.points.cpu())
