"""A defensive ``.npz`` reader: every malformed file becomes a ``TreeFormatError``.

``np.load`` trusts the file (array headers decide how much memory is allocated, pickled object
arrays, odd exceptions from zipfile/zlib). This reader opens the zip itself, parses every
member's ``.npy`` header first (cheap), rejects object arrays, checks that each member's
declared size matches its header, and reads an array only when asked. All failures raise
``TreeFormatError("<path>: <problem>")``.
"""

from __future__ import annotations

import json
import os
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from .errors import TreeFormatError

__all__ = ["NpzReader"]

_MAX_DEFLATE_RATIO = 1100     # DEFLATE cannot expand data by more than ~1032:1


class NpzReader:
    """Read-only view of an ``.npz`` archive; use as a context manager.

    Attributes:
        name: the path as given (used in messages).
        meta: ``{key: (shape, dtype)}`` of every well-formed ``.npy`` member.
        pickled: keys whose arrays hold Python objects (never loaded).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.name = str(path)
        if not self.path.exists():
            self.fail("no such file")
        if not self.path.is_file():
            self.fail("not a regular file")
        try:
            self._zip = zipfile.ZipFile(self.path)
        except zipfile.BadZipFile:
            self.fail("not an .npz file (not a zip archive)")
        except Exception as e:      # OSError, ValueError, ... from a damaged archive
            self.fail(f"cannot open as an .npz (zip) archive: {type(e).__name__}: {e}")
        self.meta: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
        self.pickled: set[str] = set()
        self._info: dict[str, tuple[zipfile.ZipInfo, bool]] = {}
        try:
            for info in self._zip.infolist():
                if not info.filename.endswith(".npy") or info.is_dir():
                    continue
                self._scan(info)
        except TreeFormatError:
            self.close()
            raise
        except Exception as e:      # zlib.error, EOFError, struct.error, ... (damaged member)
            self.close()
            self.fail(f"damaged .npz archive: {type(e).__name__}: {e}")

    # ------------------------------------------------------------------ internals
    def fail(self, problem: str) -> None:
        """Raise ``TreeFormatError("<path>: <problem>")``."""
        raise TreeFormatError(f"{self.name}: {problem}")

    def _scan(self, info: zipfile.ZipInfo) -> None:
        key = info.filename[:-4]
        with self._zip.open(info) as f:
            try:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    self.fail(f"array {key!r}: unsupported .npy version {version}")
            except TreeFormatError:
                raise
            except (ValueError, SyntaxError, TypeError) as e:
                self.fail(f"array {key!r}: bad .npy header ({e})")
            header_len = f.tell()
        if dtype.hasobject:
            self.pickled.add(key)
            return
        count = 1
        for s in shape:
            count *= int(s)
        archive_size = self.path.stat().st_size
        ratio = 1 if info.compress_type == zipfile.ZIP_STORED else _MAX_DEFLATE_RATIO
        if info.compress_size > archive_size or info.file_size > ratio * info.compress_size + 64:
            self.fail(f"array {key!r}: corrupt zip entry (declares {info.file_size} bytes "
                      f"from {info.compress_size} stored bytes in a {archive_size}-byte file)")
        if count * dtype.itemsize != info.file_size - header_len:
            self.fail(f"array {key!r}: truncated or corrupt (header says {list(shape)} "
                      f"{dtype}, {count * dtype.itemsize} bytes; member holds "
                      f"{info.file_size - header_len})")
        self.meta[key] = (tuple(int(s) for s in shape), dtype)
        self._info[key] = (info, bool(fortran))

    def close(self) -> None:
        self._zip.close()

    def __enter__(self) -> NpzReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ access
    def __contains__(self, key: str) -> bool:
        return key in self.meta or key in self.pickled

    def keys(self) -> list[str]:
        return sorted(set(self.meta) | self.pickled)

    def require(self, *keys: str) -> None:
        """Fail naming every missing key."""
        missing = [k for k in keys if k not in self]
        if missing:
            self.fail(f"missing keys {missing} (found {self.keys()})")

    def shape(self, key: str) -> tuple[int, ...]:
        self._usable(key)
        return self.meta[key][0]

    def dtype(self, key: str) -> np.dtype:
        self._usable(key)
        return self.meta[key][1]

    def _usable(self, key: str) -> None:
        if key in self.pickled:
            self.fail(f"array {key!r} holds Python objects (pickled data is never loaded)")
        if key not in self.meta:
            self.fail(f"missing key {key!r} (found {self.keys()})")

    def read(self, key: str) -> np.ndarray:
        """The array stored under ``key`` (C-contiguous, writable, native byte order)."""
        self._usable(key)
        shape, dtype = self.meta[key]
        info, fortran = self._info[key]
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        try:
            buf = np.empty(nbytes, dtype=np.uint8)      # any dtype, any byte order
            got = self._read_stored(info, nbytes, buf)
            if got is None:                 # DEFLATE member: through zipfile
                with self._zip.open(info) as f:
                    f.seek(info.file_size - nbytes)
                    got = f.readinto(buf) if nbytes else 0
        except TreeFormatError:
            raise
        except Exception as e:      # MemoryError, zlib.error, BadZipFile (CRC), EOFError, OSError
            self.fail(f"array {key!r}: cannot read ({type(e).__name__}: {e})")
        if got != nbytes:
            self.fail(f"array {key!r}: truncated ({got} of {nbytes} bytes)")
        arr = buf.view(dtype).reshape(shape, order="F" if fortran else "C")
        arr = np.ascontiguousarray(arr)
        if not arr.dtype.isnative:
            arr = arr.astype(arr.dtype.newbyteorder("="))
        return arr

    def _read_stored(self, info: zipfile.ZipInfo, nbytes: int, buf: Any) -> int | None:
        """Read an uncompressed member's last ``nbytes`` (its array) straight from the archive
        into ``buf`` with one ``readinto`` (no intermediate copies: a 1.25 GB tree loads 2.2x
        faster than through zipfile, ``benchmarks/scoring_speed.py``) and check the member's
        CRC-32; the local header is parsed with zipfile's public ``structFileHeader``. Returns
        the bytes read (the caller reports a short read), or None for a compressed member
        (read through zipfile)."""
        if info.compress_type != zipfile.ZIP_STORED:
            return None
        with open(self.path, "rb") as f:
            f.seek(info.header_offset)
            local = f.read(zipfile.sizeFileHeader)
            if (len(local) != zipfile.sizeFileHeader
                    or local[:4] != zipfile.stringFileHeader):
                self.fail(f"member {info.filename!r}: bad local zip header")
            *_, n_name, n_extra = struct.unpack(zipfile.structFileHeader, local)
            f.seek(info.header_offset + zipfile.sizeFileHeader + n_name + n_extra)
            head = f.read(info.file_size - nbytes)          # the .npy header
            got = f.readinto(buf) if nbytes else 0
        if got == nbytes and zlib.crc32(buf, zlib.crc32(head)) != info.CRC:
            self.fail(f"member {info.filename!r}: CRC-32 mismatch (damaged file)")
        return got

    # ------------------------------------------------------------------ typed scalars
    def scalar_int(self, key: str) -> int:
        """An integer scalar (shape ``()`` or ``(1,)``)."""
        dt, shape = self.dtype(key), self.shape(key)
        if dt.kind not in "iu" or shape not in ((), (1,)):
            self.fail(f"{key!r} must be an integer scalar, got {dt} {list(shape)}")
        return int(self.read(key).reshape(()))

    def scalar_str(self, key: str) -> str:
        """A string scalar (numpy unicode, or ASCII bytes)."""
        dt, shape = self.dtype(key), self.shape(key)
        if dt.kind not in "US" or shape not in ((), (1,)):
            self.fail(f"{key!r} must be a string scalar, got {dt} {list(shape)}")
        v = self.read(key).reshape(())[()]
        if isinstance(v, bytes):
            try:
                v = v.decode("ascii")
            except UnicodeDecodeError:
                self.fail(f"{key!r} is not ASCII text")
        return str(v)

    def json(self, key: str) -> dict:
        """A JSON object stored as a string scalar."""
        text = self.scalar_str(key)
        try:
            obj = json.loads(text)
        except ValueError as e:
            self.fail(f"{key!r} is not valid JSON ({e})")
        if not isinstance(obj, dict):
            self.fail(f"{key!r} must be a JSON object, got {type(obj).__name__}")
        return obj
