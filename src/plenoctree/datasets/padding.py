"""Black padding at the photos' borders: rows or columns that a video encoder or a converter
left black in every frame, found once per image folder and cropped where the images load.

A padded row is no part of the scene, but a loader that keeps it trains on black there and
scores every render against it: lounge's frames (``../shared/data/real/lounge``, mip-NeRF
360's layout) end in a black row (``images_2/``: mean ≤ 0.71 of 255, the row above ≥ 68.8;
``images_4/``: a quarter as bright as the row above), which alone cost the chain's fine-tuned
tree 1.9 dB on its held-out frames (26.56 with it, 28.41 without; docs/results.md).

Rule (:func:`border_padding`): on up to :data:`SAMPLE` photos spread evenly over the folder
(the same photos whatever split is loaded, so every split crops alike), the ``k``-th line from
an edge (``k < MAX_PAD``) is padding when, in every one of them, its mean brightness is below
:data:`DARK` times that of the line :data:`MAX_PAD` in from the same edge, and so are the
lines between it and the edge. A scene's own border is not that much darker than the line a
few pixels in on every photo of a capture; a video's padding is. The crop
(:func:`crop_padding`) takes as many lines from both opposite edges as the more padded of the
two has, so the principal point stays at the centre where LLFF's poses put it (one row of
content lost at the top for one black row at the bottom).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ._files import decode_image, evenly_spaced, run_parallel

__all__ = ["border_padding", "crop_padding", "MAX_PAD", "DARK", "SAMPLE"]

logger = logging.getLogger(__name__)

#: Lines per edge that may be padding (the reference line is this far in).
MAX_PAD = 8
#: A padding line's mean brightness is below this share of the reference line's, in every
#: photo looked at.
DARK = 0.5
#: Photos looked at, spread evenly over the folder.
SAMPLE = 16
#: Reference lines darker than this (0–1) say nothing: a dark photo cannot show padding.
_MIN_REF = 0.02


def _edge_means(img: np.ndarray) -> np.ndarray:
    """Mean brightness (0–1) of the ``MAX_PAD + 1`` lines nearest each edge: ``[4, MAX_PAD + 1]``
    rows top, bottom, columns left, right (index 0 at the edge)."""
    g = img[..., :3].astype(np.float32).mean(axis=-1) / 255.0
    n = MAX_PAD + 1
    return np.stack([g[:n].mean(axis=1), g[::-1][:n].mean(axis=1),
                     g[:, :n].mean(axis=0), g[:, ::-1][:, :n].mean(axis=0)])


def _padding_of(means: np.ndarray) -> tuple[int, int]:
    """``(rows, cols)`` to crop from both edges, from the ``[photos, 4, MAX_PAD + 1]`` means."""
    ref = means[:, :, MAX_PAD:MAX_PAD + 1]
    dark = (means[:, :, :MAX_PAD] < DARK * ref) & (ref > _MIN_REF)
    every = dark.all(axis=0)                       # [4, MAX_PAD]: padding in every photo
    per_edge = [int(np.argmin(e)) if not e.all() else MAX_PAD for e in every]
    return max(per_edge[0], per_edge[1]), max(per_edge[2], per_edge[3])


@functools.lru_cache(maxsize=64)
def _cached(files: tuple[str, ...], stamps: tuple[tuple[int, int], ...]) -> tuple[int, int]:
    pick = evenly_spaced(len(files), SAMPLE)
    means: list[np.ndarray | None] = [None] * len(pick)

    def look(j: int) -> None:
        img = decode_image(Path(files[pick[j]]), None)
        if min(img.shape[:2]) >= 4 * MAX_PAD:
            means[j] = _edge_means(img)

    run_parallel(len(pick), look, None)
    if any(m is None for m in means):               # photos too small to tell
        return 0, 0
    rows, cols = _padding_of(np.stack(means))
    if rows or cols:
        logger.info("%s: %s of every photo %s black padding (%d photos looked at): cropped "
                    "from both opposite edges", Path(files[0]).parent,
                    " and ".join(s for s in (f"{rows} border row(s)" if rows else "",
                                             f"{cols} border column(s)" if cols else "") if s),
                    "are", len(pick))
    return rows, cols


def border_padding(files: Sequence[Path]) -> tuple[int, int]:
    """``(rows, cols)`` of black padding to crop from both opposite edges of the photos
    ``files`` (one folder's images, at their stored size); see the module docstring. Looked
    up once per folder and process (cached on the files' names, sizes and times): decoding
    the 16 photos (in parallel, as the loaders decode) took 0.04 s for lounge's 480x270 frames
    and 4.3 s for 12-MP JPEGs on 2 cores (7.1 s one after the other)."""
    paths = tuple(str(p) for p in files)
    if not paths:
        return 0, 0
    stamps = []
    for p in paths:
        try:
            st = Path(p).stat()
            stamps.append((int(st.st_size), int(st.st_mtime_ns)))
        except OSError:
            stamps.append((-1, -1))
    return _cached(paths, tuple(stamps))


def crop_padding(images: np.ndarray | None, alphas: np.ndarray | None, cameras, rows: int,
                 cols: int, factor: int = 1):
    """Crop ``rows`` / ``cols`` lines of the stored images (``ceil(lines / factor)`` of images
    loaded at a downscale ``factor``) from both opposite edges: ``images [N, H, W, 3]``,
    ``alphas [N, H, W]`` (either may be None) and the :class:`~.cameras.Cameras` of that size
    (principal point moved by the crop, size reduced; NDC cameras keep the uncropped
    reference camera, so the NDC space does not change). Returns the three, unchanged when
    there is nothing to crop."""
    r, c = math.ceil(rows / factor), math.ceil(cols / factor)
    if r == 0 and c == 0:
        return images, alphas, cameras
    h, w = cameras.height - 2 * r, cameras.width - 2 * c

    def cut(a):
        return None if a is None else np.ascontiguousarray(a[:, r:r + h, c:c + w])

    # An NDC space keeps the uncropped image's reference (its scale is 2 f / size per axis), so
    # a cropped pixel's NDC ray is the uncropped one's.
    ref = cameras.ndc_ref
    if cameras.ndc and ref is None:
        fx, fy = cameras.ndc_focal
        ref = (2.0 * fx / cameras.width, 2.0 * fy / cameras.height)
    cams = dataclasses.replace(cameras, cx=cameras.cx - c, cy=cameras.cy - r, width=w, height=h,
                               ndc_ref=ref)
    return cut(images), cut(alphas), cams
