"""Level of detail (SH truncation, depth merge, pruning, size fitting) and the codec's CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plenoctree.cli import main
from plenoctree.compression import (LodOptions, fit_to_size, load_any_tree, make_lod,
                                 merge_to_depth, prune, truncate_sh)
from plenoctree.errors import ConfigError
from plenoctree.octree import Octree
from plenoctree.octree.io import save_tree
from plenoctree.sh import eval_sh_bases


def test_truncate_sh_keeps_low_bands():
    t = Octree.dense(1, "SH16", seed=1)
    out = truncate_sh(t, 1)
    assert out.data_format == "SH4" and out.data_dim == 13
    c_old = t.leaf_data()[:, :-1].reshape(-1, 3, 16)
    c_new = out.leaf_data()[:, :-1].reshape(-1, 3, 4)
    np.testing.assert_array_equal(c_new, c_old[:, :, :4])
    np.testing.assert_array_equal(out.data[..., -1], t.data[..., -1])
    # the truncated colour function is the orthogonal projection on degrees <= 1: the
    # residual is orthogonal to every degree-<=1 basis function over the sphere
    d = np.random.default_rng(0).normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    y3 = eval_sh_bases(3, d)
    resid = c_old[0] @ y3.T - c_new[0] @ y3[:, :4].T         # [3, n]
    proj = resid @ y3[:, :4] * (4 * np.pi / len(d))          # Monte-Carlo inner products
    assert np.abs(proj).max() < 0.1 * np.abs(c_old[0]).max()
    assert np.abs(resid).max() > 0.1
    with pytest.raises(ConfigError, match="not SH"):
        truncate_sh(Octree.dense(1, "RGBA", seed=0), 0)


def test_merge_uniform_block_is_exact():
    values = np.zeros((4, 4, 4, 4), np.float32)
    values[..., :3] = [0.3, -0.2, 0.1]
    values[..., 3] = 2.5
    t = Octree.dense(1, "SH1", values=values)
    out = merge_to_depth(t, 0)
    out.check_integrity()
    assert out.n_nodes == 1 and out.max_depth == 0
    np.testing.assert_allclose(out.data[..., :3], np.broadcast_to([0.3, -0.2, 0.1], (1, 2, 2, 2, 3)),
                               atol=1e-6)
    np.testing.assert_allclose(out.data[..., -1], 2.5, rtol=1e-5)


def test_merge_keeps_mean_transmittance_of_axis_rays():
    values = np.zeros((4, 4, 4, 4), np.float32)
    values[0::2, :, :, 3] = 8.0                        # the low-x half of each root cell is dense
    values[..., :3] = 1.0
    t = Octree.dense(1, "RGBA", values=values, radius=1.0)
    out = merge_to_depth(t, 0)
    cell = 0.5                                          # child cell side (world): radius 1 -> 2/4
    sig_x = 8.0 * cell / (2 * cell)                     # along x every column crosses one dense cell
    sig_yz = -np.log(0.5 + 0.5 * np.exp(-2 * 8.0 * cell)) / (2 * cell)   # half the columns
    want = (sig_x + 2 * sig_yz) / 3                     # axes averaged: (4 + 2 * 0.69) / 3
    np.testing.assert_allclose(out.data[0, 0, 0, 0, -1], want, rtol=1e-5)
    np.testing.assert_allclose(out.data[0, 0, 0, 0, :3], 1.0, atol=1e-6)
    assert 0 < want < 8.0


def test_prune_and_collapse():
    t = Octree.dense(2, "SH4", seed=3)
    t.data[..., -1] = 0.0
    t.data[0, 0, 0, 0, -1] = 0.0
    node = t.n_nodes - 1                                # one deep node keeps a dense leaf
    t.data[node, 1, 1, 1, -1] = 50.0
    t.data[1, 0, 0, 0, -1] = 1e-3                       # a nearly transparent leaf
    out = prune(t, 0.01)
    out.check_integrity()
    assert out.n_nodes < t.n_nodes
    sig = out.leaf_data()[:, -1]
    assert (sig > 0).sum() == 1 and sig.max() == pytest.approx(50.0)
    dense = t.leaf_centers()[[t.leaf_data()[:, -1].argmax()]]
    np.testing.assert_allclose(out.query(dense), t.query(dense), rtol=1e-6)


def test_make_lod_and_fit_to_size(tmp_path):
    from plenoctree.datasets.procedural import procedural_tree

    t = procedural_tree(32)
    lod = make_lod(t, LodOptions(sh_degree=2, max_depth=3, prune_alpha=0.01))
    lod.check_integrity()
    assert lod.data_format == "SH9" and lod.max_depth <= 3 and lod.n_leaves < t.n_leaves
    full = tmp_path / "full.npz"
    save_tree(t, full, precision="fp16")
    target = 0.5 * full.stat().st_size / 1e6
    used, size = fit_to_size(t, tmp_path / "small.npz", target)
    assert size <= target * 1e6 and (tmp_path / "small.npz").stat().st_size == size
    assert used != LodOptions()
    load_any_tree(tmp_path / "small.npz").check_integrity()
    with pytest.raises(ConfigError, match="no level of detail fits"):
        fit_to_size(t, tmp_path / "tiny.plnz", 1e-5)
    with pytest.raises(ConfigError):
        LodOptions(prune_alpha=1.5).validated()
    assert list(tmp_path.glob("tmp*")) == []            # candidates are cleaned up


# ---------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def tree_file(tmp_path_factory):
    from plenoctree.datasets.procedural import procedural_tree

    path = tmp_path_factory.mktemp("cli") / "tree.npz"
    save_tree(procedural_tree(32), path, precision="fp16")
    return path


def test_cli_compress_decompress(tree_file, tmp_path, capsys):
    out = tmp_path / "t.plnz"
    js = tmp_path / "rep.json"
    assert main(["compress", str(tree_file), "--out", str(out), "--bits", "12",
                 "--orbit-views", "1", "--size", "32", "--json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "ratio" in text and "PSNR" in text and "compress" in text
    rep = json.loads(js.read_text())
    assert rep["ratio"] > 1 and rep["compressed_bytes"] == out.stat().st_size
    assert rep["psnr_fidelity"] > 35 and rep["options"]["bits"] == 12
    back = tmp_path / "back.npz"
    assert main(["decompress", str(out), "--out", str(back)]) == 0
    assert load_any_tree(back).n_leaves == load_any_tree(tree_file).n_leaves


def test_cli_compress_with_dataset(tree_file, tmp_path, capsys):
    from plenoctree.datasets.procedural import write_procedural_dataset

    data = write_procedural_dataset(tmp_path / "data", n_train=0, n_val=0, n_test=1,
                                    width=24, height=24, n_samples=64)
    assert main(["compress", str(tree_file), "--out", str(tmp_path / "d.plnz"), "--data",
                 str(data), "--downscale", "1", "--json", str(tmp_path / "r.json")]) == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["eval"] == "dataset" and rep["views"] == 1
    assert abs(rep["psnr_change"]) < 1.0 and "change" in capsys.readouterr().out


def test_cli_lod(tree_file, tmp_path, capsys):
    out = tmp_path / "web.plnz"
    assert main(["lod", str(tree_file), "--out", str(out), "--sh-degree", "1",
                 "--max-depth", "3"]) == 0
    t = load_any_tree(out)
    assert t.data_format == "SH4" and t.max_depth <= 3
    assert main(["lod", str(tree_file), "--out", str(tmp_path / "s.npz"),
                 "--target-mb", "0.02"]) == 0
    assert (tmp_path / "s.npz").stat().st_size <= 0.02e6
    assert "MB" in capsys.readouterr().out


def test_cli_errors(tmp_path, capsys):
    bad = tmp_path / "bad.plnz"
    bad.write_bytes(b"not a zip at all")
    assert main(["decompress", str(bad)]) == 1
    assert "bad.plnz" in capsys.readouterr().err
    assert main(["compress", str(bad), "--out", str(tmp_path / "o.plnz")]) == 1
    assert "bad.plnz" in capsys.readouterr().err
    assert main(["compress", str(bad), "--out", str(tmp_path / "o.txt")]) == 1
    assert ".plnz" in capsys.readouterr().err
