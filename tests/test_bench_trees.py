"""The speed benchmarks' tree and view choice (benchmarks/_trees.py): a
forward-facing (NDC) tree is timed from its own capture's cameras, never from orbit views; and
benchmarks/kernel_cache_check.py (the render kernel's image does not depend on numba's cache);
benchmarks/direct_leaves.py's levels."""

from __future__ import annotations

from pathlib import Path

import pytest

from plenoctree.datasets.forward_facing import forward_facing_tree, write_forward_facing_dataset
from plenoctree.octree import save_tree

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture()
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(_BENCH))
    import _trees

    return _trees


def test_ndc_tree_file_needs_its_data(bench, tmp_path):
    trees = bench
    data = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=18, height=12,
                                        n_samples=8)
    path = tmp_path / "ff.npz"
    save_tree(forward_facing_tree(data, 8), path)
    with pytest.raises(SystemExit, match="forward-facing .NDC. tree; pass --data"):
        trees.load_bench_tree(str(path))
    tree, desc = trees.load_bench_tree(str(path), data=str(data))
    assert desc["data"] == str(data) and tree.ndc is not None
    cams, idx = trees.data_cameras(desc["data"], 4)           # the test split: 0 and 8
    assert cams.ndc and len(cams) == 2 and idx == [0, 1]
    cams, idx = trees.data_cameras(desc["data"], 4, "all")
    assert len(cams) == 9 and idx == [0, 3, 5, 8]


def test_render_kernel_same_image_compiled_or_loaded_from_cache(bench, tmp_path):
    """benchmarks/kernel_cache_check.py: two processes sharing an empty NUMBA_CACHE_DIR (one
    compiles the render kernel, one loads it) draw the same image, within 1e-4 of the twin.
    With fastmath=True the two differed (1.3e-5 here, 4.6e-3 on a lego view)."""
    import kernel_cache_check

    out = tmp_path / "check.json"
    assert kernel_cache_check.main(["--tree", "procedural", "--size", "96", "--out",
                                    str(out)]) == 0
    assert '"fresh_vs_cached": 0.0' in out.read_text()


def test_direct_leaves_levels_copy_the_parent_and_empty_the_faint(monkeypatch):
    """benchmarks/direct_leaves.py: the dense start is uniform (opacity ~0.01 a cell, colour 0);
    the next level's cells hold their parent's values, faint cells empty."""
    import numpy as np

    monkeypatch.syspath_prepend(str(_BENCH))
    import direct_leaves as dl

    c, r = np.array([0.1, -0.2, 0.3]), np.array([1.0, 0.5, 0.75])
    start = dl.dense_start(c, r, 4)
    data = start.leaf_data()
    assert start.n_leaves == 64 and start.data_format == "SH9"
    np.testing.assert_allclose(data[:, -1] * 0.5, 0.01, rtol=1e-6)    # σ · side: opacity ~0.01
    assert not data[:, :-1].any()
    rng = np.random.default_rng(0)
    values = rng.normal(size=data.shape).astype(np.float32)
    values[:, -1] = np.abs(values[:, -1])
    values[0, -1] = 0.0                                        # one empty parent
    start.set_leaf_data(values)
    fine = dl.upsample(start, 8, 1e-3)
    centers = fine.leaf_centers()
    got = fine.leaf_data()
    want = start.query(centers)
    full = got[:, -1] > 0
    np.testing.assert_array_equal(got[full], want[full])       # children copy their parent
    assert fine.n_leaves < 512 and (want[~full][:, -1] <= 0).all()   # the empty parent merged
