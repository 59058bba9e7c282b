"""Compressed ``.plnz`` header and ``extra_data`` checks: one clear error, never a traceback."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plenoctree import Octree, TreeFormatError
from plenoctree.compression import compress, load_any_tree, load_compressed, save_compressed
from plenoctree.compression.codec import CompressOptions


def _good(tmp_path, fmt="SH4"):
    extra = None
    if fmt.startswith("SG"):
        extra = np.array([[2.0, 0.0, 0.0, 1.0], [3.0, 1.0, 0.0, 0.0]], np.float32)
    t = Octree.dense(2, fmt, seed=0, extra_data=extra)
    p = tmp_path / f"good_{fmt}.plnz"
    save_compressed(compress(t, CompressOptions(bits=2)), p)
    with np.load(p) as z:
        return p, {k: z[k] for k in z.files}


def _write(path, arrays):
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


@pytest.mark.parametrize("key,value", [
    ("sigma_thresh", "abc"), ("sigma_thresh", [1]), ("sigma_thresh", -1.0),
    ("bits", "16"), ("retain", 1.5), ("n_nodes", 5), ("data_format", 7), ("format", "zip"),
    ("depth_limit", "deep"), ("bbox", 3),
])
def test_plnz_header_values_are_type_checked(tmp_path, key, value):
    _, arrays = _good(tmp_path)
    header = json.loads(str(arrays["header"]))
    header[key] = value
    arrays["header"] = np.array(json.dumps(header))
    p = _write(tmp_path / "bad_header.plnz", arrays)
    with pytest.raises(TreeFormatError, match=f"{p}: header '?{key}'?"):
        load_compressed(p)


@pytest.mark.parametrize("extra", [
    np.array(["a", "b"]),                                  # strings: was a ValueError traceback
    np.zeros((3, 4), np.float32),                          # wrong lobe count
    np.full((2, 4), np.nan, np.float32),                   # non-finite lobes
    np.zeros((2, 4), np.int32),
])
def test_plnz_extra_data_is_checked(tmp_path, extra):
    _, arrays = _good(tmp_path, "SG2")
    arrays["extra_data"] = extra
    p = _write(tmp_path / "bad_extra.plnz", arrays)
    with pytest.raises(TreeFormatError, match=f"{p}: 'extra_data'"):
        load_any_tree(p)


def test_good_plnz_still_loads(tmp_path):
    for fmt in ("SH4", "SG2", "RGBA"):
        p, _ = _good(tmp_path, fmt)
        assert load_any_tree(p).data_format == fmt
