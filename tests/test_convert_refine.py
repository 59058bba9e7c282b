"""Adaptive refinement: lowers the error against the field it samples, stays a valid tree."""

from __future__ import annotations

import numpy as np
import pytest

from plenoctree.convert import AnalyticField
from plenoctree.convert.grid import GridSpec, evaluate_density_grid
from plenoctree.convert.refine import (MAX_DEPTH, RefineOptions, compact_tree, field_error,
                                       merge_leaves, refine_tree, subdivide_leaves)
from plenoctree.convert.sampling import SampleOptions, sample_cells
from plenoctree.errors import ConfigError
from plenoctree.octree import Octree, export_svox, import_svox, load_tree, save_tree


@pytest.fixture(scope="module")
def coarse():
    """The procedural NeRF-SH extracted at 16³ (every cell with σ > 0 kept)."""
    f = AnalyticField()
    b = f.scene_bbox
    c, r = (b[0] + b[1]) / 2, (b[1] - b[0]) / 2
    spec = GridSpec.make(c, r, 16)
    mask = evaluate_density_grid(f, spec) > 0
    vals = sample_cells(f, spec, np.flatnonzero(mask), SampleOptions(samples=8))
    return f, Octree.from_grid(vals, mask, c, r, f.data_format)


def _h(tree):
    return float(tree.leaf_sizes()[:, 0].min())


def test_refinement_lowers_the_error_against_the_field(coarse, tmp_path):
    f, tree = coarse
    h = _h(tree)
    e0 = field_error(tree, f, h=h)
    t1, rec = refine_tree(tree, f, RefineOptions(passes=1, threshold=0.02))
    t2, rec2 = refine_tree(tree, f, RefineOptions(passes=2, threshold=0.02))
    e1, e2 = field_error(t1, f, h=h), field_error(t2, f, h=h)
    assert e2 < e1 < 0.9 * e0, (e0, e1, e2)
    assert rec2[0]["subdivided"] > 0 and t2.max_depth == tree.max_depth + 2
    # fewer leaves than refining everything one level (only where the field varies)
    assert rec[0]["subdivided"] < rec[0]["scored"]
    for t in (t1, t2):
        t.check_integrity()
        assert len(np.unique(t.leaf_depths())) >= 2          # mixed depths
    # svox export round trip and native save/load keep every value
    export_svox(t2, tmp_path / "s.npz")
    back = import_svox(tmp_path / "s.npz")
    pts = np.random.default_rng(0).uniform(-1, 1, (5000, 3))
    np.testing.assert_allclose(back.query(pts), t2.query(pts), rtol=1e-3, atol=2e-3)  # fp16
    save_tree(t2, tmp_path / "n.npz")
    np.testing.assert_array_equal(load_tree(tmp_path / "n.npz").query(pts), t2.query(pts))


def test_subdivide_assembles_like_concatenate_then_compact(coarse, monkeypatch):
    """The subdivided tree is written straight into breadth-first order, in blocks of old
    nodes: it equals the slow twin (new nodes appended, then :func:`compact_tree`), also for
    an input with an unreachable node (dropped) and with blocks smaller than the tree."""
    import dataclasses

    from plenoctree.convert import refine as refine_mod

    _, tree = coarse
    (node, i, j, k), _, _, _ = refine_mod._leaf_boxes(tree)
    leaves = np.flatnonzero(tree.leaf_data()[:, -1] > 0)[::3]
    cells = (node[leaves], i[leaves], j[leaves], k[leaves])
    n, m, dim = tree.n_nodes, leaves.size, tree.data_dim
    vals = np.random.default_rng(3).random((8 * m, dim), dtype=np.float32) + 0.5
    stray = dataclasses.replace(                      # one unreachable node at the end
        tree, child=np.concatenate([tree.child, np.zeros((1, 2, 2, 2), np.int32)]),
        data=np.concatenate([tree.data, np.full((1, 2, 2, 2, dim), 7, np.float32)]))
    monkeypatch.setattr(refine_mod, "_COPY_NODES", 5)
    got = refine_mod._with_children(stray, cells, vals, tree.depth_limit + 1)
    # the twin: append the children, point the split cells at them, compact
    child = np.concatenate([tree.child, np.zeros((m, 2, 2, 2), np.int32)])
    data = np.concatenate([tree.data, vals.reshape(m, 2, 2, 2, dim)])
    child[cells] = n + np.arange(m) - cells[0]
    data[cells] = 0
    twin = compact_tree(dataclasses.replace(tree, child=child, data=data,
                                            depth_limit=tree.depth_limit + 1))
    np.testing.assert_array_equal(got.child, twin.child)
    np.testing.assert_array_equal(got.data, twin.data)
    assert got.n_nodes == n + m and got.depth_limit == tree.depth_limit + 1
    got.check_integrity()


def test_subdivide_renders_the_same_where_nothing_changes(coarse):
    """Compaction keeps every value: a tree subdivided nowhere queries identically, and a
    subdivided leaf's children are the field's means in their own boxes."""
    f, tree = coarse
    same = compact_tree(tree)
    pts = np.random.default_rng(1).uniform(-1, 1, (4000, 3))
    np.testing.assert_array_equal(same.query(pts), tree.query(pts))
    leaf = int(np.flatnonzero(tree.leaf_data()[:, -1] > 0)[0])
    t2, spread = subdivide_leaves(tree, [leaf], f, samples=64)
    t2.check_integrity()
    assert t2.n_leaves == tree.n_leaves + 7 and (spread >= 0).sum() == 8
    centre = tree.leaf_centers()[leaf]
    size = tree.leaf_sizes()[leaf]
    kid = centre + 0.25 * size                      # centre of child (1, 1, 1)
    sig, co = f.query(kid[None].astype(np.float32))
    got = t2.query(kid[None])[0]
    assert got[-1] == pytest.approx(float(sig[0]), rel=0.5, abs=0.5)
    far = np.abs(pts - centre).max(axis=1) > size.max()
    np.testing.assert_array_equal(t2.query(pts[far]), tree.query(pts[far]))


def test_merge_undoes_subdivision_of_a_uniform_region():
    """Eight equal siblings merge back into one leaf; differing ones do not."""
    t = Octree.dense(1, "SH1")                     # root + 8 nodes, 4³ leaves
    t.data[..., -1] = 0.0
    leaves = t.child == 0
    t.data[leaves, -1] = 2.0
    t.data[leaves, 0] = 0.3
    merged, n = merge_leaves(t, tol=1e-3)
    merged.check_integrity()
    assert n == 8 and merged.n_leaves == 8 and merged.n_nodes == 1
    t.data[1, 0, 0, 0, -1] = 50.0                          # one child differs
    merged, n = merge_leaves(t, tol=1e-3)
    assert n == 7 and merged.n_nodes == 2


def test_depth_limit_and_bad_options(coarse):
    f, tree = coarse
    t, _ = refine_tree(tree, f, RefineOptions(passes=3, threshold=0.0,
                                              max_depth=tree.max_depth + 1, max_fraction=0.05))
    assert t.max_depth == tree.max_depth + 1 <= MAX_DEPTH
    with pytest.raises(ConfigError, match="max_fraction"):
        refine_tree(tree, f, RefineOptions(max_fraction=0))
    with pytest.raises(ConfigError, match="passes"):
        refine_tree(tree, f, RefineOptions(passes=-1))
    from plenoctree.convert.refine import RefineConfig

    with pytest.raises(ConfigError, match="--averaging"):
        RefineConfig(averaging="median").validated()


def test_opacity_average_of_new_leaves(coarse):
    # the same samples (same seeds) valued with the opacity-preserving average: never denser
    # than the mean, equal where the field is uniform, lower where a surface cuts the child
    f, tree = coarse
    tm, _ = refine_tree(tree, f, RefineOptions(passes=1, threshold=0.02, averaging="mean"))
    to, _ = refine_tree(tree, f, RefineOptions(passes=1, threshold=0.02, averaging="opacity"))
    to.check_integrity()
    assert to.n_leaves == tm.n_leaves
    sm, so = tm.leaf_data()[:, -1], to.leaf_data()[:, -1]
    assert np.all(so <= sm * (1 + 1e-5) + 1e-6)
    assert np.mean(np.isclose(so, sm, rtol=1e-4)) > 0.5 and np.any(so < 0.9 * sm)


def test_refine_cli_on_a_run(tmp_path, capsys):
    """``plenoctree refine TREE --run-dir RUN``: a tiny (untrained) NeRF-SH run, its extracted
    tree, the refined tree saved with its JSON record; a bad option names itself."""
    from nerf_fixtures import tiny_run_and_tree

    from plenoctree.cli import main
    from plenoctree.octree import load_tree

    _, _, tree = tiny_run_and_tree(tmp_path)
    out = tmp_path / "ref.npz"
    assert main(["refine", str(tree), "--run-dir", str(tmp_path / "run"), "--out", str(out),
                 "--threshold", "0", "--max-fraction", "0.1", "--eval-views", "1"]) == 0
    text = capsys.readouterr().out
    assert "leaves" in text and "test PSNR before" in text
    before, after = load_tree(tree), load_tree(out)
    after.check_integrity()
    assert after.n_leaves > before.n_leaves and after.max_depth == before.max_depth + 1
    assert (tmp_path / "ref.refine.json").exists()
    assert main(["refine", str(tree), "--run-dir", str(tmp_path / "run"),
                 "--max-fraction", "2"]) == 1
    assert "max-fraction" in capsys.readouterr().err
