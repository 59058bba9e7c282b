"""The fine-tuner's best values so far, kept on disk beside the checkpoint instead of in memory.

A copy of the values is a tree-sized array (1.9 GB for a 9.7 M-leaf SH16 tree, float32), only
read back to restore them after a validation drop or a divergence, or at the end when the last
epoch was not the best. Written to a raw file, it costs no resident memory: the page cache holds
it, and a write takes a few seconds per validation that improves (2.6 s per GB here).

Files: ``<stem>.best-<n>.f32`` (raw float32 in C order, the values' shape), ``n`` counting the
stores. A checkpoint records the ``n`` of the file it needs (:meth:`BestValues.pin`); that file
is kept until the next checkpoint, so a crash at any point leaves a checkpoint with its best
values. ``stem=None`` keeps the copy in memory (no checkpoint then). :class:`DeviceBestValues` keeps
it on a device stepper's device and writes the file only for a checkpoint.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError


class BestValues:
    """The best values of shape ``shape`` so far: :meth:`store` them (or :meth:`adopt` a
    checkpoint's) before :meth:`load`."""

    def __init__(self, shape: tuple[int, ...], dtype: np.dtype, stem: Path | None) -> None:
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self.stem = stem
        self.token = 0              # file number of the current best (0: none yet)
        self.pinned: int | None = None   # file number the last checkpoint refers to
        self._mem: np.ndarray | None = None

    def file(self, token: int) -> Path:
        assert self.stem is not None
        return self.stem.with_name(f"{self.stem.name}.best-{token}.f32")

    def store(self, values: np.ndarray) -> None:
        """Make ``values`` the best ones (a copy: later steps do not change it)."""
        if values.shape != self.shape:
            raise ValueError(f"best values: shape {values.shape}, expected {self.shape}")
        if self.stem is None:
            if self._mem is None:
                self._mem = np.array(values, dtype=self.dtype, copy=True)
            else:
                np.copyto(self._mem, values)
            return
        old, self.token = self.token, self.token + 1
        self.stem.parent.mkdir(parents=True, exist_ok=True)
        np.ascontiguousarray(values, dtype=self.dtype).tofile(self.file(self.token))
        if old and old != self.pinned:
            self.file(old).unlink(missing_ok=True)

    def load(self) -> np.ndarray:
        """The best values (a new array when on disk; the kept copy when in memory)."""
        if self.stem is None:
            assert self._mem is not None
            return self._mem
        return np.fromfile(self._check(self.token), dtype=self.dtype).reshape(self.shape)

    def _check(self, token: int) -> Path:
        path = self.file(token)
        n = int(np.prod(self.shape)) * self.dtype.itemsize
        if token <= 0 or not path.is_file() or path.stat().st_size != n:
            raise ConfigError(f"{path}: the fine-tuner's best values are missing or truncated "
                              f"(expected {n} bytes)")
        return path

    def pin(self) -> int:
        """Make the current file durable (fsync) for a checkpoint about to be written; returns
        its number, which the checkpoint records. Call :meth:`pinned_by` once it is written."""
        if self.stem is None:
            raise ValueError("best values kept in memory cannot be checkpointed")
        fd = os.open(self.file(self.token), os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        return self.token

    def pinned_by(self, token: int) -> None:
        """A checkpoint referring to file ``token`` is written: the one before can go."""
        old, self.pinned = self.pinned, token
        if old is not None and old not in (token, self.token):
            self.file(old).unlink(missing_ok=True)

    def adopt(self, token: int) -> None:
        """Resume: the checkpoint's file ``token`` holds the best values."""
        self._check(int(token))     # ConfigError when the file is gone or truncated
        self.remove(keep=int(token))
        self.token = self.pinned = int(token)

    def remove(self, keep: int | None = None) -> None:
        """Delete the files (all, or all but number ``keep``)."""
        if self.stem is not None:
            _remove(self.stem, None if keep is None else self.file(keep).name)


class DeviceBestValues(BestValues):
    """The best values kept as a copy on the device beside the live ones (a device stepper's
    ``[n_cells, D]`` tensor ``like``): :meth:`store` is a device-to-device copy and
    :meth:`load` returns that tensor, so keeping or restoring the best reads nothing back.
    The file beside the checkpoint is written only when a checkpoint pins the values
    (:meth:`pin`); resumed or stored numpy values go through the file as in
    :class:`BestValues`."""

    def __init__(self, like: Any, stem: Path | None) -> None:
        super().__init__(tuple(like.shape), np.float32, stem)
        self._dev = like.detach().clone()
        self._have = False          # _dev holds the best values
        self._dirty = False         # _dev is newer than the file

    def store(self, values: Any) -> None:
        if isinstance(values, np.ndarray):
            super().store(values)
            self._have = False
            return
        if tuple(values.shape) != self.shape:
            raise ValueError(f"best values: shape {tuple(values.shape)}, expected {self.shape}")
        self._dev.copy_(values)
        self._have = self._dirty = True

    def load(self) -> Any:
        """The best values: the device copy (a tensor), or the file's / memory's (numpy)."""
        return self._dev if self._have else super().load()

    def adopt(self, token: int) -> None:
        super().adopt(token)
        self._have = False

    def pin(self) -> int:
        if self._have and self._dirty and self.stem is not None:
            super().store(self._dev.cpu().numpy())
            self._dirty = False
        return super().pin()


def remove_best_files(checkpoint: Path) -> None:
    """Delete the best values' files of ``checkpoint`` (done with it, or starting afresh)."""
    _remove(Path(checkpoint).with_suffix(""), None)


def _remove(stem: Path, keep: str | None) -> None:
    for p in stem.parent.glob(f"{stem.name}.best-*.f32"):
        if p.name != keep:
            p.unlink(missing_ok=True)
