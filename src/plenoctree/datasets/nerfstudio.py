"""Loader for nerfstudio / instant-ngp captures: one ``transforms.json`` for all images.

Layout::

    root/transforms.json   {"camera_model": "OPENCV", "fl_x": ..., "fl_y": ..., "cx": ...,
                            "cy": ..., "w": ..., "h": ..., "aabb_scale": 16,
                            "frames": [{"file_path": "images/frame_00001.png",
                                        "transform_matrix": [[4x4]], "mask_path": ...}, ...]}

``transform_matrix`` is the OpenGL camera-to-world matrix (as in Blender files). Intrinsics
are read per frame, a frame's own ``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` overriding the
top-level ones; ``camera_angle_x``/``camera_angle_y`` (instant-ngp) stand in for a missing
``fl_x``/``fl_y``, ``fl_y`` defaults to ``fl_x`` and the principal point to the image centre.
Camera models: PINHOLE / SIMPLE_PINHOLE, and the distorting OPENCV (``k1, k2, p1, p2``, and
``k3`` through COLMAP's FULL_OPENCV), OPENCV_FISHEYE (``k1..k4``; also instant-ngp's
``is_fisheye``), RADIAL (``k1, k2``) and SIMPLE_RADIAL (``k1``); a file with no
``camera_model`` is OPENCV, as instant-ngp's ``colmap2nerf.py`` writes ``k1 k2 p1 p2`` without
one (with every coefficient zero that is a pinhole camera): images with non-zero
coefficients are undistorted on load by COLMAP's undistorter
(:mod:`plenoctree.datasets.undistort`, needs ``plenoctree[colmap]``) into the pinhole camera
COLMAP chooses; other models (equirectangular, ...) are refused.

Scene box: with instant-ngp's ``aabb_scale`` ``s`` (and ``scale`` = 0.33, ``offset`` = 0.5 by
default), the box is instant-ngp's ``[0.5 - s/2, 0.5 + s/2]^3`` mapped back to the file's
coordinates (ngp axes x, y, z are the file's y, z, x; ``p_ngp = scale p + offset``), i.e.
``[-1.5 s, 1.5 s]^3`` for the defaults. Without it the box is centred on the point nearest to
every optical axis and holds every camera centre (a conservative box for 360° captures).

Splits: the file's ``train_filenames`` / ``val_filenames`` / ``test_filenames`` lists when
present; otherwise every 8th frame sorted by file name (0, 8, ...) is both val and test, the
others train (``_files.HOLDOUT``: LLFF's rule, as the LLFF and COLMAP formats; nerfstudio's
own default is a 90 % / 10 % split). ``"all"`` takes every frame.
A file ``plenoctree process`` wrote (its ``plenoctree_transform`` key: a 360° capture of
photos) is a capture of a place, ``Dataset.unbounded``: training adds the far field; its
``plenoctree_bounds`` (the sparse points' smallest and largest depth) set the near plane
(``CONTENT_NEAR`` of the smallest, as LLFF's) and the far bound. Without a near plane the
rays of cameras standing inside the box start at the camera, and training puts fog right in
front of each camera that explains its photo alone (the lounge's frames: 15.2 dB on held-out
frames at step 300 against 23.0 with it).
Optional ``mask_path`` images become ``Dataset.masks`` (non-zero = pixel valid). Every
problem raises :class:`~plenoctree.errors.DatasetError` naming the file.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError, DatasetError
from ._images import (CONTENT_NEAR, focus_point, load_images, load_masks,
                      near_far_from_box)
from ._files import (check_frame_count, check_inside_dataset, check_load_options, finite_number,
                     frame_file_path, holdout_split, image_path, parse_matrix,
                     read_json_object, take_views)
from .base import Dataset, DatasetFormat
from .cameras import Cameras

__all__ = ["load_nerfstudio", "read_nerfstudio", "write_nerfstudio", "PINHOLE_MODELS"]

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL",
                  "OPENCV_FISHEYE")
"""Camera models accepted (the distorting ones are undistorted on load)."""
NO_MODEL = "OPENCV"
"""The camera model of a file without ``camera_model`` (instant-ngp's files: ``k1 k2 p1 p2``
with no model named; OPENCV holds PINHOLE's files too, their coefficients being zero)."""
_DISTORTION = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
_INTR_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")


def _frame_camera(where: str, glob: dict, fr: dict) -> tuple[float | None, ...]:
    """Validate the camera model / distortion of one frame; return its raw intrinsics."""
    model = fr.get("camera_model", glob.get("camera_model", NO_MODEL))
    if not isinstance(model, str):
        raise DatasetError(f"{where}: camera_model must be a string, got {model!r}")
    model = model.upper()
    if fr.get("is_fisheye", glob.get("is_fisheye", False)):
        model = "OPENCV_FISHEYE"
    if model not in PINHOLE_MODELS:
        raise DatasetError(f"{where}: camera model {model!r} is not supported (supported: "
                           f"{', '.join(PINHOLE_MODELS)})")
    coef = {}
    for key in _DISTORTION:
        v = fr.get(key, glob.get(key, 0.0))
        if not finite_number(v):
            raise DatasetError(f"{where}: {key} must be a finite number, got {v!r}")
        coef[key] = float(v)
    used = {"PINHOLE": (), "SIMPLE_PINHOLE": (), "SIMPLE_RADIAL": ("k1",),
            "RADIAL": ("k1", "k2"), "OPENCV": ("k1", "k2", "k3", "p1", "p2"),
            "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4")}[model]
    for key, v in coef.items():
        if v != 0 and key not in used:
            raise DatasetError(f"{where}: distortion coefficient {key} = {v:g} is not part of "
                               f"the {model} camera model (it uses {', '.join(used) or 'none'})")
    vals = []
    for key in _INTR_KEYS:
        v = fr.get(key, glob.get(key))
        if v is not None and not finite_number(v):
            raise DatasetError(f"{where}: {key} must be a finite number, got {v!r}")
        vals.append(None if v is None else float(v))
    dist = None
    if any(coef[k] != 0 for k in used):
        if model == "OPENCV_FISHEYE":
            dist = (model, [coef[k] for k in used])
        else:           # SIMPLE_RADIAL / RADIAL are OPENCV with the other coefficients zero
            c = [coef["k1"], coef["k2"], coef["p1"], coef["p2"]]
            dist = ("FULL_OPENCV", c + [coef["k3"], 0.0, 0.0, 0.0]) if coef["k3"] else ("OPENCV", c)
    return tuple(vals) + (dist,)


def _intrinsics(where: str, raw: tuple, width: int, height: int) -> tuple[float, ...]:
    fl_x, fl_y, cx, cy, w, h, ax, ay = raw[:8]
    for key, v, actual in (("w", w, width), ("h", h, height)):
        if v is not None and int(round(v)) != actual:
            raise DatasetError(f"{where}: {key} = {v:g} but the image is {width}x{height}")
    if fl_x is None and ax is not None:
        if not 0 < ax < math.pi:
            raise DatasetError(f"{where}: camera_angle_x must be in (0, pi), got {ax}")
        fl_x = 0.5 * width / math.tan(0.5 * ax)
    if fl_y is None and ay is not None:
        if not 0 < ay < math.pi:
            raise DatasetError(f"{where}: camera_angle_y must be in (0, pi), got {ay}")
        fl_y = 0.5 * height / math.tan(0.5 * ay)
    if fl_x is None and fl_y is None:
        raise DatasetError(f"{where}: missing intrinsics: no fl_x / fl_y / camera_angle_x at the "
                           "top level or in the frame")
    fl_x = fl_y if fl_x is None else fl_x
    fl_y = fl_x if fl_y is None else fl_y
    if not (fl_x > 0 and fl_y > 0):
        raise DatasetError(f"{where}: focal lengths must be positive, got {fl_x}, {fl_y}")
    return (fl_x, fl_y, width / 2.0 if cx is None else cx, height / 2.0 if cy is None else cy)


def read_nerfstudio(path: str | os.PathLike) -> tuple[dict, list[dict]]:
    """Parse ``transforms.json``: ``(top-level object, frames sorted by file_path)``, each
    frame with ``file_path`` (str), ``c2w`` (float64 ``[4, 4]``), ``mask_path`` (str|None),
    ``raw`` (its raw intrinsics) and ``where`` (for messages)."""
    path = Path(path)
    obj = read_json_object(path)
    frames_in = obj.get("frames")
    if not isinstance(frames_in, list) or not frames_in:
        raise DatasetError(f"{path}: missing or empty 'frames' list")
    check_frame_count(len(frames_in), str(path))
    frames = []
    for i, fr in enumerate(frames_in):
        where = f"{path}: frames[{i}]"
        fp = frame_file_path(fr, where)
        mp = fr.get("mask_path")
        if mp is not None and (not isinstance(mp, str) or not mp.strip() or "\x00" in mp):
            raise DatasetError(f"{where}: mask_path must be a non-empty string")
        if mp is not None:
            check_inside_dataset(mp, f"{where}: mask_path")
        m = fr["transform_matrix"]
        if isinstance(m, list) and len(m) == 3:       # 3x4 accepted
            m = m + [[0, 0, 0, 1]]
        frames.append({"file_path": fp, "c2w": parse_matrix(m, where), "mask_path": mp,
                       "raw": _frame_camera(where, obj, fr), "where": where})
    frames.sort(key=lambda f: f["file_path"])
    return obj, frames


def _split(obj: dict, frames: list[dict], split: str, path: Path) -> list[int]:
    n = len(frames)
    if split == "all":
        return list(range(n))
    if split not in ("train", "val", "test"):
        raise ConfigError(f"nerfstudio split must be train, val, test or all, got {split!r}")
    key = f"{split}_filenames"
    if key in obj:
        names = obj[key]
        if not isinstance(names, list) or not all(isinstance(s, str) for s in names):
            raise DatasetError(f"{path}: {key} must be a list of file names")
        wanted = {os.path.normpath(s) for s in names}
        idx = [i for i, f in enumerate(frames) if os.path.normpath(f["file_path"]) in wanted]
        if len(idx) != len(wanted):
            raise DatasetError(f"{path}: {key} lists {len(wanted)} files but only {len(idx)} "
                               "match frames' file_path")
    else:
        idx = holdout_split(n, split, path)
    if not idx:
        raise DatasetError(f"{path}: split {split!r} is empty ({n} frames)")
    return idx


def _scene_box(obj: dict, c2w: np.ndarray, path: Path) -> np.ndarray:
    if "aabb_scale" in obj:
        s = obj["aabb_scale"]
        scale = obj.get("scale", 0.33)
        offset = obj.get("offset", [0.5, 0.5, 0.5])
        if not (finite_number(s) and s > 0 and finite_number(scale) and scale > 0):
            raise DatasetError(f"{path}: aabb_scale and scale must be positive numbers")
        if finite_number(offset):
            offset = [offset] * 3
        if not (isinstance(offset, list) and len(offset) == 3
                and all(finite_number(v) for v in offset)):
            raise DatasetError(f"{path}: offset must be 3 numbers, got {offset!r}")
        ngp = np.array([[0.5 - 0.5 * s] * 3, [0.5 + 0.5 * s] * 3])
        box = (ngp - np.array(offset, dtype=np.float64)) / scale    # in ngp axis order
        return box[:, [2, 0, 1]]                                    # ngp (x,y,z) = file (y,z,x)
    centers = c2w[:, :3, 3]
    c = focus_point(c2w)
    r = float(np.abs(centers - c).max()) if len(c2w) > 1 else 1.0
    r = max(r, 1e-3)
    return np.stack([c - r, c + r])


def load_nerfstudio(root: str | os.PathLike, split: str = "train", downscale: int = 1,
                    background: Sequence[float] | float = (1.0, 1.0, 1.0),
                    limit: int | None = None, spread: bool = False,
                    num_threads: int | None = None) -> Dataset:
    """Load one split of a nerfstudio / instant-ngp ``transforms.json`` capture.

    Args:
        root: folder holding ``transforms.json`` (file paths are relative to it).
        split: "train", "val", "test" or "all" (see the module docstring).
        downscale: integer factor; for an image ``<dir>/<name>`` a pre-downscaled
            ``<dir>_<downscale>/<name>`` is used when present (nerfstudio's layout), otherwise
            the image is area-downscaled on the fly (the factor must divide the size). Masks
            likewise.
        background: RGB for transparent pixels. limit: first ``limit`` frames of the split
        (``spread``: evenly spaced).
        num_threads: decoding threads.

    Returns:
        A :class:`Dataset` whose cameras carry per-frame intrinsics when they differ, and
        ``masks`` when the frames name mask files.

    Raises:
        DatasetError: malformed file, missing intrinsics, unsupported camera model or
            distortion, missing / unreadable images, mixed image sizes, non-finite poses.
        ConfigError: bad option values.
    """
    bg = check_load_options(split, downscale, background, limit)
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    path = root / "transforms.json"
    obj, frames = read_nerfstudio(path)
    all_c2w = np.stack([f["c2w"] for f in frames])
    bbox = _scene_box(obj, all_c2w, path)
    idx = _split(obj, frames, split, path)
    idx = take_views(idx, limit, spread)
    f = int(downscale)
    pre = [_prescaled(root, frames[i]["file_path"], f, True) for i in idx]
    prescaled = f > 1 and all(p is not None for p in pre)
    factor = 1 if prescaled else f        # on-the-fly downscale factor
    paths = []
    for j, i in enumerate(idx):
        p = pre[j] if prescaled else image_path(root, frames[i]["file_path"])
        if not p.is_file():
            raise DatasetError(f"{p}: image file not found (listed in {frames[i]['where']})")
        paths.append(p)
    images, alphas, (w0, h0) = load_images(paths, factor, bg, num_threads)
    w, h = w0 // factor, h0 // factor     # loaded size
    intr = []
    for i in idx:
        raw = frames[i]["raw"]
        if prescaled:   # full size: the file's w / h, else f times the pre-downscaled size
            full = (int(round(raw[4])) if raw[4] else w0 * f,
                    int(round(raw[5])) if raw[5] else h0 * f)
        else:
            full = (w0, h0)
        k = _intrinsics(frames[i]["where"], raw, *full)
        sx, sy = w / full[0], h / full[1]
        intr.append((k[0] * sx, k[1] * sy, k[2] * sx, k[3] * sy))
    intr = np.array(intr)
    dists = [frames[i]["raw"][8] for i in idx]
    if any(d is not None for d in dists):
        images, intr = _undistort(images, intr, dists, paths)
        alphas = None
        h, w = images.shape[1:3]
    masks = None
    if any(frames[i]["mask_path"] for i in idx):
        if any(d is not None for d in dists):
            raise DatasetError(f"{path}: masks (mask_path) with lens distortion are not "
                               "supported; undistort the images and masks first")
        mpaths: list[Path | None] = []
        for i in idx:
            mp = frames[i]["mask_path"]
            q = None if mp is None else root / mp
            if mp is not None and prescaled:
                q = _prescaled(root, mp, f, False)
                if q is None:
                    raise DatasetError(f"{root / mp}: no pre-downscaled copy <dir>_{f}/ of this "
                                       "mask, though its image has one")
            mpaths.append(q)
        masks = load_masks(mpaths, (w0, h0), factor, num_threads)
    c2w = np.stack([frames[i]["c2w"] for i in idx]).astype(np.float32)
    try:
        cams = Cameras(c2w, intr[:, 0], intr[:, 1], intr[:, 2], intr[:, 3], w, h)
    except ConfigError as e:
        raise DatasetError(f"{path}: {e}") from None
    near, far = near_far_from_box(all_c2w, bbox)
    if "plenoctree_bounds" in obj:      # a 360° capture by process: its content's depths
        lo, hi = _content_bounds(obj["plenoctree_bounds"], path)
        near, far = max(near, CONTENT_NEAR * lo), max(far, hi)
    return Dataset(images=images, cameras=cams, near=near, far=far, scene_bbox=bbox,
                   split=split, root=root, background=tuple(float(v) for v in bg),
                   names=[Path(frames[i]["file_path"]).stem for i in idx], alphas=alphas,
                   masks=masks, unbounded="plenoctree_transform" in obj)


def _content_bounds(val: Any, path: Path) -> tuple[float, float]:
    """``plenoctree_bounds`` (``[near, far]``: the smallest and largest depth of the sparse
    points, world units), checked."""
    try:
        lo, hi = (float(v) for v in val)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: plenoctree_bounds must be [near, far], got {val!r}") \
            from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise DatasetError(f"{path}: plenoctree_bounds must satisfy 0 < near <= far, got "
                           f"{val!r}")
    return lo, hi


def _undistort(images: np.ndarray, intr: np.ndarray, dists: list, paths: list[Path]
               ) -> tuple[np.ndarray, np.ndarray]:
    """Undistort loaded images (their pinhole part ``intr [N, 4]`` at the loaded size)."""
    from .undistort import undistort_images

    h, w = images.shape[1:3]
    cams = []
    for k, d in zip(intr, dists):
        model, coef = d if d is not None else ("OPENCV", [0.0] * 4)
        cams.append(SimpleNamespace(model=model, params=np.concatenate([k, coef]),
                                    width=w, height=h))
    return undistort_images(images, cams, 1.0, paths)


def _prescaled(root: Path, rel: str, factor: int, image: bool) -> Path | None:
    """``<dir>_<factor>/<name>`` for ``<dir>/<name>`` when it exists (nerfstudio layout)."""
    if factor <= 1:
        return None
    p = image_path(root, rel) if image else root / rel
    q = p.parent.with_name(f"{p.parent.name}_{factor}") / p.name
    return q if q.is_file() else None


def write_nerfstudio(out_dir: str | os.PathLike, c2w: np.ndarray, images: np.ndarray,
                     intrinsics: np.ndarray | Sequence[float], masks: np.ndarray | None = None,
                     extra: dict[str, Any] | None = None, suffix: str = ".png") -> Path:
    """Write a nerfstudio capture: ``transforms.json``, ``images/``, optional ``masks/``.

    Args:
        c2w: ``[N, 4, 4]`` OpenGL camera-to-world. images: ``[N, H, W, 3|4]`` uint8 or float.
        intrinsics: ``(fx, fy, cx, cy)`` shared (written at the top level) or ``[N, 4]``
            per frame (written into each frame).
        masks: optional ``[N, H, W]`` bool / uint8 validity masks.
        extra: more top-level keys (e.g. ``{"aabb_scale": 4}``).

    Files are written atomically; returns ``Path(out_dir)``.
    """
    from PIL import Image

    from .._util import atomic_save_json, atomic_write

    out = Path(out_dir)
    c2w = np.asarray(c2w, dtype=np.float64)
    n, h, w = images.shape[:3]
    k = np.asarray(intrinsics, dtype=np.float64)
    per_frame = k.ndim == 2
    top: dict[str, Any] = {"camera_model": "OPENCV", "w": int(w), "h": int(h),
                           "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    if not per_frame:
        top.update(fl_x=float(k[0]), fl_y=float(k[1]), cx=float(k[2]), cy=float(k[3]))
    top.update(extra or {})
    frames = []
    fmt = "PNG" if suffix.lower() == ".png" else "JPEG"
    for i in range(n):
        img = images[i]
        if img.dtype != np.uint8:
            img = np.clip(np.round(np.asarray(img, np.float64) * 255.0), 0, 255).astype(np.uint8)
        name = f"frame_{i + 1:05d}{suffix}"
        with atomic_write(out / "images" / name) as fh:
            Image.fromarray(np.ascontiguousarray(img)).save(fh, format=fmt, quality=95)
        fr: dict[str, Any] = {"file_path": f"images/{name}", "transform_matrix": c2w[i].tolist()}
        if per_frame:
            fr.update(fl_x=float(k[i, 0]), fl_y=float(k[i, 1]), cx=float(k[i, 2]),
                      cy=float(k[i, 3]))
        if masks is not None:
            mname = f"frame_{i + 1:05d}.png"
            with atomic_write(out / "masks" / mname) as fh:
                Image.fromarray((np.asarray(masks[i]) > 0).astype(np.uint8) * 255).save(fh, "PNG")
            fr["mask_path"] = f"masks/{mname}"
        frames.append(fr)
    top["frames"] = frames
    atomic_save_json(out / "transforms.json", top)
    return out


def _own_val(root: Path) -> bool:
    """Whether ``val_filenames`` lists frames other than the test split's (without a list, every
    8th frame is both; ``process`` writes the test's list twice)."""
    path = root / "transforms.json"
    obj, frames = read_nerfstudio(path)
    if not obj.get("val_filenames"):
        return False
    if "test_filenames" in obj and not obj["test_filenames"]:
        return True
    return set(_split(obj, frames, "val", path)) != set(_split(obj, frames, "test", path))


FORMAT = DatasetFormat("nerfstudio", "transforms.json",
                       detect=lambda root: (root / "transforms.json").is_file(),
                       load=load_nerfstudio, photos=True, own_val=_own_val)
"""nerfstudio / instant-ngp in the registry of :mod:`plenoctree.datasets.dataset` (a split
exists when loading one of its views does not find it empty; ``val`` is one of its own only
with a list of frames other than the test ones)."""
