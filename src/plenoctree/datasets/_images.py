"""Shared helpers of the loaders (Blender, LLFF, NSVF, nerfstudio): threaded image / mask
loading, image listing, near/far bounds from a box.

Decoding and area downscaling are :mod:`._files`' (:func:`_files.decode_image`,
:func:`_files.composite_into`), so every format treats PNG/JPEG, alpha and downscaling alike.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..errors import DatasetError
from ._files import composite_into, decode_image, reading, run_parallel

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def image_files(folder: Path, prefix: str = "") -> list[Path]:
    """Image files (PNG / JPEG, any case) in ``folder`` whose name starts with ``prefix``, sorted."""
    try:
        entries = list(folder.iterdir())
    except FileNotFoundError:
        raise DatasetError(f"{folder}: image folder not found") from None
    except OSError as e:
        raise DatasetError(f"{folder}: cannot list ({e.strerror or e})") from None
    return sorted(p for p in entries if p.suffix.lower() in IMAGE_SUFFIXES
                  and p.name.startswith(prefix) and p.is_file())


def probe_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file from its header (DatasetError naming it)."""
    from PIL import Image

    with reading(path, "image"), Image.open(path) as im:
        return im.size


def load_images(paths: Sequence[Path], downscale: int, background: np.ndarray,
                num_threads: int | None = None, *,
                check_size: Callable[[int, int], None] | None = None,
                composite_all: bool = False
                ) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int]]:
    """Decode, area-downscale and composite images of one size (every loader's images).

    Args:
        paths: image files (at least one). downscale: integer factor dividing the size.
        background: float32 ``[3]`` RGB for transparent pixels.
        check_size: called with the first image's ``(width, height)`` before the others are
            decoded (a loader's own size check, e.g. against its metadata).
        composite_all: composite every image, opaque or not, and always return ``alphas``
            (the Blender loader); default: fully opaque images skip the compositing.

    Returns:
        ``images`` float32 ``[N, H/f, W/f, 3]``, ``alphas`` float32 ``[N, H/f, W/f]`` (``None``
        when every image is fully opaque, unless ``composite_all``), and the files' size
        ``(W, H)``.

    Raises:
        DatasetError naming the file: unreadable / truncated images, mixed sizes, a
        ``downscale`` not dividing the size.
    """
    first = decode_image(paths[0], None)
    height, width = first.shape[:2]
    if check_size is not None:
        check_size(width, height)
    f = int(downscale)
    if width % f or height % f:
        raise DatasetError(f"{paths[0]}: downscale {f} does not divide the image size "
                           f"{width}x{height}")
    h, w, n = height // f, width // f, len(paths)
    images = np.empty((n, h, w, 3), dtype=np.float32)
    alphas: list[np.ndarray | None] = [
        np.empty((n, h, w), dtype=np.float32) if composite_all else None]
    lock = threading.Lock()
    scale = np.float32(1.0 / 255.0)

    def work(i: int) -> None:
        arr = first if i == 0 else decode_image(paths[i], (width, height))
        if composite_all:
            composite_into(arr, f, background, images[i], alphas[0][i])
            return
        if arr[..., 3].min() == 255:     # opaque: same values as compositing, 4x less work
            rgb = arr[..., :3]
            if f == 1:
                np.multiply(rgb, scale, out=images[i])
            else:
                np.multiply(rgb.reshape(h, f, w, f, 3).mean(axis=(1, 3), dtype=np.float32),
                            scale, out=images[i])
            return
        a = np.empty((h, w), dtype=np.float32)
        composite_into(arr, f, background, images[i], a)
        with lock:
            if alphas[0] is None:
                alphas[0] = np.ones((n, h, w), dtype=np.float32)
            alphas[0][i] = a

    run_parallel(n, work, num_threads)
    return images, alphas[0], (width, height)


def load_masks(paths: Sequence[Path | None], size: tuple[int, int], downscale: int,
               num_threads: int | None = None) -> np.ndarray:
    """Pixel validity masks: float32 ``[N, H/f, W/f]`` in [0, 1] (``None`` paths: all valid).

    A mask file is any grey / RGB(A) image of the same size as its image; a pixel is valid when
    its (grey) value is non-zero (the nerfstudio rule). Downscaling averages the validity over
    each block, so a value is the fraction of valid source pixels.
    """
    from PIL import Image

    width, height = size
    f = int(downscale)
    h, w = height // f, width // f
    out = np.ones((len(paths), h, w), dtype=np.float32)

    def work(i: int) -> None:
        p = paths[i]
        if p is None:
            return
        with reading(p, "mask"), Image.open(p) as im:
            if im.size != (width, height):
                raise DatasetError(f"{p}: mask is {im.size[0]}x{im.size[1]}, its image is "
                                   f"{width}x{height}")
            m = np.asarray(im.convert("L")) > 0
        mf = m.astype(np.float32)
        if f > 1:
            mf = mf.reshape(h, f, w, f).mean(axis=(1, 3), dtype=np.float32)
        out[i] = mf

    run_parallel(len(paths), work, num_threads)
    return out


#: The near plane of a capture with content depths (LLFF's ``poses_bounds.npy``, the bounds
#: ``process`` writes for a 360° capture): this fraction of the smallest depth.
CONTENT_NEAR = 0.9


def near_far_from_box(c2w: np.ndarray, bbox: np.ndarray) -> tuple[float, float]:
    """Ray bounds for cameras ``c2w [N, 4, 4]`` looking at the content box ``bbox [2, 3]``.

    ``near``: the smallest distance from a camera centre to the box (0 when a camera is
    inside it); ``far``: the largest distance from a camera centre to a box corner. Every ray
    segment inside the box then lies in ``[near, far]``.
    """
    c = np.asarray(c2w, dtype=np.float64)[:, :3, 3]
    lo, hi = np.asarray(bbox, dtype=np.float64).reshape(2, 3)
    gap = np.maximum(np.maximum(lo - c, c - hi), 0.0)
    near = float(np.linalg.norm(gap, axis=1).min())
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    far = float(np.linalg.norm(c[:, None, :] - corners[None], axis=-1).max())
    return near, far


def focus_point(c2w: np.ndarray) -> np.ndarray:
    """The point nearest (least squares) to every camera's optical axis, float64 ``[3]``.

    Minimises ``Σ_i |P_i (p - o_i)|²`` with ``P_i = I - a_i a_i^T`` the projector orthogonal
    to axis ``a_i``: ``p = (Σ P_i)^-1 Σ P_i o_i``. Falls back to the mean centre when the axes
    are (nearly) parallel.
    """
    m = np.asarray(c2w, dtype=np.float64)
    a = m[:, :3, 2]
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    o = m[:, :3, 3]
    proj = np.eye(3)[None] - a[:, :, None] * a[:, None, :]
    lhs = proj.sum(0)
    rhs = np.einsum("nij,nj->i", proj, o)
    if np.linalg.cond(lhs) > 1e8:
        return o.mean(0)
    return np.linalg.solve(lhs, rhs)
