"""The fine-tuner's best values on disk: stores, checkpoint pinning, resume, clean-up."""

import numpy as np
import pytest

from plenoctree.errors import ConfigError
from plenoctree.optim._best import BestValues, remove_best_files


def _files(tmp_path):
    return sorted(p.name for p in tmp_path.glob("ft.ckpt.best-*.f32"))


def test_store_load_and_pinning(tmp_path):
    rng = np.random.default_rng(0)
    a, b, c = (rng.normal(size=(50, 7)).astype(np.float32) for _ in range(3))
    best = BestValues(a.shape, a.dtype, tmp_path / "ft.ckpt")
    best.store(a)
    a[0, 0] = 99.0                        # a copy: later changes of the values do not leak in
    assert best.load()[0, 0] != 99.0 and _files(tmp_path) == ["ft.ckpt.best-1.f32"]
    best.store(b)                         # the previous file goes: no checkpoint needs it
    np.testing.assert_array_equal(best.load(), b)
    assert _files(tmp_path) == ["ft.ckpt.best-2.f32"]
    token = best.pin()                    # a checkpoint refers to file 2 ...
    best.pinned_by(token)
    best.store(c)                         # ... so it stays beside the new best
    assert _files(tmp_path) == ["ft.ckpt.best-2.f32", "ft.ckpt.best-3.f32"]
    best.store(b)
    assert _files(tmp_path) == ["ft.ckpt.best-2.f32", "ft.ckpt.best-4.f32"]
    best.pinned_by(best.pin())            # the next checkpoint: file 2 is free
    assert _files(tmp_path) == ["ft.ckpt.best-4.f32"]

    # resume: a fresh store adopts the checkpoint's file and drops the others
    (tmp_path / "ft.ckpt.best-9.f32").write_bytes(b"stale")
    again = BestValues(a.shape, a.dtype, tmp_path / "ft.ckpt")
    again.adopt(4)
    np.testing.assert_array_equal(again.load(), b)
    assert _files(tmp_path) == ["ft.ckpt.best-4.f32"]
    remove_best_files(tmp_path / "ft.ckpt.npz")
    assert _files(tmp_path) == []


def test_missing_or_truncated_file_is_a_clear_error(tmp_path):
    best = BestValues((10, 3), np.float32, tmp_path / "ft.ckpt")
    with pytest.raises(ConfigError, match="best-5.f32.*missing or truncated"):
        best.adopt(5)
    (tmp_path / "ft.ckpt.best-5.f32").write_bytes(b"\0" * 12)
    with pytest.raises(ConfigError, match="expected 120 bytes"):
        best.adopt(5)


def test_in_memory_without_a_checkpoint():
    v = np.arange(12, dtype=np.float32).reshape(4, 3)
    best = BestValues(v.shape, v.dtype, None)
    best.store(v)
    v += 1
    np.testing.assert_array_equal(best.load(), np.arange(12).reshape(4, 3))
    with pytest.raises(ValueError):
        best.pin()
