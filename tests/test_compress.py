"""The web codec: median cut (numba kernel vs torch twin), compress/decompress, the .plnz file."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plenoctree.compression import (CompressOptions, compress, decompress, is_compressed_file,
                                 load_any_tree, load_compressed, median_cut, save_compressed)
from plenoctree.compression.quantize import _median_cut_torch, median_cut_many
from plenoctree.errors import ConfigError, TreeFormatError
from plenoctree.octree import Octree
from plenoctree.octree.io import load_tree, save_tree


# ---------------------------------------------------------------------------- median cut
def _points(n: int, seed: int, ties: bool) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    if ties:                                    # runs of equal values and repeated triplets
        pts[: n // 3] = np.round(pts[: n // 3])
        pts[n // 3: n // 2, 1] = 0.5
    return pts


@pytest.mark.parametrize("n,bits,ties", [(1, 3, False), (2, 1, False), (7, 4, True),
                                         (1000, 6, True), (5000, 8, False), (300, 10, True)])
def test_median_cut_matches_twin(n, bits, ties):
    pts = _points(n, n + bits, ties)
    cb, idx = median_cut(pts, bits)
    cb_ref, idx_ref = _median_cut_torch(pts, bits)
    assert cb.shape == (1 << bits, 3) and idx.dtype == np.uint16
    np.testing.assert_array_equal(idx, idx_ref)
    np.testing.assert_allclose(cb, cb_ref, rtol=0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(*[st.sampled_from([-1.0, 0.0, 0.25, 2.0, 3.5])] * 3),
                min_size=1, max_size=60), st.integers(1, 7))
def test_median_cut_twin_property(rows, bits):
    pts = np.asarray(rows, dtype=np.float32)
    cb, idx = median_cut(pts, bits)
    cb_ref, idx_ref = _median_cut_torch(pts, bits)
    np.testing.assert_array_equal(idx, idx_ref)
    np.testing.assert_allclose(cb, cb_ref, atol=1e-12)
    # identical triplets always share a bucket, and each bucket's entry is its members' mean
    _, inverse = np.unique(pts, axis=0, return_inverse=True)
    for u in np.unique(inverse):
        assert len(set(idx[inverse.reshape(-1) == u].tolist())) == 1
    for b in np.unique(idx):
        np.testing.assert_allclose(cb[b], pts[idx == b].astype(np.float64).mean(0), atol=1e-6)


def test_median_cut_quality_and_edge_cases():
    pts = _points(4000, 0, ties=False)
    cb, idx = median_cut(pts, 12)               # 4096 buckets >= 4000 distinct points: exact
    np.testing.assert_allclose(cb[idx], pts, atol=1e-6)
    cb, idx = median_cut(pts, 4)
    err = np.abs(cb[idx] - pts).mean()
    assert 0 < err < 0.5
    same = np.tile(np.float32([[0.1, -2.0, 3.0]]), (50, 1))
    cb, idx = median_cut(same, 8)               # no split on zero range: one bucket, exact
    assert set(idx.tolist()) == {0}
    np.testing.assert_allclose(cb[0], same[0], atol=1e-7)
    outlier = np.concatenate([np.zeros((999, 3), np.float32), [[6.0, 0.0, 0.0]]]).astype(np.float32)
    cb, idx = median_cut(outlier, 1)            # the lone outlier gets its own bucket
    assert idx[-1] != idx[0] and cb[idx[-1], 0] == pytest.approx(6.0)
    cbs, idxs = median_cut_many(np.stack([pts[:100], pts[100:200]]), 5)
    for k in range(2):
        np.testing.assert_array_equal(idxs[k], median_cut(pts[100 * k:100 * (k + 1)], 5)[1])
    cbs, idxs = median_cut_many(np.zeros((3, 0, 3), np.float32), 4)
    assert cbs.shape == (3, 16, 3) and idxs.shape == (3, 0)


def test_median_cut_bad_args():
    with pytest.raises(ConfigError, match="bits"):
        median_cut(np.zeros((4, 3)), 17)
    with pytest.raises(ConfigError, match="bits"):
        median_cut(np.zeros((4, 3)), 0)
    with pytest.raises(ValueError, match="shape"):
        median_cut(np.zeros((4, 2)), 4)
    with pytest.raises(ValueError, match="NaN"):
        median_cut(np.full((4, 3), np.nan), 4)


# ---------------------------------------------------------------------------- codec
def _tree(fmt: str = "SH9", depth: int = 2, seed: int = 0) -> Octree:
    t = Octree.dense(depth, fmt, seed=seed)
    t.data[..., -1][t.data[..., -1] < 1.0] = 0.0      # some empty leaves
    return t


@pytest.mark.parametrize("fmt", ["SH1", "SH4", "SH16", "SH25", "RGBA", "SG3"])
def test_roundtrip_exact_when_codebook_is_large(fmt):
    t = _tree(fmt)
    ct = compress(t, CompressOptions(bits=16))
    out = decompress(ct)
    out.check_integrity()
    np.testing.assert_array_equal(out.child, t.child)
    np.testing.assert_allclose(out.offset, t.offset)
    np.testing.assert_allclose(out.invradius, t.invradius)
    assert out.data_format == t.data_format and out.depth_limit == t.depth_limit
    if t.extra_data is not None:
        np.testing.assert_array_equal(out.extra_data, t.extra_data)
    on = (t.child == 0) & (t.data[..., -1] > 0)
    assert ct.n_kept == on.sum() < t.n_leaves
    # fewer leaves than codebook entries: every coefficient survives up to float16 rounding
    np.testing.assert_allclose(out.data[on], t.data[on].astype(np.float16).astype(np.float32),
                               rtol=0, atol=2e-3)
    assert (out.data[~on] == 0).all()


def test_quantisation_error_and_retain():
    t = _tree("SH9", depth=3)
    on = (t.child == 0) & (t.data[..., -1] > 0)
    full = decompress(compress(t, CompressOptions(bits=6)))
    err = np.abs(full.data[on][:, :-1] - t.data[on][:, :-1])
    assert 0.01 < err.mean() < 1.0
    kept = decompress(compress(t, CompressOptions(bits=6, retain=2)))
    coef = lambda tr: tr.data[on][:, :-1].reshape(-1, 3, 9)     # noqa: E731
    np.testing.assert_allclose(coef(kept)[:, :, :2], coef(t)[:, :, :2], atol=2e-3)
    assert np.abs(coef(kept)[:, :, 2:] - coef(t)[:, :, 2:]).mean() > 0.01
    with pytest.raises(ConfigError, match="retain"):
        compress(t, CompressOptions(retain=10))


def test_sigma_thresh_drops_leaves_and_input_is_untouched():
    t = _tree("SH4")
    before = t.data.copy()
    ct = compress(t, CompressOptions(sigma_thresh=3.0))
    np.testing.assert_array_equal(t.data, before)
    out = decompress(ct)
    sig = t.data[..., -1]
    leaf = t.child == 0
    assert (out.data[leaf & (sig <= 3.0)] == 0).all()
    assert (out.data[..., -1][leaf & (sig > 3.0)] > 0).all()
    with pytest.raises(ConfigError):
        compress(t, CompressOptions(sigma_thresh=-1))


def test_decompressed_tree_renders_like_the_original():
    from plenoctree.compression_report import tree_orbit_cameras
    from plenoctree.metrics import psnr
    from plenoctree.render import render_image

    from plenoctree.datasets.procedural import procedural_tree
    t = procedural_tree(32)
    out = decompress(compress(t, CompressOptions(bits=10)))
    cams = tree_orbit_cameras(t, n=2, size=48)
    for i in range(2):
        a = render_image(t, cams, i).rgb.numpy()
        b = render_image(out, cams, i).rgb.numpy()
        assert psnr(b, a) > 40.0


# ---------------------------------------------------------------------------- file
def test_file_roundtrip_and_layout(tmp_path):
    t = _tree("SH16")
    ct = compress(t, CompressOptions(bits=8, retain=1))
    path = tmp_path / "t.plnz"
    size = save_compressed(ct, path, level=9)
    assert size == path.stat().st_size and is_compressed_file(path)
    with zipfile.ZipFile(path) as zf:                  # DEFLATE zip of .npy, np.load-able
        assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in zf.infolist())
    z = np.load(path, allow_pickle=False)
    for key, dt in (("quant_colors", np.float16), ("quant_map", np.uint16),
                    ("sigma", np.float16), ("data_retained", np.float16), ("child", np.int32)):
        assert z[key].dtype == dt
    assert z["quant_colors"].shape == (15, 256, 3) and z["quant_map"].shape == (15,) + t.child.shape
    header = json.loads(str(z["header"]))
    assert header["format"] == "plenoctree-compressed" and header["bits"] == 8
    assert header["retain"] == 1 and str(z["data_format"]) == "SH16"
    back = load_compressed(path)
    for key in ("child", "sigma", "quant_colors", "quant_map", "data_retained"):
        np.testing.assert_array_equal(getattr(back, key), getattr(ct, key))
    np.testing.assert_array_equal(load_any_tree(path).data, decompress(ct).data)
    raw = tmp_path / "t.npz"
    save_tree(t, raw)
    assert not is_compressed_file(raw)
    np.testing.assert_array_equal(load_any_tree(raw).data, t.data)
    with pytest.raises(TreeFormatError, match="compressed"):
        load_tree(path)                                # the tree loader points here
    with pytest.raises(TreeFormatError, match="not a compressed tree"):
        load_compressed(raw)


def _svox_compressed(t: Octree, path, capacity_extra: int = 3) -> None:
    """Write ``t`` the way the original octree/compression.py does (no header, spare rows)."""
    ct = compress(t, CompressOptions(bits=16))
    cap = t.n_nodes + capacity_extra
    pad = lambda a, axis=0: np.concatenate(      # noqa: E731
        [a, np.zeros(a.shape[:axis] + (capacity_extra,) + a.shape[axis + 1:], a.dtype)], axis)
    np.savez_compressed(path, child=pad(t.child), invradius3=t.invradius.astype(np.float32),
                        offset=t.offset.astype(np.float32), data_dim=np.int64(t.data_dim),
                        data_format=np.array(t.data_format), quant_colors=ct.quant_colors,
                        quant_map=pad(ct.quant_map, 1), sigma=pad(ct.sigma))
    assert cap == t.n_nodes + capacity_extra


def test_reads_original_svox_compressed_files(tmp_path):
    t = _tree("SH4")
    path = tmp_path / "svox_min.npz"
    _svox_compressed(t, path)
    assert is_compressed_file(path)
    out = load_any_tree(path)
    assert out.n_nodes == t.n_nodes
    np.testing.assert_array_equal(out.child, t.child)
    np.testing.assert_allclose(out.offset, t.offset, atol=1e-6)
    np.testing.assert_array_equal(out.data, decompress(compress(t, CompressOptions(bits=16))).data)


def _rewrite(src, dst, **changes) -> None:
    z = dict(np.load(src, allow_pickle=False))
    z.update(changes)
    with open(dst, "wb") as f:                      # a file object: no ".npz" appended
        np.savez_compressed(f, **z)


def test_bad_files_raise_clear_errors(tmp_path):
    t = _tree("SH4")
    good = tmp_path / "good.plnz"
    save_compressed(compress(t, CompressOptions(bits=4)), good)
    data = good.read_bytes()
    cases = {
        "truncated.plnz": data[: len(data) // 2],
        "foreign.plnz": b"\x89PNG\r\n\x1a\n" + bytes(200),
        "empty.plnz": b"",
    }
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(TreeFormatError, match=name):
            load_compressed(tmp_path / name)
    z = np.load(good)
    qm = z["quant_map"].copy()
    on = z["sigma"] > 0
    qm[0][on] = 100                                   # codebook has 16 entries
    _rewrite(good, tmp_path / "index.plnz", quant_map=qm)
    with pytest.raises(TreeFormatError, match=r"index\.plnz: codebook index 100 out of range"):
        load_compressed(tmp_path / "index.plnz")
    _rewrite(good, tmp_path / "version.plnz", plnz_version=np.int64(7))
    with pytest.raises(TreeFormatError, match="plnz_version 7"):
        load_compressed(tmp_path / "version.plnz")
    _rewrite(good, tmp_path / "shape.plnz", sigma=z["sigma"][:-1])
    with pytest.raises(TreeFormatError, match="sigma"):
        load_compressed(tmp_path / "shape.plnz")
    z2 = dict(np.load(good))
    del z2["quant_map"]
    with open(tmp_path / "missing.plnz", "wb") as f:
        np.savez(f, **z2)
    with pytest.raises(TreeFormatError, match="quant_map"):
        load_compressed(tmp_path / "missing.plnz")
    _rewrite(good, tmp_path / "nan.plnz",
             quant_colors=np.full_like(z["quant_colors"], np.nan))
    with pytest.raises(TreeFormatError, match="NaN"):
        load_compressed(tmp_path / "nan.plnz")


def test_import_compiles_nothing():
    code = ("import sys, plenoctree, plenoctree.compression, plenoctree.viewer; "
            "print('plenoctree.compression._median_cut_numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
