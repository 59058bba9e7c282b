"""Renderers on hostile in-memory trees and extreme geometry: clear errors, no crash, no hang."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from plenoctree import Octree
from plenoctree.errors import ConfigError
from plenoctree.octree import check as check_mod
from plenoctree.render import render_rays


def small_tree() -> Octree:
    return Octree.dense(2, "RGBA", seed=0)


def rays(n=16):
    rng = np.random.default_rng(0)
    o = np.tile(np.array([[0.1, 0.2, -3.0]]), (n, 1))
    d = np.tile(np.array([[0.0, 0.0, 1.0]]), (n, 1)) + rng.normal(0, 0.05, (n, 3))
    return o, d


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_render_rays_rejects_bad_child_offsets(backend):
    t = small_tree()
    t.child[0, 0, 0, 0] = 10 ** 8                   # was a segfault (numba)
    with pytest.raises(ConfigError, match=r"render: tree: child\[0, 0, 0, 0\] = 100000000"):
        render_rays(t, *rays(), backend=backend)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_render_rays_rejects_too_deep_in_memory_tree(backend):
    from test_reliability_depth import chain_tree

    deep = chain_tree(40)                           # overran the numba path stack
    o = np.array([[0.01, 0.01, -3.0]])
    d = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(ConfigError, match="MAX_DEPTH"):
        render_rays(deep, o, d, backend=backend)


def test_topology_checked_once_per_tree_and_version(monkeypatch):
    calls = []
    real = check_mod.check_child
    monkeypatch.setattr(check_mod, "check_child", lambda *a, **k: (calls.append(1), real(*a, **k)))
    t = small_tree()
    o, d = rays()
    for _ in range(3):
        render_rays(t, o, d, backend="torch")
    assert len(calls) == 1
    t2 = small_tree()
    render_rays(t2, o, d, backend="torch")           # another tree object: checked again
    assert len(calls) == 2
    t.child = t.child.copy()                         # replaced array: checked again
    render_rays(t, o, d, backend="torch")
    assert len(calls) == 3
    t.child[0, 1, 1, 1] = 10 ** 8                    # edited in place: noticed
    with pytest.raises(ConfigError):
        render_rays(t, o, d, backend="numba")
    tc = small_tree()
    tc.child = torch.from_numpy(tc.child)
    render_rays(tc, o, d, backend="torch")
    tc.child[0, 0, 0, 0] = -5                        # torch in-place edit bumps _version
    with pytest.raises(ConfigError, match="negative"):
        render_rays(tc, o, d, backend="torch")


# ---------------------------------------------------------------------- extreme geometry
def _saved_with(tmp_path, name, **changes):
    from plenoctree import save_tree

    t = small_tree()
    save_tree(t, tmp_path / "ok.npz")
    with np.load(tmp_path / "ok.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    p = tmp_path / name
    np.savez(p, **arrays)
    return p


@pytest.mark.parametrize("key,value,problem", [
    ("invradius3", [1e300, 1e300, 1e300], "invradius"),       # was a hang (ray never advances)
    ("invradius3", [1.0, 1.0, 1e-160], "invradius"),          # 1e160-wide slab: was a hang
    ("offset", [0.5, 0.5, 1e300], "offset"),
])
def test_load_bounds_box_values(tmp_path, key, value, problem):
    from plenoctree import TreeFormatError, load_tree

    p = _saved_with(tmp_path, "extreme.npz", **{key: np.array(value)})
    with pytest.raises(TreeFormatError, match=f"{p}: {problem} .* is outside"):
        load_tree(p)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_render_rays_refuses_extreme_geometry(backend):
    t = small_tree()
    t.invradius = np.full(3, 1e300)
    with pytest.raises(ConfigError, match="invradius .* is outside"):
        render_rays(t, np.zeros((2, 3)), np.ones((2, 3)), backend=backend)
    t = small_tree()
    with pytest.raises(ConfigError, match="origins: a ray starts at tree coordinate 5e\\+299"):
        render_rays(t, np.array([[0.0, 0.0, -1e300]]), np.array([[0.0, 0.0, 1.0]]),
                    backend=backend)
    far = render_rays(t, np.array([[0.0, 0.0, -1e7]]), np.array([[0.0, 0.0, 1.0]]),
                      backend=backend)                       # far but within the bound: renders
    assert float(far.alpha[0]) > 0.5


_TWIN_HANG_SCRIPT = """
import numpy as np, torch
from plenoctree import Octree
from plenoctree.render._torch_impl import render_rays_torch
t = Octree.dense(3, "RGBA", seed=0)
t.data[..., -1] = 1e-3
d = np.random.default_rng(0).normal(size=(32, 3))
t.offset = np.full(3, 0.5)
for inv in ([1e300] * 3, [1.0, 1.0, 1e-160]):
    t.invradius = np.array(inv)
    out = render_rays_torch(t, torch.zeros(32, 3, dtype=torch.float64), torch.tensor(d))
    assert torch.isfinite(out.rgb).all()
t.invradius = np.ones(3)
out = render_rays_torch(t, torch.tensor([[0.0, 0.0, -1e300]], dtype=torch.float64),
                        torch.tensor([[1e-3, 1e-3, 1.0]], dtype=torch.float64))
print("done")
"""


def test_torch_twin_always_terminates():
    """Overflow-free step epsilon, forced progress and the per-ray step cap (twin, unchecked
    input). Run in a subprocess: before the fix these rays never advanced (a hang)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _TWIN_HANG_SCRIPT], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "done" in r.stdout, r.stderr[-2000:]


def test_step_cap_stops_a_ray(monkeypatch):
    from plenoctree.render import _torch_impl

    t = small_tree()
    t.data[..., -1] = 0.2                             # 8 cells of 0.25 world units on the ray
    o, d = np.array([[0.1, 0.2, -3.0]]), np.array([[0.0, 0.0, 1.0]])
    full = render_rays(t, o, d, backend="torch")
    np.testing.assert_allclose(float(full.alpha[0]), 1 - np.exp(-0.2 * 2.0), rtol=1e-5)
    monkeypatch.setattr(_torch_impl, "max_steps", lambda depth: 1)
    capped = render_rays(t, o, d, backend="torch")     # stops after one segment, T kept
    np.testing.assert_allclose(float(capped.alpha[0]), 1 - np.exp(-0.2 * 0.25), rtol=1e-5)


# ---------------------------------------------------------------------- huge values
def test_huge_finite_values_are_refused_at_load(tmp_path):
    from plenoctree import TreeFormatError, load_tree, save_tree
    from plenoctree.octree.limits import MAX_ABS_VALUE

    t = Octree.dense(2, "SH16", seed=0)
    t.data[1, 0, 0, 0, 3] = 3e38                       # rendered NaN with exit 0
    with pytest.raises(TreeFormatError, match="exceeds MAX_ABS_VALUE"):
        save_tree(t, tmp_path / "huge.npz")
    p = tmp_path / "huge2.npz"
    ok = Octree.dense(2, "SH16", seed=0)
    save_tree(ok, tmp_path / "ok.npz")
    with np.load(tmp_path / "ok.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["data"] = t.data
    np.savez(p, **arrays)
    with pytest.raises(TreeFormatError, match=f"{p}: data\\[1, 0, 0, 0, 3\\] = .* exceeds"):
        load_tree(p)
    # At the bound every backend renders finite values.
    rng = np.random.default_rng(0)
    big = Octree.dense(3, "SH25", seed=0)
    big.data[:] = np.sign(rng.normal(size=big.data.shape)) * np.float32(MAX_ABS_VALUE)
    big.data[..., -1] = MAX_ABS_VALUE
    big.check_integrity()
    o = np.tile([[0.0, 0.0, -3.0]], (64, 1))
    d = rng.normal(size=(64, 3)) * 0.2 + [0.0, 0.0, 1.0]
    for backend in ("numba", "torch"):
        out = render_rays(big, o, d, backend=backend)
        assert all(bool(torch.isfinite(x).all()) for x in (out.rgb, out.depth, out.alpha))


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_differentiable_render_checks_in_memory_trees(backend):
    from plenoctree.optim.autograd import render_rays_differentiable

    t = small_tree()
    t.child[0, 1, 0, 0] = 10 ** 8
    data = torch.zeros(t.data.shape, dtype=torch.float32, requires_grad=True)
    with pytest.raises(ConfigError, match="render: tree: child"):
        render_rays_differentiable(data, t, *rays(), backend=backend)
