"""One tree depth limit (``MAX_DEPTH``), enforced by every reader, writer and checker.

Regression: a chain deeper than the renderers' path stacks loaded fine and corrupted memory
in the numba renderer and the fine-tuning kernel.
"""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from plenoctree import Octree, TreeFormatError, export_svox, import_svox, load_tree, save_tree
from plenoctree.compression import compress, load_compressed, save_compressed
from plenoctree.compression.codec import CompressOptions
from plenoctree.octree import MAX_DEPTH, max_steps


def chain_tree(depth: int, depth_limit: int | None = None) -> Octree:
    """Root + a chain: node t is the child of cell (0, 0, 0) of node t - 1; cell depth ``depth``."""
    n = depth + 1
    child = np.zeros((n, 2, 2, 2), dtype=np.int32)
    child[:-1, 0, 0, 0] = 1
    data = np.zeros((n, 2, 2, 2, 4), dtype=np.float32)
    data[..., -1] = 1.0
    return Octree(child, data, offset=np.full(3, 0.5), invradius=np.full(3, 0.5),
                  data_format="RGBA", depth_limit=depth if depth_limit is None else depth_limit)


def _write_npz(path, arrays):
    with zipfile.ZipFile(path, "w") as zf:
        for k, v in arrays.items():
            with zf.open(f"{k}.npy", "w") as f:
                np.lib.format.write_array(f, np.asanyarray(v), allow_pickle=False)
    return path


def test_max_depth_is_supported_by_every_renderer():
    from plenoctree.render.options import QUANT_BITS

    assert MAX_DEPTH == 21                  # the WebGL page: 22 levels (tree.js MAX_VIEWER_DEPTH)
    assert MAX_DEPTH + 1 <= QUANT_BITS - 1  # torch twin's descent loop
    assert MAX_DEPTH + 1 < QUANT_BITS + 1   # numba path stacks hold QUANT_BITS + 1 entries
    assert max_steps(0) == 3 * 2 + 64 and max_steps(MAX_DEPTH) == 1 << 20


def test_max_depth_tree_is_accepted_and_round_trips(tmp_path):
    t = chain_tree(MAX_DEPTH)
    t.check_integrity()
    save_tree(t, tmp_path / "ok.npz")
    assert load_tree(tmp_path / "ok.npz").max_depth == MAX_DEPTH
    export_svox(t, tmp_path / "ok_svox.npz")
    assert import_svox(tmp_path / "ok_svox.npz").max_depth == MAX_DEPTH


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 40])
def test_too_deep_tree_is_refused_everywhere(tmp_path, depth):
    deep = chain_tree(depth)
    with pytest.raises(TreeFormatError, match=f"MAX_DEPTH = {MAX_DEPTH}"):
        deep.check_integrity()
    with pytest.raises(TreeFormatError, match="MAX_DEPTH"):
        save_tree(deep, tmp_path / "deep.npz")
    with pytest.raises(TreeFormatError, match="MAX_DEPTH"):
        export_svox(deep, tmp_path / "deep_svox.npz")
    assert not list(tmp_path.iterdir())            # nothing written
    # Files written by someone else: native, svox and compressed.
    ok = chain_tree(MAX_DEPTH)
    save_tree(ok, tmp_path / "ok.npz")
    with np.load(tmp_path / "ok.npz") as z:
        arrays = {k: z[k] for k in z.files}
    header = json.loads(str(arrays["header"]))
    header["depth_limit"] = depth
    arrays.update(child=deep.child, data=deep.data, header=np.array(json.dumps(header)))
    header["n_nodes"] = deep.n_nodes
    arrays["header"] = np.array(json.dumps(header))
    p = _write_npz(tmp_path / "native_deep.npz", arrays)
    with pytest.raises(TreeFormatError, match=f"{p}: .*MAX_DEPTH"):
        load_tree(p)
    svox = dict(child=deep.child, data=deep.data.astype(np.float16), data_dim=np.int64(4),
                data_format=np.array("RGBA"), invradius3=deep.invradius.astype(np.float32),
                offset=deep.offset.astype(np.float32), depth_limit=np.int64(depth))
    p = _write_npz(tmp_path / "svox_deep.npz", svox)
    with pytest.raises(TreeFormatError, match=f"{p}: .*MAX_DEPTH"):
        import_svox(p)
    with pytest.raises(TreeFormatError, match=f"{p}: .*MAX_DEPTH"):
        load_tree(p)
    ctree = compress(ok, CompressOptions(bits=1))
    save_compressed(ctree, tmp_path / "ok.plnz")
    with np.load(tmp_path / "ok.plnz") as z:
        carr = {k: z[k] for k in z.files}
    carr["child"] = deep.child
    cheader = json.loads(str(carr["header"]))
    cheader["n_nodes"] = deep.n_nodes
    carr["header"] = np.array(json.dumps(cheader))
    carr["sigma"] = np.ones((deep.n_nodes, 2, 2, 2), np.float16)
    carr["quant_map"] = np.zeros((1, deep.n_nodes, 2, 2, 2), np.uint16)
    p = _write_npz(tmp_path / "deep.plnz", carr)
    with pytest.raises(TreeFormatError, match=f"{p}: .*MAX_DEPTH"):
        load_compressed(p)


def test_depth_limit_beyond_max_depth():
    with pytest.raises(TreeFormatError, match="depth_limit 30 exceeds MAX_DEPTH"):
        chain_tree(3, depth_limit=30).check_integrity()


def test_svox_depth_limit_is_clamped_for_shallow_trees(tmp_path):
    t = chain_tree(3)
    export_svox(t, tmp_path / "s.npz")
    with np.load(tmp_path / "s.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["depth_limit"] = np.int64(40)        # svox's refinement cap, not the tree's depth
    p = _write_npz(tmp_path / "s40.npz", arrays)
    assert import_svox(p).depth_limit == MAX_DEPTH


def test_hostile_deep_svox_chain_fails_fast(tmp_path):
    import time

    n = 200_000                                     # one level per node: was a long level walk
    child = np.zeros((n, 2, 2, 2), dtype=np.int32)
    child[:-1, 0, 0, 0] = 1
    p = _write_npz(tmp_path / "chain.npz", dict(
        child=child, data=np.zeros((n, 2, 2, 2, 4), np.float16), data_format=np.array("RGBA"),
        invradius3=np.full(3, 0.5, np.float32), offset=np.full(3, 0.5, np.float32)))
    t0 = time.perf_counter()
    with pytest.raises(TreeFormatError, match="MAX_DEPTH"):
        import_svox(p)
    assert time.perf_counter() - t0 < 30
