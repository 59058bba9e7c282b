"""benchmarks/shell_lookups.py's counters on a hand-made row of leaves: lookups, σ > 0
lookups and empty runs (the floor of an exact empty-space skip); and render_speed.py's
whole-frame comparison of the renderer with and without its skip tables."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from plenoctree.octree.tree import Octree
from plenoctree.render import RenderOptions, tree_to_device

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture()
def shell_lookups(monkeypatch):
    monkeypatch.syspath_prepend(str(_BENCH))
    import shell_lookups

    return shell_lookups


def _row_tree(sigmas: list[float]) -> Octree:
    """A 4³ grid over [-1, 1]³ (RGBA, grey) whose row at y = z = -0.25 has σ ``sigmas`` along
    +x; every other leaf empty."""
    tree = Octree.dense(1, "RGBA")
    tree.data[...] = 0.0
    tree.data[..., :3] = 0.5
    centres = np.asarray(tree.leaf_centers())            # world units
    node, i, j, k = tree.leaf_indices()
    for x, s in zip((-0.75, -0.25, 0.25, 0.75), sigmas):
        m = np.flatnonzero(np.all(np.isclose(centres, [x, -0.25, -0.25]), axis=1))
        assert m.size == 1
        tree.data[node[m], i[m], j[m], k[m], 3] = s
    return tree


@pytest.mark.parametrize("skip", [True, False])
@pytest.mark.parametrize("sigmas, runs, sigma_lookups, empty_leaves", [
    ([0.0, 0.0, 0.1, 0.0], 2, 1, 3),      # an empty run of two leaves, a thin leaf, a run of one
    ([0.1, 0.0, 0.1, 0.1], 1, 3, 1),      # one empty leaf between thin ones
    ([0.0, 0.0, 0.0, 0.0], 1, 0, 4),      # nothing but empty space: one run
    ([0.0, 50.0, 0.0, 0.0], 1, 1, 1),     # the ray stops in the opaque leaf
])
def test_empty_runs_along_one_ray(shell_lookups, sigmas, runs, sigma_lookups, empty_leaves,
                                  skip):
    tree = _row_tree(sigmas)
    o = np.array([[-3.0, -0.25, -0.25]], np.float32)
    d = np.array([[1.0, 0.0, 0.0]], np.float32)
    fast = tree_to_device(tree, "cpu") if skip else SimpleNamespace(empty_skip=None)
    counts, n = shell_lookups.lookups_by_ring(tree, fast, [(o, d)], RenderOptions())
    assert n == 1
    total = counts.sum(axis=0)
    assert total[4] == runs and total[3] == sigma_lookups
    if skip:                                     # each run takes at least one lookup
        assert runs <= total[0] <= empty_leaves
    else:                                        # one lookup per empty leaf crossed
        assert total[0] == empty_leaves


def test_render_speed_compares_whole_frames_with_and_without_skip_tables(monkeypatch):
    # benchmarks/render_speed.py's skip_deviation: every pixel of every view, both paths
    monkeypatch.syspath_prepend(str(_BENCH))
    import _trees
    import render_speed

    tree = _row_tree([0.0, 0.0, 3.0, 0.0])
    cams = _trees.orbit_cameras(2, 24)
    dev = render_speed.skip_deviation(tree, tree_to_device(tree, "cpu"), cams, [0, 1],
                                      RenderOptions())
    assert dev["pixels"] == 2 * 24 * 24
    assert dev["pixels_over_1e-4"] == 0 and dev["max_abs_diff_rgb"] < 1e-4
    # a tree whose values differ from the prepared one shows up pixel by pixel
    other = _row_tree([0.0, 0.0, 30.0, 0.0])
    dev = render_speed.skip_deviation(other, tree_to_device(tree, "cpu"), cams, [0, 1],
                                      RenderOptions())
    assert dev["pixels_over_1e-4"] > 0 and dev["max_abs_diff_rgb"] > 1e-2


def test_render_speed_scores_the_fast_rule_against_the_exact_frames(monkeypatch):
    # benchmarks/render_speed.py's fast_psnr: the `fast` path's frames against the exact ones
    monkeypatch.syspath_prepend(str(_BENCH))
    import _trees
    import render_speed

    tree = _row_tree([0.0, 2.0, 30.0, 0.0])
    fast = tree_to_device(tree, "cpu")
    cams = _trees.orbit_cameras(2, 24)
    exact = RenderOptions(background=(0.0, 0.0, 0.0))
    assert render_speed.fast_psnr(fast, cams, [0, 1], exact, exact) == 200.0      # identical
    renorm = RenderOptions(background=(0.0, 0.0, 0.0), stop_thresh=0.5, renormalize=True)
    db = render_speed.fast_psnr(fast, cams, [0, 1], exact, renorm)
    assert 10.0 < db < 80.0                      # the rule changed the stopped rays, not all
