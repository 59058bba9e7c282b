"""Input images for ``process``: listing and checking photos, picking sharp frames of a video,
telling whether a folder of photos is in capture order (:func:`in_capture_order`).

:func:`list_photos` returns the image files of a folder after decoding each (one clear error
for an empty folder, a folder of non-images, a corrupt file, mixed sizes under one camera).
:func:`video_frames` reads a video with imageio-ffmpeg (``plenoctree[video]``), takes
``ceil(n / (1 - drop))`` candidate frames evenly spaced over its length, splits them into
``n`` runs of consecutive candidates and keeps the sharpest of each run (variance of the
Laplacian of the grey image): a blurred frame gives way to a neighbour, and no stretch of the
video loses its frames (dropping the least sharp candidates of the whole video did: views with
less texture went together, leaving gaps the matching could not bridge). Frames are decoded
once, in order, and only one candidate per run is held in memory.
"""

from __future__ import annotations

import logging
import math
import re
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .sfm import ProcessError

__all__ = ["list_photos", "video_frames", "sharpness", "is_video", "require_video_reader",
           "in_capture_order", "thumbnails", "natural_key", "VIDEO_SUFFIXES", "PHOTO_SUFFIXES"]

logger = logging.getLogger(__name__)

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")


def is_video(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a file with a video suffix."""
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple:
    """Sort key of a file name whose runs of digits compare as numbers: ``IMG_4831_2`` comes
    before ``IMG_4831_10`` (frames numbered without leading zeros, as many frame extractors
    write them, keep their capture order; zero-padded names sort as before). Ties (``f01`` /
    ``f1``) by the name itself.

    >>> sorted(["f_10.jpg", "f_2.jpg", "f_1.jpg"], key=natural_key)
    ['f_1.jpg', 'f_2.jpg', 'f_10.jpg']
    """
    parts = _DIGITS.split(name)           # text, number, text, ...: the types match by position
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


def list_photos(folder: str | os.PathLike, single_camera: bool = True) -> list[Path]:
    """The photos (PNG / JPEG) of ``folder`` in name order with numbers compared as numbers
    (:func:`natural_key`: the capture order of unpadded frame numbers), each fully decoded once.

    Raises:
        ProcessError: folder missing or empty, no image among its files, fewer than 3
            photos, a corrupt / truncated image (named), mixed sizes with ``single_camera``.
    """
    from PIL import Image

    folder = Path(folder)
    if not folder.is_dir():
        raise ProcessError(f"{folder}: not a folder of photos or a video file "
                           f"({', '.join(VIDEO_SUFFIXES)})")
    files = sorted((p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")),
                   key=lambda p: natural_key(p.name))
    photos = [p for p in files if p.suffix.lower() in PHOTO_SUFFIXES]
    if not files:
        raise ProcessError(f"{folder}: the folder is empty (put the photos there: PNG or JPEG)")
    if not photos:
        raise ProcessError(f"{folder}: none of its {len(files)} files is a photo (PNG or JPEG; "
                           f"e.g. {files[0].name})")
    if len(photos) < 3:
        raise ProcessError(f"{folder}: {len(photos)} photo(s); camera poses need at least 3 "
                           "overlapping photos (20-200 recommended)")
    size = None
    for p in photos:
        try:
            with Image.open(p) as im:
                im.load()
                s = im.size
        except Exception as e:  # noqa: BLE001 - any decoder failure means a corrupt file
            raise ProcessError(f"{p}: unreadable or corrupt image ({type(e).__name__}: {e}); "
                               "remove or replace it") from None
        if size is None:
            size, first = s, p
        elif s != size and single_camera:
            raise ProcessError(f"{p}: {s[0]}x{s[1]} pixels but {first.name} is "
                               f"{size[0]}x{size[1]}; one shared camera needs one size "
                               "(use --no-single-camera for photos from several cameras)")
    return photos


THUMB = 16
"""Side of the grey thumbnails :func:`in_capture_order` compares."""
ORDER_RATIO = 0.5
"""Photos are in capture order when consecutive ones differ by less than this fraction of the
median difference of all pairs (:func:`in_capture_order`)."""


def thumbnails(paths: Sequence[Path]) -> np.ndarray:
    """``[N, THUMB * THUMB]`` float32 grey thumbnails of the images, each zero-mean and of
    unit norm (JPEGs are decoded at 1/8 scale: a few ms each)."""
    from PIL import Image

    out = []
    for p in paths:
        with Image.open(p) as im:
            im.draft("L", (4 * THUMB, 4 * THUMB))
            t = np.asarray(im.convert("L").resize((THUMB, THUMB), Image.BOX), np.float32).ravel()
        t = t - t.mean()
        out.append(t / max(float(np.linalg.norm(t)), 1e-6))
    return np.stack(out)


def in_capture_order(paths: Sequence[Path]) -> bool:
    """Whether the photos' (name) order is the order they were taken in (frames of a video,
    a phone's numbered photos): consecutive thumbnails differ by less than
    :data:`ORDER_RATIO` x the median difference of all pairs (1 - correlation). Views of
    random directions (lego's training photos) are not; fewer than 4 photos never are."""
    if len(paths) < 4:
        return False
    t = thumbnails(paths)
    d = 1.0 - t @ t.T
    step = float(np.median(np.diag(d, 1)))
    return step < ORDER_RATIO * float(np.median(d[np.triu_indices(len(t), 1)]))


def require_video_reader():
    """``imageio.v2`` with its ffmpeg plugin, or :class:`ProcessError` naming the extra."""
    try:
        import imageio.v2 as iio
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise ProcessError("reading videos needs imageio-ffmpeg: pip install "
                           "'plenoctree[video]'") from None
    return iio


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image (higher = sharper)."""
    g = np.asarray(rgb, dtype=np.float32)
    g = g[..., :3].mean(-1) if g.ndim == 3 else g
    lap = (g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1])
    return float(lap.var())


_BANNER = re.compile(r"^(ffmpeg version|built with|configuration:|lib[a-z]+\s+\d|Input #|"
                     r"Metadata:|Duration:|Stream #|=== stderr|=+$)", re.IGNORECASE)


def decoder_message(e: BaseException) -> str:
    """A decoder failure in one line: imageio's first line and ffmpeg's last, without the
    version banner and configuration ffmpeg prints before every error."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    lines = [ln for ln in lines if not _BANNER.match(ln)] or [type(e).__name__]
    keep = lines[:1] + ([lines[-1]] if len(lines) > 1 else [])
    return "; ".join(keep)[:300]


def video_frames(video: str | os.PathLike, out_dir: str | os.PathLike, n_frames: int = 150,
                 drop: float = 0.5) -> list[Path]:
    """Write ``n_frames`` sharp, evenly spread frames of ``video`` as ``out_dir/frame_NNNNN.png``
    (``NNNNN``: the frame's number in the video, from 0): the sharpest of each run of
    ``1 / (1 - drop)`` evenly spaced candidates (module docstring).

    Returns the frame files in time order. Raises :class:`ProcessError` for an unreadable
    video, one with fewer than 3 frames, or a missing imageio-ffmpeg.
    """
    from PIL import Image

    from .._util import progress

    video, out = Path(video), Path(out_dir)
    if not 0 <= drop < 1:
        raise ProcessError(f"drop fraction must be in [0, 1), got {drop}")
    if n_frames < 3:
        raise ProcessError(f"--frames must be at least 3, got {n_frames}")
    iio = require_video_reader()
    try:
        reader = iio.get_reader(str(video), format="FFMPEG")
        total = reader.count_frames()
    except Exception as e:  # noqa: BLE001 - any decoder failure
        raise ProcessError(f"{video}: unreadable video ({decoder_message(e)})") from None
    if total < 3:
        raise ProcessError(f"{video}: {total} frame(s); need at least 3")
    n_cand = min(total, math.ceil(n_frames / (1.0 - drop)))
    want = np.unique(np.linspace(0, total - 1, n_cand).round().astype(int))
    keep = min(n_frames, len(want))
    # consecutive candidates in `keep` groups (the larger ones spread evenly); one per group
    group = np.searchsorted(np.round(np.linspace(0, len(want), keep + 1))[1:-1],
                            np.arange(len(want)), side="right")
    slot = {int(f): int(g) for f, g in zip(want, group)}
    out.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    best: tuple | None = None                        # (sharpness, frame number, pixels, group)

    def flush() -> None:                             # named by the video frame number
        if best is not None:
            p = out / f"frame_{best[1]:05d}.png"
            Image.fromarray(best[2]).save(p)
            paths.append(p)

    try:
        with progress(total=len(want), desc="video frames", unit="frame") as bar:
            for i, fr in enumerate(reader):
                if i in slot:
                    rgb = np.asarray(fr)[..., :3].copy()
                    score = sharpness(rgb)
                    if best is not None and best[3] != slot[i]:
                        flush()
                        best = None
                    if best is None or score > best[0]:
                        best = (score, i, rgb, slot[i])
                    bar.update(1)
                if i >= want[-1]:
                    break
    except Exception as e:  # noqa: BLE001
        raise ProcessError(f"{video}: decoding failed ({decoder_message(e)})") from None
    finally:
        reader.close()
    flush()
    logger.info(f"video: {len(paths)} of {total} frames kept (the sharpest of each run of "
        f"{len(want) / max(1, len(paths)):.2g} evenly spaced candidates)")
    return paths
