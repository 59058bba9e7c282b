"""File and value helpers shared by every dataset loader (Blender, LLFF, NSVF, nerfstudio,
COLMAP): number and matrix checks, frame file paths, image decoding (PNG/JPEG, alpha, the
truncation check), area downscaling with compositing, option checks, a thread pool.

The module is private to :mod:`plenoctree.datasets`; its functions have public names because
the loader modules share them (:func:`take_views` is re-exported by the package). Every
problem raises ``DatasetError`` naming the file, or ``ConfigError`` for bad option values.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import ConfigError, DatasetError
from .cameras import MAX_IMAGE_PIXELS, degenerate_rotations

_PNG_END = b"IEND\xaeB`\x82"   # the last 8 bytes of every complete PNG
_MAX_PIXELS = MAX_IMAGE_PIXELS  # refuse absurd image headers before allocating anything
#: Most frames (views) a dataset file may list: 100,000 (a 20-minute video at 60 fps would
#: need 72,000). A file listing more is refused before any frame is validated or loaded.
MAX_FRAMES = 100_000
#: Largest metadata JSON read (``transforms*.json``): 64 MB, about 200,000 frames' worth.
MAX_JSON_BYTES = 64 << 20
#: Rotations (``c2w[:3, :3]``) must be orthonormal to this tolerance: ``|RᵀR - I| <= 1e-2``.
ROTATION_TOL = 1e-2


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def finite_number(v: Any) -> bool:
    """True for a finite int or float (not a bool, not a string)."""
    try:
        return _is_number(v) and math.isfinite(v)
    except OverflowError:      # int too large for a float
        return False


def parse_matrix(value: Any, where: str) -> np.ndarray:
    """A finite 4x4 float64 matrix from nested JSON lists, or DatasetError."""
    if not (isinstance(value, list) and len(value) == 4
            and all(isinstance(row, list) and len(row) == 4 for row in value)):
        raise DatasetError(f"{where}: transform_matrix must be a 4x4 list of numbers")
    if not all(_is_number(v) for row in value for v in row):
        raise DatasetError(f"{where}: transform_matrix must contain only numbers")
    if not all(finite_number(v) for row in value for v in row):
        raise DatasetError(f"{where}: transform_matrix contains non-finite values")
    m = np.array(value, dtype=np.float64)
    if np.abs(m).max() > 1e30:
        raise DatasetError(f"{where}: transform_matrix has non-finite (float32 overflowing) values")
    if degenerate_rotations(m[None]).size:
        raise DatasetError(f"{where}: transform_matrix rotation (the upper-left 3x3) is singular "
                           "(e.g. all zeros); a camera needs three independent axes")
    m[:3, :3] = rigid_rotation(m[:3, :3], f"{where}: transform_matrix")
    return m


def rigid_rotation(r: np.ndarray, where: str) -> np.ndarray:
    """A camera rotation ``[3, 3]`` without its uniform scale: ``r / s`` must be orthonormal
    within :data:`ROTATION_TOL` (``s``: the mean column length). A uniformly scaled rotation
    is valid input (ray directions do not depend on it) and is returned unscaled; a mirror is
    allowed; a non-uniform scale or a shear distorts the rays and is refused (DatasetError)."""
    if float(np.abs(r.T @ r - np.eye(3)).max()) <= ROTATION_TOL:
        return r                                  # orthonormal already: kept bit for bit
    s = float(np.linalg.norm(r, axis=0).mean())
    u = r / s
    err = float(np.abs(u.T @ u - np.eye(3)).max())
    if not err <= ROTATION_TOL:
        lengths = ", ".join(f"{v:.3g}" for v in np.linalg.norm(r, axis=0))
        raise DatasetError(f"{where}: rotation (the upper-left 3x3) is not a scaled orthonormal "
                           f"matrix (column lengths {lengths}, |UᵀU - I| = {err:.3g} > "
                           f"{ROTATION_TOL:g} for U = R / {s:.3g}): a non-uniform scale or a "
                           "shear would distort the camera's rays")
    return u


def check_frame_count(n: int, where: str) -> None:
    """At most :data:`MAX_FRAMES` frames in one dataset file (DatasetError)."""
    if n > MAX_FRAMES:
        raise DatasetError(f"{where}: lists {n} frames; at most {MAX_FRAMES} are supported "
                           "(keep every k-th frame)")


def frame_file_path(fr: Any, where: str) -> str:
    """Check one ``frames[i]`` entry (an object with ``file_path`` and ``transform_matrix``)
    and return its ``file_path``; DatasetError prefixed with ``where`` otherwise."""
    if not isinstance(fr, dict):
        raise DatasetError(f"{where}: expected an object")
    for key in ("file_path", "transform_matrix"):
        if key not in fr:
            raise DatasetError(f"{where}: missing key {key!r}")
    fp = fr["file_path"]
    if not isinstance(fp, str) or not fp.strip() or "\x00" in fp:
        raise DatasetError(f"{where}: file_path must be a non-empty string")
    check_inside_dataset(fp, f"{where}: file_path")
    return fp


def check_inside_dataset(rel: str, where: str) -> None:
    """A path listed in a dataset file must stay inside the dataset folder (DatasetError).

    Lexical: absolute paths and paths whose normal form starts with ``..`` are refused; a
    symbolic link that leads out of the folder is refused where the file is opened
    (:func:`confined`).
    """
    norm = os.path.normpath(rel.replace("\\", "/"))
    if os.path.isabs(norm) or norm == ".." or norm.startswith(".." + os.sep) \
            or re.match(r"^[A-Za-z]:", norm):
        raise DatasetError(f"{where} {rel!r} points outside the dataset folder; paths must "
                           "be relative and inside it (move or link the files there)")


def image_path(root: Path, file_path: str) -> Path:
    """The image file of a frame's ``file_path`` under ``root``; ``.png`` is added when the
    path has no image suffix (Blender's ``./train/r_0``)."""
    p = root / file_path
    p = p if p.suffix.lower() in (".png", ".jpg", ".jpeg") else p.with_name(p.name + ".png")
    return confined(root, p)


def confined(root: Path, p: Path) -> Path:
    """``p`` (a file named by a dataset file) if it lies inside ``root`` after resolving every
    symbolic link; DatasetError otherwise, so a dataset cannot make the loader read a file
    outside its folder (``../../etc/passwd``, or a link to one). Returns ``p`` unresolved."""
    try:
        real, base = p.resolve(), root.resolve()
    except (OSError, RuntimeError) as e:          # a symlink loop
        raise DatasetError(f"{p}: cannot resolve the path ({e})") from None
    if not real.is_relative_to(base):
        raise DatasetError(f"{p}: resolves to {real}, outside the dataset folder {base} (a "
                           "symbolic link?); the files a dataset names must lie inside it: "
                           "copy them there, or give the real folder as --data")
    return p


def read_json_object(path: Path) -> dict:
    """The JSON object in file ``path`` (a loader's metadata file); anything else raises one
    :class:`DatasetError` naming it (missing, unreadable, not JSON, not an object)."""
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise DatasetError(f"{path}: {size / 2**20:.0f} MB; a dataset's JSON file may be at "
                               f"most {MAX_JSON_BYTES >> 20} MB")
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror or e})") from None
    try:
        obj = json.loads(raw)
    except (ValueError, RecursionError) as e:     # JSONDecodeError, UnicodeDecodeError, ...
        raise DatasetError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(obj, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level, got "
                           f"{type(obj).__name__}")
    return obj


@contextmanager
def reading(path: Path, what: str = "image") -> Iterator[None]:
    """Turn any failure reading ``path`` inside the block into one :class:`DatasetError`
    naming it: ``<path>: <what> file not found`` or ``<path>: unreadable <what> (<error>)``
    (a DatasetError raised inside passes unchanged)."""
    try:
        yield
    except DatasetError:
        raise
    except FileNotFoundError:
        raise DatasetError(f"{path}: {what} file not found") from None
    except Exception as e:  # noqa: BLE001 - any decoder failure means an unreadable file
        raise DatasetError(f"{path}: unreadable {what} ({type(e).__name__}: {e})") from None


def decode_image(path: Path, expect: tuple[int, int] | None) -> np.ndarray:
    """Decode one PNG (or JPEG) image to uint8 ``[H, W, 4]`` (alpha 255 when the file has none).

    ``expect`` = (width, height) the image must have; raises DatasetError naming ``path``.
    """
    from PIL import Image

    with reading(path, "image"):
        raw = path.read_bytes()
        with Image.open(io.BytesIO(raw), formats=("PNG", "JPEG")) as im:
            if im.format == "PNG" and not raw.endswith(_PNG_END):
                raise DatasetError(f"{path}: truncated PNG (no IEND chunk at the end)")
            w, h = im.size
            if w * h > _MAX_PIXELS or w <= 0 or h <= 0:
                raise DatasetError(f"{path}: implausible image size {w}x{h}")
            if expect is not None and (w, h) != expect:
                raise DatasetError(f"{path}: image is {w}x{h}, expected {expect[0]}x{expect[1]} "
                                   "like the other images of the split")
            im.load()
            mode = im.mode
            if mode == "RGBA":
                arr = np.asarray(im)
            elif mode == "RGB":
                arr = np.asarray(im)
                arr = np.concatenate([arr, np.full(arr.shape[:2] + (1,), 255, np.uint8)], -1)
            elif mode.startswith("I"):      # 16/32-bit grey
                g = np.asarray(im).astype(np.float64)
                scale = 65535.0 if mode.startswith("I;16") or g.max(initial=0) > 255 else 255.0
                g = np.clip(np.round(g / scale * 255.0), 0, 255).astype(np.uint8)
                arr = np.stack([g, g, g, np.full_like(g, 255)], -1)
            else:
                arr = np.asarray(im.convert("RGBA"))
    if arr.shape != (h, w, 4):
        raise DatasetError(f"{path}: decoded to shape {list(arr.shape)}, expected {[h, w, 4]}")
    return arr


def composite_into(arr: np.ndarray, factor: int, bg: np.ndarray,
                    out_rgb: np.ndarray, out_alpha: np.ndarray) -> None:
    """Area-downscale ``arr`` (uint8 RGBA) by ``factor`` and composite it onto ``bg``.

    Premultiplied colour and alpha are averaged over ``factor x factor`` blocks, then
    ``rgb = premult + (1 - alpha) bg`` is written to ``out_rgb [h, w, 3]``, alpha to
    ``out_alpha [h, w]``.
    """
    a = arr[..., 3:4].astype(np.float32) * np.float32(1.0 / 255.0)
    pre = arr[..., :3].astype(np.float32) * np.float32(1.0 / 255.0) * a
    if factor > 1:
        h, w = out_alpha.shape
        pre = pre.reshape(h, factor, w, factor, 3).mean(axis=(1, 3), dtype=np.float32)
        a = a.reshape(h, factor, w, factor, 1).mean(axis=(1, 3), dtype=np.float32)
    np.add(pre, (1.0 - a) * bg, out=out_rgb)
    np.clip(out_rgb, 0.0, 1.0, out=out_rgb)
    out_alpha[...] = a[..., 0]


HOLDOUT = 8
"""Captures without a split of their own hold out every ``HOLDOUT``-th image (0, 8, 16, ... of
the images sorted by name) for testing, the rest train: LLFF's rule, which NeRF, mip-NeRF 360
and most real-capture results use (LLFF, COLMAP folders, nerfstudio / instant-ngp files
without ``*_filenames`` lists)."""


def holdout_split(n: int, split: str, where: Any, every: int = HOLDOUT) -> list[int]:
    """Indices of ``split`` ("train", "val", "test" or "all") among ``n`` images sorted by
    name: every ``every``-th is test (and val), the others train (``every`` 0: none held out).
    An empty split raises :class:`DatasetError` naming ``where``."""
    if split not in ("train", "val", "test", "all"):
        raise ConfigError(f"split must be train, val, test or all, got {split!r}")
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 0:
        raise ConfigError(f"the hold-out interval (llffhold) must be a non-negative integer, "
                          f"got {every!r}")
    idx = np.arange(n)
    if split == "all":
        return idx.tolist()
    test = idx[::every] if every > 0 and n > 1 else idx[:0]
    out = test if split in ("val", "test") else np.setdiff1d(idx, test)
    if not len(out):
        raise DatasetError(f"{where}: split {split!r} is empty ({n} images, every {every}th "
                           "held out)")
    return out.tolist()


def evenly_spaced(n_total: int, n: int) -> list[int]:
    """``n`` indices evenly spaced over ``range(n_total)`` starting at 0 (5 of 200: 0, 40, …)."""
    if n <= 0 or n_total <= 0:
        return []
    n = min(n, n_total)
    return [int(i * n_total // n) for i in range(n)]


def take_views(items: Any, limit: int | None, spread: bool = False) -> Any:
    """The loaders' ``limit`` / ``spread`` rule on a split's frames (list or 1-D array), before
    any image is read: all of ``items`` when ``limit`` is None, else the first ``limit``, or
    with ``spread`` ``limit`` of them evenly spaced (:func:`evenly_spaced`)."""
    if limit is None:
        return items
    if not spread:
        return items[:limit]
    idx = evenly_spaced(len(items), limit)
    return items[np.asarray(idx, dtype=np.int64)] if isinstance(items, np.ndarray) else \
        [items[i] for i in idx]


def check_load_options(split: Any, downscale: Any, background: Any, limit: Any) -> np.ndarray:
    """Check the options every loader takes (``ConfigError`` naming the bad one); returns the
    background as float32 ``[3]`` in [0, 1]."""
    if not isinstance(split, str) or not split or any(c in split for c in "/\\\x00"):
        raise ConfigError(f"split must be a plain name like 'train', got {split!r}")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise ConfigError(f"downscale must be a positive integer, got {downscale!r}")
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, (int, np.integer))
                              or limit < 1):
        raise ConfigError(f"limit must be None or a positive integer, got {limit!r}")
    try:
        bg = np.broadcast_to(np.asarray(background, dtype=np.float32), (3,)).copy()
    except (TypeError, ValueError):
        raise ConfigError(f"background must be an RGB triple in [0, 1], got {background!r}") from None
    if not np.all((bg >= 0) & (bg <= 1)):
        raise ConfigError(f"background must be an RGB triple in [0, 1], got {background!r}")
    return bg


def run_parallel(n: int, work, num_threads: int | None) -> None:
    """Call ``work(i)`` for ``i < n`` on up to ``num_threads`` threads (default: cores, ≤ 8);
    the first exception cancels the rest and is re-raised."""
    threads = num_threads or min(8, os.cpu_count() or 1)
    if threads <= 1 or n <= 1:
        for i in range(n):
            work(i)
        return
    with ThreadPoolExecutor(max_workers=threads) as pool:
        futures = [pool.submit(work, i) for i in range(n)]
        try:
            for fut in futures:
                fut.result()
        except BaseException:
            for fut in futures:
                fut.cancel()
            raise
