"""Loader for NSVF-format scenes (Tanks&Temples and Synthetic-NSVF as released by NSVF).

Layout::

    root/intrinsics.txt   a 4x4 (or 3x3) intrinsics matrix K (fx = K00, fy = K11, cx = K02,
                          cy = K12), or the older one-line form "f cx cy [0]" (fx = fy = f)
    root/pose/<name>.txt  4x4 camera-to-world, OpenCV convention (x right, y down, looks +z);
                          a 3x4 matrix is accepted too
    root/rgb/<name>.png   the image of the same stem (PNG or JPEG; RGBA composited)
    root/bbox.txt         optional "xmin ymin zmin xmax ymax zmax [voxel size]": content box

File names start with the split: ``0_`` train, ``1_`` val, ``2_`` test (a scene without
``2_`` files tests on ``1_``, as the original code does). Poses are converted to our OpenGL
convention by flipping the camera's y and z axes (``c2w @ diag(1, -1, -1, 1)``). The scene box
comes from ``bbox.txt`` (the conversion step reads it from ``Dataset.scene_bbox``); without it
the box of the cameras' centres is used. near/far bound every ray segment inside that box.
Unlike the original (one focal, principal point at the centre) both focal lengths and the
principal point of ``intrinsics.txt`` are used. Every problem raises
:class:`~plenoctree.errors.DatasetError` naming the file; nothing is returned half-loaded.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ConfigError, DatasetError
from ._images import image_files, load_images, near_far_from_box
from ._files import check_load_options, take_views
from .base import Dataset, DatasetFormat
from .cameras import Cameras

__all__ = ["load_nsvf", "read_intrinsics", "read_pose", "read_bbox", "write_nsvf",
           "NSVF_SPLIT_PREFIX"]

NSVF_SPLIT_PREFIX = {"train": "0_", "val": "1_", "test": "2_"}
"""File-name prefix of each split (``"all"`` takes every file)."""
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def _numbers(path: Path, what: str) -> list[list[float]]:
    """Rows of numbers of a small text file (blank lines skipped); DatasetError naming it."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DatasetError(f"{path}: {what} file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: cannot read {what} ({e})") from None
    rows = []
    for ln, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            rows.append([float(t) for t in line.replace(",", " ").split()])
        except ValueError:
            raise DatasetError(f"{path}: line {ln} of the {what} is not a list of numbers: "
                               f"{line.strip()[:60]!r}") from None
    if not rows:
        raise DatasetError(f"{path}: empty {what} file")
    return rows


def read_intrinsics(path: str | os.PathLike) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` from an NSVF ``intrinsics.txt`` (matrix or "f cx cy" form)."""
    path = Path(path)
    rows = _numbers(path, "intrinsics")
    flat = [v for r in rows for v in r]
    if len(rows) in (3, 4) and all(len(r) == len(rows) for r in rows):
        k = np.array(rows)
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    elif len(rows[0]) in (3, 4):
        fx = fy = rows[0][0]
        cx, cy = rows[0][1], rows[0][2]
    else:
        raise DatasetError(f"{path}: expected a 3x3 / 4x4 intrinsics matrix or a first line "
                           f"'f cx cy [0]', got {len(rows)} lines / {len(flat)} numbers")
    vals = np.array([fx, fy, cx, cy])
    if not np.all(np.isfinite(vals)) or fx <= 0 or fy <= 0:
        raise DatasetError(f"{path}: focal lengths must be finite and positive, principal point "
                           f"finite; got fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    return float(fx), float(fy), float(cx), float(cy)


def read_pose(path: str | os.PathLike) -> np.ndarray:
    """One NSVF pose file as an OpenGL camera-to-world ``[4, 4]`` float64."""
    path = Path(path)
    rows = _numbers(path, "pose")
    flat = np.array([v for r in rows for v in r])
    if flat.size not in (12, 16):
        raise DatasetError(f"{path}: expected a 4x4 (or 3x4) camera-to-world matrix, got "
                           f"{flat.size} numbers")
    if not np.all(np.isfinite(flat)) or np.abs(flat).max() > 1e30:
        raise DatasetError(f"{path}: pose contains non-finite values")
    m = np.eye(4)
    m[:flat.size // 4] = flat.reshape(-1, 4)
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise DatasetError(f"{path}: last row of the pose must be 0 0 0 1, got {m[3].tolist()}")
    r = m[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-2:
        raise DatasetError(f"{path}: pose rotation is not orthonormal")
    return m @ _OPENCV_TO_OPENGL


def read_bbox(path: str | os.PathLike) -> np.ndarray:
    """``bbox.txt`` as float32 ``[2, 3]`` (min, max); a trailing voxel size is ignored."""
    path = Path(path)
    flat = [v for r in _numbers(path, "bounding box") for v in r]
    if len(flat) not in (6, 7):
        raise DatasetError(f"{path}: expected 'xmin ymin zmin xmax ymax zmax [voxel size]', got "
                           f"{len(flat)} numbers")
    box = np.array(flat[:6]).reshape(2, 3)
    if not np.all(np.isfinite(box)) or not np.all(box[1] > box[0]):
        raise DatasetError(f"{path}: box must be finite with max > min, got {box.tolist()}")
    return box.astype(np.float32)


def _split_files(rgb: list[Path], split: str) -> list[Path]:
    if split == "all":
        return rgb
    if split not in NSVF_SPLIT_PREFIX:
        raise ConfigError(f"NSVF split must be train, val, test or all, got {split!r}")
    files = [p for p in rgb if p.name.startswith(NSVF_SPLIT_PREFIX[split])]
    if not files and split == "test":
        files = [p for p in rgb if p.name.startswith(NSVF_SPLIT_PREFIX["val"])]
    return files


def load_nsvf(root: str | os.PathLike, split: str = "train", downscale: int = 1,
              background: Sequence[float] | float = (1.0, 1.0, 1.0),
              limit: int | None = None, spread: bool = False,
              num_threads: int | None = None) -> Dataset:
    """Load one split of an NSVF-format scene (see the module docstring for the layout).

    Args:
        root: scene folder. split: "train", "val", "test" or "all".
        downscale: integer area-downscale factor (must divide the image size).
        background: RGB for transparent pixels. limit: first ``limit`` images of the split
        (``spread``: evenly spaced).
        num_threads: decoding threads.

    Returns:
        A :class:`Dataset` (OpenGL cameras, ``scene_bbox`` from ``bbox.txt``).

    Raises:
        DatasetError: missing / malformed intrinsics, pose or box files, a pose without an
            image or an image without a pose, unreadable or mixed-size images.
        ConfigError: bad option values.
    """
    bg = check_load_options(split, downscale, background, limit)
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    fx, fy, cx, cy = read_intrinsics(root / "intrinsics.txt")
    pose_dir, rgb_dir = root / "pose", root / "rgb"
    if not pose_dir.is_dir():
        raise DatasetError(f"{pose_dir}: pose folder not found")
    rgb = image_files(rgb_dir)
    poses = sorted(p for p in pose_dir.iterdir() if p.suffix == ".txt" and p.is_file())
    rgb_stems = {p.stem: p for p in rgb}
    pose_stems = {p.stem: p for p in poses}
    if len(rgb_stems) != len(rgb):
        raise DatasetError(f"{rgb_dir}: several images share a name stem (e.g. .png and .jpg)")
    if rgb_stems.keys() != pose_stems.keys():
        only_pose = sorted(pose_stems.keys() - rgb_stems.keys())
        only_rgb = sorted(rgb_stems.keys() - pose_stems.keys())
        detail = (f"pose {pose_stems[only_pose[0]]} has no image in {rgb_dir}" if only_pose
                  else f"image {rgb_stems[only_rgb[0]]} has no pose in {pose_dir}")
        raise DatasetError(f"{root}: {len(poses)} poses but {len(rgb)} images; {detail}")
    files = _split_files(rgb, split)
    if not files:
        raise DatasetError(f"{rgb_dir}: no images of split {split!r} (names starting with "
                           f"{NSVF_SPLIT_PREFIX.get(split, '')!r})")
    files = take_views(files, limit, spread)
    c2w = np.stack([read_pose(pose_stems[p.stem]) for p in files])
    all_c2w = np.stack([read_pose(p) for p in poses]) if split != "all" else c2w
    bbox_path = root / "bbox.txt"
    if bbox_path.is_file():
        bbox = read_bbox(bbox_path)
    else:
        centers = all_c2w[:, :3, 3]
        pad = max(float(np.ptp(centers, axis=0).max()) * 0.05, 1e-3)
        bbox = np.stack([centers.min(0) - pad, centers.max(0) + pad])
    images, alphas, (w, h) = load_images(files, int(downscale), bg, num_threads)
    try:
        cams = Cameras(c2w.astype(np.float32), fx, fy, cx, cy, w, h).scaled(int(downscale))
    except ConfigError as e:
        raise DatasetError(f"{root / 'intrinsics.txt'}: {e}") from None
    near, far = near_far_from_box(all_c2w, bbox)
    return Dataset(images=images, cameras=cams, near=near, far=far, scene_bbox=bbox,
                   split=split, root=root, background=tuple(float(v) for v in bg),
                   names=[p.stem for p in files], alphas=alphas)


def write_nsvf(out_dir: str | os.PathLike, splits: dict[str, tuple[np.ndarray, np.ndarray]],
               fx: float, fy: float, cx: float, cy: float, bbox: np.ndarray | None = None,
               suffix: str = ".png") -> Path:
    """Write an NSVF-format scene.

    Args:
        splits: ``{"train"|"val"|"test": (c2w [N, 4, 4] OpenGL, images [N, H, W, 3|4])}``;
            images uint8 or float in [0, 1] (RGBA keeps its alpha).
        fx, fy, cx, cy: intrinsics (written as a 4x4 matrix). bbox: ``[2, 3]`` or None.

    Files ``rgb/<p><i>.png``, ``pose/<p><i>.txt`` (OpenCV c2w), ``intrinsics.txt`` and
    ``bbox.txt`` are written atomically; returns ``Path(out_dir)``.
    """
    from PIL import Image

    from .._util import atomic_write

    out = Path(out_dir)
    for split, (c2w, images) in splits.items():
        prefix = NSVF_SPLIT_PREFIX[split]
        for i, (m, img) in enumerate(zip(np.asarray(c2w, dtype=np.float64), images)):
            cv = m @ _OPENCV_TO_OPENGL
            with atomic_write(out / "pose" / f"{prefix}{i:04d}.txt", "w") as fh:
                fh.write("\n".join(" ".join(f"{v:.17g}" for v in row) for row in cv) + "\n")
            if img.dtype != np.uint8:
                img = np.clip(np.round(np.asarray(img, np.float64) * 255.0), 0, 255).astype(np.uint8)
            fmt = "PNG" if suffix.lower() == ".png" else "JPEG"
            with atomic_write(out / "rgb" / f"{prefix}{i:04d}{suffix}") as fh:
                Image.fromarray(np.ascontiguousarray(img)).save(fh, format=fmt, quality=95)
    k = np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=np.float64)
    with atomic_write(out / "intrinsics.txt", "w") as fh:
        fh.write("\n".join(" ".join(f"{v:.17g}" for v in row) for row in k) + "\n")
    if bbox is not None:
        b = np.asarray(bbox, dtype=np.float64).reshape(-1)
        with atomic_write(out / "bbox.txt", "w") as fh:
            fh.write(" ".join(f"{v:.17g}" for v in b) + " 0.1\n")
    return out


def _has_images(root: Path, *splits: str) -> bool:
    """Whether ``rgb/`` holds an image of one of ``splits`` (by its file-name prefix)."""
    names = [p.name for p in (root / "rgb").iterdir()] if (root / "rgb").is_dir() else []
    prefixes = [NSVF_SPLIT_PREFIX[s] for s in splits if s in NSVF_SPLIT_PREFIX]
    return any(n.startswith(p) for n in names for p in prefixes)


def _has_split(root: Path, split: str) -> bool:
    return _has_images(root, split, "val") if split == "test" else _has_images(root, split)


FORMAT = DatasetFormat(
    "nsvf", "intrinsics.txt + pose/",
    detect=lambda root: (root / "intrinsics.txt").is_file() and (root / "pose").is_dir(),
    load=load_nsvf, has_split=_has_split, own_val=lambda root: _has_images(root, "test"))
"""NSVF in the registry of :mod:`plenoctree.datasets.dataset`: images named ``0_`` / ``1_`` /
``2_`` (test falls back to ``1_``, and ``val`` is then not a split of its own)."""
