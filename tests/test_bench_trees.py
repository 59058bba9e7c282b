"""The speed benchmarks' tree and view choice (benchmarks/_trees.py, render_speed.py): a
forward-facing (NDC) tree is timed from its own capture's cameras, never from orbit views."""

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
    import render_speed

    return _trees, render_speed


def test_ndc_tree_file_needs_its_data(bench, tmp_path):
    trees, rs = bench
    data = write_forward_facing_dataset(tmp_path / "ff", n_images=9, width=18, height=12,
                                        n_samples=8)
    path = tmp_path / "ff.npz"
    save_tree(forward_facing_tree(data, 8), path)
    with pytest.raises(SystemExit, match="forward-facing .NDC. tree; pass --data"):
        trees.load_bench_tree(str(path))
    tree, desc = trees.load_bench_tree(str(path), data=str(data))
    assert desc["data"] == str(data) and tree.ndc is not None
    cams, idx = rs.data_cameras(desc["data"], 4)              # the test split: 0 and 8
    assert cams.ndc and len(cams) == 2 and idx == [0, 1]
    cams, idx = rs.data_cameras(desc["data"], 4, "all")
    assert len(cams) == 9 and idx == [0, 3, 5, 8]
