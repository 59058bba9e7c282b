"""Loader for Blender / NeRF-synthetic datasets (``transforms_<split>.json`` + RGBA PNGs).

Layout::

    root/transforms_train.json   {"camera_angle_x": 0.69, "frames": [
                                    {"file_path": "./train/r_0", "transform_matrix": [[4x4]]}, ...]}
    root/train/r_0.png           RGBA (RGB, grey or palette images are accepted too)

``transform_matrix`` is the OpenGL camera-to-world matrix. The focal length is
``0.5 W / tan(0.5 camera_angle_x)`` with the principal point at the image centre; instant-ngp
style files giving ``fl_x`` / ``fl_y`` / ``cx`` / ``cy`` in pixels are read too. Every problem
with the files raises :class:`~plenoctree.errors.DatasetError` naming the file; nothing is
returned half-loaded.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ConfigError, DatasetError
from ._files import (check_frame_count, _check_options, _finite_number, _frame_file_path, _image_path, _matrix,
                     read_json_object, take_views)
from ._images import load_images
from .cameras import Cameras
from .dataset import Dataset

__all__ = ["load_blender", "read_transforms", "BLENDER_NEAR", "BLENDER_FAR", "BLENDER_BBOX"]

BLENDER_NEAR = 2.0
BLENDER_FAR = 6.0
BLENDER_BBOX = np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], dtype=np.float32)


def read_transforms(path: str | os.PathLike) -> tuple[dict, list[tuple[str, np.ndarray]]]:
    """Parse and validate one ``transforms_<split>.json``.

    Returns:
        ``(meta, frames)``: ``meta`` holds the top-level intrinsics keys present
        (``camera_angle_x``, ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``) as floats;
        ``frames`` is a list of ``(file_path, c2w [4, 4] float64)``.
    """
    path = Path(path)
    obj = read_json_object(path)
    meta: dict[str, float] = {}
    for key in ("camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h"):
        if key in obj:
            if not _finite_number(obj[key]):
                raise DatasetError(f"{path}: {key} must be a finite number, got {obj[key]!r}")
            meta[key] = float(obj[key])
    if "camera_angle_x" not in meta and "fl_x" not in meta:
        raise DatasetError(f"{path}: missing key 'camera_angle_x' (or 'fl_x')")
    if "camera_angle_x" in meta and not 0.0 < meta["camera_angle_x"] < math.pi:
        raise DatasetError(f"{path}: camera_angle_x must be in (0, pi) radians, got "
                           f"{meta['camera_angle_x']}")
    for key in ("fl_x", "fl_y", "w", "h"):
        if key in meta and not meta[key] > 0:
            raise DatasetError(f"{path}: {key} must be positive, got {meta[key]}")
    if "frames" not in obj:
        raise DatasetError(f"{path}: missing key 'frames'")
    if not isinstance(obj["frames"], list):
        raise DatasetError(f"{path}: 'frames' must be a list")
    if not obj["frames"]:
        raise DatasetError(f"{path}: 'frames' is empty")
    check_frame_count(len(obj["frames"]), str(path))
    frames = []
    for i, fr in enumerate(obj["frames"]):
        where = f"{path}: frames[{i}]"
        frames.append((_frame_file_path(fr, where), _matrix(fr["transform_matrix"], where)))
    return meta, frames


def load_blender(root: str | os.PathLike, split: str = "train", downscale: int = 1,
                 background: Sequence[float] | float = (1.0, 1.0, 1.0),
                 limit: int | None = None, spread: bool = False,
                 num_threads: int | None = None) -> Dataset:
    """Load one split of a Blender / NeRF-synthetic dataset.

    Args:
        root: dataset folder holding ``transforms_<split>.json``.
        split: "train", "val", "test" (any plain name with a matching json file).
        downscale: integer factor; images are area-averaged over ``downscale^2`` blocks
            (premultiplied colour and alpha averaged, then composited) and the intrinsics scaled.
            Must divide the image size.
        background: RGB (or one grey value) in [0, 1] that transparent pixels are composited on.
        limit: keep only the first ``limit`` frames (with ``spread``: ``limit`` frames evenly
            spaced over the split).
        num_threads: image decoding threads (default ``min(8, cpu count)``).

    Returns:
        A :class:`Dataset` with float32 ``images [N, H/downscale, W/downscale, 3]``, ``alphas``,
        cameras, near 2, far 6, scene box ``[-1.5, 1.5]^3``.

    Raises:
        DatasetError: missing / malformed json, bad matrices, missing or unreadable images,
            images of the wrong or mixed sizes, ``downscale`` not dividing the size.
        ConfigError: bad option values.
    """
    bg = _check_options(split, downscale, background, limit)
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    json_path = root / f"transforms_{split}.json"
    meta, frames = read_transforms(json_path)
    frames = take_views(frames, limit, spread)
    paths = []
    for i, (fp, _) in enumerate(frames):
        try:
            p = _image_path(root, fp)
            ok = p.is_file()
        except (OSError, ValueError) as e:
            raise DatasetError(f"{json_path}: frames[{i}]: bad file_path {fp!r} ({e})") from None
        if not ok:
            raise DatasetError(f"{p}: image file not found (listed in {json_path})")
        paths.append(p)

    def check_size(width: int, height: int) -> None:
        for key, val in (("w", width), ("h", height)):
            if key in meta and int(meta[key]) != val:
                raise DatasetError(f"{json_path}: {key} = {meta[key]:g} but {paths[0]} is "
                                   f"{width}x{height}")

    images, alphas, (width, height) = load_images(paths, downscale, bg, num_threads,
                                                  check_size=check_size, composite_all=True)
    f = int(downscale)

    if "fl_x" in meta:
        fx = meta["fl_x"]
        fy = meta.get("fl_y", fx)
    else:
        fx = fy = 0.5 * width / math.tan(0.5 * meta["camera_angle_x"])
    cx, cy = meta.get("cx", width / 2.0), meta.get("cy", height / 2.0)
    c2w = np.stack([m for _, m in frames]).astype(np.float32)
    try:
        cams = Cameras(c2w, fx, fy, cx, cy, width, height).scaled(f)
    except ConfigError as e:
        raise DatasetError(f"{json_path}: {e}") from None
    return Dataset(images=images, cameras=cams, near=BLENDER_NEAR, far=BLENDER_FAR,
                   scene_bbox=BLENDER_BBOX.copy(), split=split, root=root,
                   background=tuple(float(v) for v in bg),
                   names=[Path(fp).stem for fp, _ in frames], alphas=alphas)
