"""Small shared helpers: atomic writes, progress bars, shape checks.

Imports nothing else from the package except :mod:`plenoctree.errors`.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

__all__ = [
    "atomic_write",
    "atomic_save_npz",
    "atomic_save_json",
    "save_png",
    "progress",
    "check_shape",
]


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[Any]:
    """Open ``path.tmp-<pid>`` for writing and move it onto ``path`` only on success.

    A crash or exception inside the block leaves ``path`` untouched (no half-written file).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_save_npz(path: str | os.PathLike, compressed: bool = False, **arrays: np.ndarray) -> None:
    """Save arrays to ``path`` (an ``.npz``) atomically; ``compressed`` uses DEFLATE."""
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)


def atomic_save_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    with atomic_write(path, "w") as f:
        json.dump(obj, f, indent=2, sort_keys=False)
        f.write("\n")


def to_uint8(img: Any) -> np.ndarray:
    """Convert a float image in [0, 1] (numpy or torch, [H, W] or [H, W, C]) to uint8."""
    if hasattr(img, "detach"):
        img = img.detach().cpu().numpy()
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    return (np.clip(np.nan_to_num(img.astype(np.float32)), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_png(path: str | os.PathLike, img: Any) -> None:
    """Save an image (float [H, W(, C)] in [0, 1] or uint8) as PNG atomically."""
    from PIL import Image

    arr = to_uint8(img)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    with atomic_write(path, "wb") as f:
        Image.fromarray(arr).save(f, format="PNG")


def progress(iterable: Iterable | None = None, total: int | None = None, desc: str = "",
             disable: bool | None = None, **kw: Any):
    """A tqdm progress bar on stderr; disabled when stderr is not a terminal unless ``disable=False``."""
    from tqdm.auto import tqdm

    if disable is None:
        disable = not sys.stderr.isatty()
    return tqdm(iterable, total=total, desc=desc, disable=disable, dynamic_ncols=True, **kw)


def check_shape(name: str, x: Any, shape: tuple) -> None:
    """Raise ``ValueError`` unless ``x.shape`` matches ``shape`` (``None`` or ``...`` = any).

    ``...`` may appear once, first, standing for any number of leading dimensions.
    """
    actual = tuple(x.shape)
    if shape and shape[0] is Ellipsis:
        tail = shape[1:]
        ok = len(actual) >= len(tail) and all(
            s is None or s == a for s, a in zip(tail, actual[len(actual) - len(tail):]))
    else:
        ok = len(actual) == len(shape) and all(s is None or s == a for s, a in zip(shape, actual))
    if not ok:
        want = tuple("..." if s is Ellipsis else ("*" if s is None else s) for s in shape)
        raise ValueError(f"{name}: expected shape {want}, got {actual}")
