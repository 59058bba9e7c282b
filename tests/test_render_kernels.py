"""The numba kernels on every kind of tree the project makes, against the torch twin (the spec):
mixed leaf depths (refinement), image-shaped rays (2-D tiles), NDC trees, SG/RGBA formats, the
fine-tuning forward (same traversal), per-ray counters, and trees deeper than the stack."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from plenoctree.octree import MAX_DEPTH, Octree
from plenoctree.render import RenderOptions, render_rays
from plenoctree.render.options import parse_data_format


def _subdivide(tree: Octree, frac: float, seed: int) -> Octree:
    """Split a random ``frac`` of the leaves into 8 children holding the parent's value plus
    noise (what adaptive refinement does); nodes are appended, so offsets stay positive."""
    rng = np.random.default_rng(seed)
    child = tree.child.reshape(-1, 8).copy()
    data = tree.data.reshape(-1, 8, tree.data_dim).copy()
    node, cell = np.nonzero(child == 0)
    pick = rng.random(node.size) < frac
    node, cell = node[pick], cell[pick]
    n0 = child.shape[0]
    new = n0 + np.arange(node.size)
    child[node, cell] = (new - node).astype(np.int32)
    kids = np.repeat(data[node, cell][:, None, :], 8, axis=1)
    kids = kids + rng.normal(scale=0.3, size=kids.shape).astype(np.float32)
    kids[..., -1] = np.abs(kids[..., -1])
    kids[rng.random(kids.shape[:2]) < 0.3, -1] = 0.0          # some empty children
    data[node, cell] = 0.0
    child = np.concatenate([child, np.zeros((node.size, 8), np.int32)])
    data = np.concatenate([data, kids.astype(np.float32)])
    out = Octree(child.reshape(-1, 2, 2, 2), data.reshape(-1, 2, 2, 2, tree.data_dim),
                 tree.offset, tree.invradius, tree.data_format, tree.extra_data,
                 depth_limit=tree.max_depth + 1)
    return out


def _grid_tree(fmt: str, seed: int, res: int = 16, occ: float = 0.3) -> Octree:
    rng = np.random.default_rng(seed)
    b = 1 if fmt == "RGBA" else int(fmt[2:])
    dim = 4 if fmt == "RGBA" else 3 * b + 1
    values = rng.normal(size=(res, res, res, dim)).astype(np.float32)
    values[..., -1] = np.abs(values[..., -1]) * rng.uniform(1.0, 10.0)
    mask = rng.random((res, res, res)) < occ
    extra = None
    if fmt.startswith("SG"):
        mu = rng.normal(size=(b, 3))
        mu /= np.linalg.norm(mu, axis=1, keepdims=True)
        extra = np.c_[rng.uniform(0.5, 8.0, b), mu].astype(np.float32)
    return Octree.from_grid(values, mask, 0.1, 1.2, fmt, extra)


def _image_rays(tree: Octree, h: int, w: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    from plenoctree.datasets import generate_rays
    from plenoctree.datasets.procedural import look_at

    rng = np.random.default_rng(seed)
    v = rng.normal(size=3)
    eye = tree.center + 3.5 * float(tree.radius.max()) * v / np.linalg.norm(v)
    return generate_rays(look_at(eye, tree.center), 2.0 * w, 2.0 * w, w / 2, h / 2, w, h)


def _compare(tree: Octree, o: np.ndarray, d: np.ndarray, opts: RenderOptions) -> None:
    fast = render_rays(tree, o, d, opts, backend="numba")
    t64 = Octree(tree.child, tree.data.astype(np.float64), tree.offset, tree.invradius,
                 tree.data_format, tree.extra_data, depth_limit=tree.depth_limit)
    ref = render_rays(t64, o, d, opts, backend="torch")
    assert float(ref.alpha.max()) > 0.3                     # the rays do hit something
    assert (fast.rgb.double() - ref.rgb).abs().max() <= 1e-4
    assert (fast.alpha.double() - ref.alpha).abs().max() <= 1e-4
    rel = (fast.depth.double() - ref.depth).abs() / ref.depth.clamp(min=1)
    assert rel.max() <= 1e-4


@pytest.mark.parametrize("fmt", ["SH9", "SG4", "RGBA"])
def test_mixed_depth_tree_image_tiles_match_twin(fmt):
    tree = _subdivide(_subdivide(_grid_tree(fmt, seed=len(fmt)), 0.3, 1), 0.2, 2)
    tree.check_integrity()
    assert len(set(tree.leaf_depths().tolist())) >= 3          # really mixed depths
    o, d = _image_rays(tree, 27, 37, seed=3)                   # not multiples of the tile
    _compare(tree, o, d, RenderOptions(stop_thresh=0.01))
    _compare(tree, o, d, RenderOptions(stop_thresh=0.0, sh_min=1, background=(0.2, 0.3, 0.4)))


def test_image_tiles_equal_flat_rays():
    tree = _subdivide(_grid_tree("SH4", seed=5), 0.3, 4)
    o, d = _image_rays(tree, 19, 45, seed=1)
    img = render_rays(tree, o, d, backend="numba")                       # [H, W]: 2-D tiles
    flat = render_rays(tree, o.reshape(-1, 3), d.reshape(-1, 3), backend="numba")
    for a, b in zip((img.rgb, img.depth, img.alpha), (flat.rgb, flat.depth, flat.alpha)):
        torch.testing.assert_close(a.reshape(b.shape), b, rtol=0, atol=0)


def _ff_tree(tmp_path) -> tuple[Octree, object]:
    """A small forward-facing NDC tree (32³) and the NDC cameras of its 24×18 scene."""
    from plenoctree.datasets.forward_facing import (forward_facing_tree,
                                                    write_forward_facing_dataset)
    from plenoctree.datasets.llff import load_llff

    root = write_forward_facing_dataset(tmp_path / "ff", n_images=3, width=24, height=18,
                                        n_samples=16)
    return forward_facing_tree(root, 32), load_llff(root, split="all").cameras


def test_ndc_forward_facing_tree_matches_twin(tmp_path):
    tree, cams = _ff_tree(tmp_path)
    assert cams.ndc
    o, d = cams.rays(1)
    _compare(tree, o, d, RenderOptions())


def _cameras_around(tree: Octree, h: int, w: int, n: int, seed: int):
    from plenoctree.datasets import Cameras
    from plenoctree.datasets.procedural import look_at

    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    eyes = tree.center + 3.5 * float(tree.radius.max()) * v / np.linalg.norm(v, axis=1)[:, None]
    c2w = np.stack([look_at(e, tree.center) for e in eyes])
    return Cameras(c2w, rng.uniform(1.5, 2.5, n) * w, rng.uniform(1.5, 2.5, n) * w,
                   w / 2 + rng.uniform(-2, 2, n), h / 2 + rng.uniform(-2, 2, n), w, h)


def _same_as_array_rays(tree: Octree, cams, i: int, opts: RenderOptions, twin: bool) -> None:
    from plenoctree.render import render_image

    got = render_image(tree, cams, i, opts, backend="numba")           # rays made in-kernel
    o, d = cams.rays(i)
    ref = render_rays(tree, o, d, opts, backend="numba")               # rays from arrays
    assert got.rgb.shape == (cams.height, cams.width, 3)
    for a, b in zip((got.rgb, got.depth, got.alpha), (ref.rgb, ref.depth, ref.alpha)):
        torch.testing.assert_close(a, b, rtol=0, atol=2e-6)
    if twin:
        _compare(tree, o, d, opts)


def test_render_image_makes_the_rays_in_the_kernel():
    tree = _subdivide(_grid_tree("SH9", seed=4), 0.3, 5)
    cams = _cameras_around(tree, 21, 30, 3, seed=6)        # per-camera fx, fy, cx, cy
    for i in range(3):
        _same_as_array_rays(tree, cams, i, RenderOptions(), twin=i == 0)


def test_render_image_makes_ndc_rays_in_the_kernel(tmp_path):
    from plenoctree.errors import ConfigError
    from plenoctree.render import render_image

    tree, cams = _ff_tree(tmp_path)
    for i in range(len(cams)):
        _same_as_array_rays(tree, cams, i, RenderOptions(), twin=i == 1)
    back = cams.c2w.copy()
    back[0, :3, 2] *= -1.0                                # camera 0 looks up +z: no NDC rays
    back[0, :3, 0] *= -1.0
    from plenoctree.datasets import Cameras
    bad = Cameras(back, cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height, ndc=True)
    with pytest.raises(ConfigError, match="NDC"):
        render_image(tree, bad, 0, backend="numba")


def test_finetune_forward_shares_the_render_traversal():
    from plenoctree.optim._render_grad import forward_numba, kernel_args

    tree = _subdivide(_grid_tree("SH4", seed=9), 0.4, 7)
    o, d = _image_rays(tree, 16, 16, seed=2)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    opts = RenderOptions(stop_thresh=0.01)
    data2 = np.ascontiguousarray(tree.data.reshape(-1, tree.data_dim))
    rgb = forward_numba(kernel_args(tree, opts), data2, o, d)
    ref = render_rays(tree, o, d, opts, backend="numba").rgb.numpy()
    np.testing.assert_allclose(rgb, ref, atol=2e-6)


def test_ray_counters():
    from plenoctree.render._render_numba import STAT_NAMES, ray_stats_numba

    tree = _subdivide(_grid_tree("SH1", seed=4, occ=0.2), 0.3, 3)
    o, d = _image_rays(tree, 12, 12, seed=5)
    s = ray_stats_numba(tree, o.reshape(-1, 3), d.reshape(-1, 3), RenderOptions(stop_thresh=0.0))
    col = dict(zip(STAT_NAMES, s.T))
    hit = col["hit"] > 0
    assert hit.mean() > 0.5 and (col["stopped"] == 0).all()
    assert (col["leaves"][~hit] == 0).all() and (col["leaves"][hit] > 0).all()
    assert (col["leaves"] >= col["sigma_leaves"]).all()
    assert (col["sigma_leaves"] >= col["negligible"]).all()
    assert (col["descent"] >= col["leaves"]).all() and col["sigma_leaves"].sum() > 0
    # A ray missing the box visits nothing.
    miss = ray_stats_numba(tree, np.float32([[50, 50, 50]]), np.float32([[1, 0, 0]]),
                           RenderOptions())
    assert miss.sum() == 0


def _chain_tree(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """A chain of ``levels`` nodes, each the child of cell 0 of the previous one, with a σ > 0
    leaf at the bottom: deeper than any loader accepts when ``levels > MAX_DEPTH + 1``."""
    child = np.zeros((levels, 8), np.int32)
    child[:-1, 0] = 1
    data = np.zeros((levels, 8, 4), np.float32)
    data[-1, :, :] = [0.5, 0.5, 0.5, 1e3]
    data[:-1, 1:, :] = [0.0, 0.0, 0.0, 0.5]
    return child.reshape(-1, 2, 2, 2), data.reshape(-1, 2, 2, 2, 4)


def test_kernels_bound_the_descent_on_too_deep_trees():
    """A tree deeper than the path stack must not corrupt memory in any numba kernel: the
    descent stops at MAX_DEPTH (the loaders reject such trees anyway)."""
    from plenoctree.optim._render_grad import SparseGrad, fused_mse_numba, kernel_args
    from plenoctree.render._render_numba import prepare, render_rays_numba

    child, data = _chain_tree(MAX_DEPTH + 12)
    off, inv = np.zeros(3), np.ones(3)
    o = np.float32([[1e-9, 1e-9, -1.0]] * 64 + [[0.3, 0.7, -1.0]] * 64)
    d = np.float32([[0.0, 0.0, 1.0]] * 128)

    class _T:
        pass

    t = _T()
    t.child, t.data, t.offset, t.invradius, t.data_format = child, data, off, inv, "RGBA"
    t.extra_data, t.depth_limit = None, MAX_DEPTH + 11
    info = parse_data_format("RGBA", 4)
    rgb, depth, alpha = render_rays_numba(prepare(t, info, RenderOptions()), o, d)
    assert np.isfinite(rgb).all() and np.isfinite(alpha).all()
    assert (alpha[64:] > 0).all()                              # the shallow leaves render
    data2 = np.ascontiguousarray(data.reshape(-1, 4))
    args = kernel_args(t, RenderOptions())
    buf = SparseGrad(data2.shape[0], 4, np.float32)
    sse = fused_mse_numba(args, data2, o, d, np.zeros((128, 3), np.float32), 1.0, buf)
    assert np.isfinite(sse) and np.isfinite(buf.grad).all()


def test_per_thread_scratch_rows_never_share_a_cache_line():
    """pad_scratch rounds every per-thread row up to SCRATCH_PAD (two 64-byte lines), so two
    threads' rows of the kernels' scratch cannot share a line (false sharing made two threads as
    slow as one in the fine-tuning kernel)."""
    from plenoctree.render._march_numba import SCRATCH_PAD, pad_scratch

    assert SCRATCH_PAD >= 128
    for n, size in ((1, 8), (4, 8), (8, 8), (16, 8), (17, 8), (25, 4), (49, 4), (1000, 8)):
        padded = pad_scratch(n, size)
        assert padded >= n and (padded * size) % SCRATCH_PAD == 0
        assert padded * size - n * size < SCRATCH_PAD
    # the rows as the fine-tuning kernel lays them out: row t's used bytes end a full line
    # before row t + 1's start
    row = pad_scratch(4, 8) * 8
    assert row - 4 * 8 >= 64


def test_marching_kernels_compile_without_value_changing_fastmath_flags():
    """Every numba kernel that marches uses MARCH_MATH (no reassociation, contraction or
    approximate functions): with fastmath=True the render kernel loaded from numba's disk cache
    was optimised differently from the freshly compiled one, and a few lookups of a lego view
    landed in the neighbouring leaf (4.6e-3 from the twin). The colour dot product
    (leaf_logits, float32, not on the march's path) may reassociate."""
    from plenoctree.optim import _render_grad_numba as g
    from plenoctree.render import _march_numba as m
    from plenoctree.render import _render_numba as r

    assert set(m.MARCH_MATH) <= {"nnan", "ninf", "nsz"}
    for f in (m.ray_start, m.next_leaf, m.look_ahead, m.basis_values, r._render_one,
              r._camera_ray, r._render_kernel, r._stats_kernel, g._trace_one, g._backprop_one,
              g.grad_kernel):
        flags = f.targetoptions.get("fastmath")
        assert flags is not True and set(flags or ()) <= set(m.MARCH_MATH), f.py_func.__name__
    assert "inline" not in m.leaf_logits.targetoptions    # compiled with its own flags
