"""The fixed-shape step's fused GPU kernels (issue 47) against their twins, in Triton's
interpreter: the network after its encoding in one launch each way (op ``mlp``,
``nerf/_mlp_triton.py``; twin: the eager network) and early ray termination by rays walking
their candidates (op ``terminate``, ``nerf/_terminate_triton.py``; twin: prefix sums)."""

from __future__ import annotations

import contextlib
import sys
from dataclasses import fields
from pathlib import Path

import pytest
import torch

from test_fixed_step import _assert_fixed_equal, _case, _slab_sigma

from plenoctree.nerf.config import ModelConfig
from plenoctree.nerf.fixed import FixedSamples, march_fixed, terminate_fixed
from plenoctree.nerf.sampling import MarchGrid
from plenoctree.nerf.model import RadianceField, mlp_spec

pytest.importorskip("triton")
pytestmark = pytest.mark.gpu_sim
_BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
ON_GPU = torch.cuda.is_available()
DEV = torch.device("cuda" if ON_GPU else "cpu")
#: compiled on a GPU the kernel's dots run in TF32 (10-bit mantissas); the interpreter in fp32
TOL = dict(atol=1e-2, rtol=1e-2) if ON_GPU else dict(atol=2e-6, rtol=1e-5)
GTOL = dict(atol=2e-2, rtol=2e-2) if ON_GPU else dict(atol=1e-5, rtol=1e-4)


def _field(**kw) -> RadianceField:
    torch.manual_seed(0)
    cfg = ModelConfig(grid_levels=8, grid_log2_table=10, grid_max_res=32, **kw)
    f = RadianceField(cfg, [[-1, -1, -1], [1, 1, 1]])
    with torch.no_grad():                     # away from the zero init: every path non-zero
        for p in f.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return f.to(DEV)


def _inputs(n: int, seed: int):
    """Points (some outside the box), unit directions and the loss weights, on ``DEV``."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=g) * 2.2 - 1.1
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    ws = [torch.randn(n, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, generator=g)]
    return pts.to(DEV), d.to(DEV), [w.to(DEV) for w in ws]


def _run(f: RadianceField, backend: str, n: int, seed: int = 1):
    """σ, rgb, density and every parameter's gradient of a loss that weighs all three."""
    pts, d, ws = _inputs(n, seed)
    f.mlp_backend = backend
    f.zero_grad(set_to_none=True)
    sigma, rgb = f.radiance(pts, d)
    dens = f.density(pts)
    ((sigma * ws[0]).sum() + (rgb * ws[1]).sum() + (dens * ws[2]).sum()).backward()
    grads = {k: p.grad.clone() for k, p in f.named_parameters() if p.grad is not None}
    return (sigma.detach(), rgb.detach(), dens.detach()), grads


@pytest.mark.parametrize("depth,act,degree,n", [(2, "trunc_exp", 3, 150), (1, "relu", 0, 64),
                                                (3, "trunc_exp", 2, 97), (2, "relu", 4, 1)])
def test_fused_network_equals_the_eager_twin_forward_and_backward(triton_cpu, depth, act,
                                                                  degree, n):
    f = _field(net_depth=depth, sigma_activation=act, sh_degree=degree, net_width=32)
    assert mlp_spec(f) is not None
    fast, g_fast = _run(f, "triton", n)
    twin, g_twin = _run(f, "torch", n)
    for a, b in zip(fast, twin):
        torch.testing.assert_close(a, b, **TOL)
    assert set(g_fast) == set(g_twin) and len(g_twin) == 2 * depth + 3   # the table too
    for k in g_twin:
        assert float(g_twin[k].abs().max()) > 0, k
        scale = float(g_twin[k].abs().max())
        torch.testing.assert_close(g_fast[k] / scale, g_twin[k] / scale, **GTOL, msg=k)


def test_fused_network_adds_into_the_gradients_in_place_as_the_trainer_runs_it(triton_cpu):
    """The trainer's mode: three passes add into one ``.grad`` per parameter (kept between
    steps and zeroed by ``zero_grad``), the same sums as the twin's."""
    f = _field()
    twin, g_twin = _run(f, "torch", 120)
    f.grad_in_place = True
    for p in f.parameters():                     # a kept buffer from an earlier step
        p.grad = torch.full_like(p, 0.5)
    f.mlp_backend = "triton"
    pts, d, ws = _inputs(120, 1)
    sigma, rgb = f.radiance(pts, d)
    dens = f.density(pts)
    ((sigma * ws[0]).sum() + (rgb * ws[1]).sum() + (dens * ws[2]).sum()).backward()
    for k, p in f.named_parameters():
        scale = float(g_twin[k].abs().max()) + 0.5
        torch.testing.assert_close(p.grad / scale, (g_twin[k] + 0.5) / scale, **GTOL, msg=k)


def test_fused_network_covers_its_family_and_leaves_the_rest_to_the_twin(triton_cpu):
    from plenoctree.errors import BackendError

    assert mlp_spec(_field(net_width=48)) is None          # not a power of two
    assert mlp_spec(_field(basis="sg")) is None
    assert mlp_spec(_field(net_depth=4, skip_layer=2)) is None
    from plenoctree.nerf._mlp_triton import mlp_backend

    f = _field(net_width=48)
    pts = torch.rand(4, 3, device=DEV)
    f.mlp_backend = "triton"                  # outside the family: the eager network runs
    fast = f.density(pts)
    f.mlp_backend = "torch"
    assert torch.equal(fast, f.density(pts))
    with pytest.raises(BackendError, match="mlp: backend 'triton' covers"):
        mlp_backend(f, pts, None)
    empty = _field()
    empty.mlp_backend = "triton"
    assert empty.density(torch.zeros(0, 3, device=DEV)).shape == (0,)


def test_fused_network_is_one_launch_each_way(triton_cpu):
    """Forward: the encoding and the network, two launches and no torch op of the MLP;
    backward: the network's and the encoding's launches."""
    sys.path.insert(0, str(_BENCH))
    import step_ops

    f = _field()
    f.mlp_backend = "triton"
    f.encoder.backend = "triton"
    pts, d, _ = _inputs(80, 2)
    f.radiance(pts, d)                        # the hash grid's layout, uploaded once
    counter = step_ops.Recorder()
    with counter.region() as c:
        sigma, rgb = f.radiance(pts, d)
        loss = sigma.sum() + rgb.sum()
    # (launches are counted where Triton interprets them: on a GPU only the torch ops)
    assert c.triton == (0 if ON_GPU else 2)
    assert not any(k in c.by_op for k in ("mm", "addmm", "relu", "t"))
    with counter.region() as c:
        loss.backward()
    assert c.triton == (0 if ON_GPU else 2)
    assert not any(k in c.by_op for k in ("mm", "addmm", "t"))
    assert sum(c.syncs.values()) == 0


@pytest.mark.parametrize("k,capacity", [(4, 50), (8, 300), (2, 100000), (4, 1000)])
def test_terminate_kernel_equals_the_twin(triton_cpu, k, capacity):
    """Rays walking their candidates keep and pack what the twin's prefix sums keep, the
    unfilled slots as the twin leaves them (dummy ray, t 0, the box's centre)."""
    rays, grid = _case(3)
    cand = march_fixed(rays, grid, k * capacity, backend="torch")
    sigma = _slab_sigma(cand.points)
    if ON_GPU:                                    # the kernels' inputs on the device
        cand = FixedSamples(*(getattr(cand, f.name).to(DEV) for f in fields(FixedSamples)))
        grid = MarchGrid(grid.step, grid.mask.to(DEV), grid.bbox.to(DEV))
        sigma = sigma.to(DEV)
    twin = terminate_fixed(cand, sigma, grid, 1e-2, capacity, backend="torch")
    fast = terminate_fixed(cand, sigma, grid, 1e-2, capacity, backend="triton")
    _assert_fixed_equal(fast, twin)
    assert torch.equal(fast.complete, twin.complete)
    opaque = terminate_fixed(cand, torch.full_like(sigma, 1e4), grid, 1e-2, capacity,
                             backend="triton")
    _assert_fixed_equal(opaque, terminate_fixed(cand, torch.full_like(sigma, 1e4), grid,
                                                1e-2, capacity, backend="torch"))


@pytest.mark.skipif(ON_GPU, reason="the stand-ins replace Triton's interpreter on the CPU")
def test_step_ops_stand_ins_compute_what_the_kernels_compute(triton_cpu, monkeypatch):
    """``benchmarks/step_ops.py`` counts a training step with stand-ins for the fused network
    (torch) and early termination (numba loops): they must give the kernels' outputs, or the
    counted step would train on something else."""
    sys.path.insert(0, str(_BENCH))
    import step_ops

    ran = []                                      # the stand-ins did run
    for key, fn in list(step_ops._STAND_INS.items()):
        monkeypatch.setitem(step_ops._STAND_INS, key,
                            lambda *a, _fn=fn, _k=key, **k: (ran.append(_k[1]), _fn(*a, **k)))
    f = _field()
    res = []
    for stand_in in (False, True):
        with step_ops.backends_of("cuda") if stand_in else contextlib.nullcontext():
            out, grads = _run(f, "triton", 100)
        res.append((out, grads))
    for a, b in zip(res[0][0], res[1][0]):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-5)
    for k in res[0][1]:
        torch.testing.assert_close(res[0][1][k], res[1][1][k], atol=1e-5, rtol=1e-4, msg=k)
    rays, grid = _case(3)
    cand = march_fixed(rays, grid, 4 * 300, backend="torch")
    sigma = _slab_sigma(cand.points).float()
    fast = terminate_fixed(cand, sigma, grid, 1e-2, 300, backend="triton")
    with step_ops.backends_of("cuda"):
        _assert_fixed_equal(terminate_fixed(cand, sigma, grid, 1e-2, 300, backend="triton"),
                            fast)
    assert {"_mlp_kernel", "_terminate_kernel"} <= set(ran), set(ran)
