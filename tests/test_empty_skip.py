"""Empty-space skipping of the numba renderer (render/empty_skip.py): the skip regions hold no
σ > 0 leaf, the images equal those without skipping and the twin's, and rays visit fewer
leaves."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from test_render_kernels import _compare, _ff_tree, _grid_tree, _image_rays, _subdivide

from plenoctree.octree import Octree
from plenoctree.render import CpuTree, RenderOptions, render_image, render_rays, tree_to_device
from plenoctree.render._spec import flat_tree as _flat
from plenoctree.render.empty_skip import skip_tables


def _sparse_tree(seed: int, fmt: str = "SH4") -> Octree:
    """A ball in a large empty box (a real scene's shape), mixed depths (3 levels) and some
    empty leaves among the occupied ones."""
    res = 32
    rng = np.random.default_rng(seed)
    b = 1 if fmt == "RGBA" else int(fmt[2:])
    values = rng.normal(size=(res, res, res, 4 if fmt == "RGBA" else 3 * b + 1))
    values[..., -1] = np.abs(values[..., -1]) * 3.0
    x = (np.arange(res) + 0.5) / res - 0.5
    r = np.sqrt(x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2)
    mask = (r < 0.3) & (r > 0.2)
    tree = Octree.from_grid(values.astype(np.float32), mask, 0.1, 1.2, fmt)
    tree = _subdivide(_subdivide(tree, 0.2, seed + 1), 0.2, seed + 2)
    tree.check_integrity()
    return tree


def _grown(tree: Octree, levels: int) -> Octree:
    """``tree`` in a root ``2^levels`` times as wide about its centre (a far-field tree's
    shape: the content in a small box at the root's centre)."""
    from plenoctree.convert.shells import _box_leaves
    from plenoctree.octree.build import tree_from_leaves

    d, c, v = _box_leaves(tree, levels)
    return tree_from_leaves(d, c, v, tree.center, tree.radius * 2.0 ** levels, tree.data_format)


@pytest.mark.parametrize("levels", [0, 3])
def test_skip_regions_hold_no_occupied_leaf(levels):
    """Every (empty leaf, ray octant): the leaf's box with its forward faces pushed by the
    table's skip overlaps no σ > 0 leaf (brute force over all pairs); in a grown tree the
    leaves of the box skip on nested grids as fine as the box's own."""
    tree = _sparse_tree(3)
    tree = _grown(tree, levels) if levels else tree
    child, data = _flat(tree.child, tree.data)       # the kernels' flat arrays
    t = skip_tables(child, data)
    assert t.grid_bits == min(8, tree.max_depth + 1) and t.skip.shape[1] == 9
    assert t.skip[:, 8].max() == max(0, tree.max_depth + 1 - 8)
    depth, corner, size = tree._leaf_geometry()
    node, i, j, k = tree.leaf_indices()
    cell = node * 8 + i * 4 + j * 2 + k
    sigma = data[cell, -1]
    full = sigma > 0
    lo_f, hi_f = corner[full], corner[full] + size[full, None]
    rows = -t.child[cell] - 1
    has = t.child[cell] < 0
    assert has.sum() > 50 and (sigma[has] <= 0).all()          # only empty leaves skip
    assert (has == ~full).all()          # every empty leaf is marked (row 0: no skip)
    assert (t.skip[0] == 0).all() and (rows[has] > 0).sum() < has.sum()
    assert (t.child[t.child >= 0] == child[t.child >= 0]).all()
    pushed = 0
    for leaf in np.flatnonzero(has):
        unit = 2.0 ** -(t.grid_bits + int(t.skip[rows[leaf], 8]))
        for o in range(8):
            r = int(t.skip[rows[leaf], o]) * unit
            if r == 0:
                continue
            pushed += 1
            lo, hi = corner[leaf].copy(), corner[leaf] + size[leaf]
            for a, sgn in enumerate(((o >> 2) & 1, (o >> 1) & 1, o & 1)):
                if sgn:
                    hi[a] += r
                else:
                    lo[a] -= r
            overlap = np.all((np.minimum(hi, hi_f) - np.maximum(lo, lo_f)) > 1e-12, axis=1)
            assert not overlap.any(), (leaf, o)
    assert pushed > 100


def test_skip_grows_only_forward_into_free_space():
    """One occupied finest cell in an otherwise empty 8³ tree: a leaf right behind it (in the
    ray's direction) cannot skip, the same leaf seen by rays going away from it can."""
    res = 8
    values = np.zeros((res, res, res, 4), np.float32)
    values[4, 4, 4] = (1, 1, 1, 5.0)
    mask = np.ones((res, res, res), bool)
    tree = Octree.from_grid(values, mask, 0.0, 1.0, "RGBA")
    child, data = _flat(tree.child, tree.data)       # the kernels' flat arrays
    t = skip_tables(child, data)
    _, corner, _ = tree._leaf_geometry()
    node, i, j, k = tree.leaf_indices()
    at = np.flatnonzero(np.all(np.abs(corner - np.array([3, 4, 4]) / res) < 1e-9, axis=1))
    cell = int(node[at[0]] * 8 + i[at[0]] * 4 + j[at[0]] * 2 + k[at[0]])   # just -x of it
    row = -int(t.child[cell]) - 1
    assert row >= 0
    plus_x = [o for o in range(8) if (o >> 2) & 1]
    # Going +x the occupied cell is the next one: no skip; going -x: free space ahead.
    assert all(t.skip[row, o] == 0 for o in plus_x)
    assert all(t.skip[row, o] >= 1 for o in range(8) if o not in plus_x)


@pytest.mark.parametrize("fmt", ["SH9", "RGBA"])
def test_skipping_renders_the_same_image(fmt):
    tree = _sparse_tree(5, fmt)
    fast = tree_to_device(tree, "cpu")
    assert isinstance(fast, CpuTree) and fast.empty_skip.skip.shape[0] > 10
    assert tree_to_device(fast, "cpu") is fast
    assert not np.shares_memory(fast.child, tree.child)       # its topology: a private copy
    for seed in (1, 2):
        o, d = _image_rays(tree, 23, 29, seed=seed)
        for opts in (RenderOptions(), RenderOptions(stop_thresh=0.0, background=(0.2, 0.3, 0.4))):
            a = render_rays(tree, o, d, opts, backend="numba")
            b = render_rays(fast, o, d, opts, backend="numba")
            for x, y in zip((a.rgb, a.depth, a.alpha), (b.rgb, b.depth, b.alpha)):
                torch.testing.assert_close(x, y, rtol=0, atol=2e-6)
    _compare(tree, o, d, RenderOptions())        # and the plain kernel equals the twin


def test_render_image_uses_the_tables_and_the_twin_ignores_them():
    from test_render_kernels import _cameras_around

    tree = _sparse_tree(7)
    fast = tree_to_device(tree, "cpu")
    cams = _cameras_around(tree, 17, 22, 2, seed=3)
    for i in range(2):
        a = render_image(tree, cams, i, backend="numba")
        b = render_image(fast, cams, i, backend="numba")
        c = render_image(fast, cams, i, backend="torch")
        torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=2e-6)
        torch.testing.assert_close(a.rgb.double(), c.rgb.double(), rtol=0, atol=1e-4)


def test_skipping_visits_fewer_leaves():
    from plenoctree.render._render_numba import STAT_NAMES, ray_stats_numba

    tree = _sparse_tree(11)
    o, d = _image_rays(tree, 24, 24, seed=4)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    args = (tree, o, d, RenderOptions())
    plain = dict(zip(STAT_NAMES, ray_stats_numba(*args).T))
    fast = dict(zip(STAT_NAMES, ray_stats_numba(*args, skip=tree_to_device(tree, "cpu")
                                                .empty_skip).T))
    for k in ("hit", "stopped", "sigma_leaves"):                # the same σ > 0 segments
        np.testing.assert_array_equal(plain[k], fast[k])
    assert (fast["leaves"] <= plain["leaves"]).all()
    assert fast["leaves"].sum() < 0.97 * plain["leaves"].sum()     # lego 256³: 0.69


def test_ndc_tree_skips_too(tmp_path):
    tree, cams = _ff_tree(tmp_path)
    fast = tree_to_device(tree, "cpu")
    for i in range(len(cams)):
        a = render_image(tree, cams, i, backend="numba")
        b = render_image(fast, cams, i, backend="numba")
        torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=2e-6)


def test_a_tree_without_empty_leaves_and_a_bad_tree():
    from plenoctree.errors import ConfigError

    tree = _grid_tree("SH1", seed=2, res=4, occ=1.0)
    tree.data[..., -1] = 1.0
    fast = tree_to_device(tree, "cpu")
    assert (fast.empty_skip.child >= 0).all()
    o, d = _image_rays(tree, 8, 8, seed=1)
    torch.testing.assert_close(render_rays(fast, o, d).rgb, render_rays(tree, o, d).rgb,
                               rtol=0, atol=0)
    bad = Octree(tree.child.copy(), tree.data, tree.offset, tree.invradius, tree.data_format)
    bad.child[0, 0, 0, 0] = -3
    with pytest.raises(ConfigError):
        tree_to_device(bad, "cpu")


def test_finetuning_steps_are_the_same_with_skipping():
    """The fine-tuner skips the empty leaves of its starting values (they get no gradient, so
    they stay empty): the steps equal those of the plain traversal, and σ ≤ 0 stays."""
    from plenoctree.optim._render_grad import kernel_args
    from plenoctree.optim._steppers import NumbaStepper

    tree = _sparse_tree(13)
    o, d = _image_rays(tree, 20, 20, seed=6)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    tgt = np.random.default_rng(0).random((o.shape[0], 3)).astype(np.float32)
    d2 = np.ascontiguousarray(tree.data, np.float32).reshape(-1, tree.data_dim)
    plain = NumbaStepper(d2.copy(), kernel_args(tree, RenderOptions()), "adam", 1e-2)
    fast = NumbaStepper(d2.copy(), kernel_args(tree, RenderOptions(), skip_from=d2), "adam", 1e-2)
    assert (fast.args.child < 0).sum() > 10 and (plain.args.child >= 0).all()
    for _ in range(4):
        a, _ = plain.step(o, d, tgt, 1.0 / o.shape[0])
        b, _ = fast.step(o, d, tgt, 1.0 / o.shape[0])
        assert b == pytest.approx(a, rel=1e-6)
    np.testing.assert_allclose(fast.values(), plain.values(), rtol=0, atol=1e-6)
    empty = (tree.child.reshape(-1) == 0) & (d2[:, -1] <= 0)
    assert (fast.values()[empty, -1] <= 0).all()
