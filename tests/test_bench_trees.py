"""The speed benchmarks' tree and view choice (benchmarks/_trees.py): a
forward-facing (NDC) tree is timed from its own capture's cameras, never from orbit views; and
benchmarks/kernel_cache_check.py (the render kernel's image does not depend on numba's cache)."""

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
