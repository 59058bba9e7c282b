"""COLMAP model folders as a dataset format, and the scene normalisation of COLMAP poses.

Layout::

    root/images/<name>          the photos, ``<name>`` as in the model (sub-folders allowed)
    root/sparse/0/cameras.bin   (or .txt; also accepted: root/sparse/ or root itself)
    root/sparse/0/images.bin    poses (cam_from_world, OpenCV axes)
    root/sparse/0/points3D.bin  sparse points (optional; used for the scene box / depth bounds)

Cameras with lens distortion (SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE, ...) are
undistorted on load by COLMAP's own undistortion (:mod:`plenoctree.datasets.undistort`,
needs pycolmap); every undistorted camera must come out at one image size.

:func:`normalize_scene` decides the capture kind and fixes the world frame (the contract
the rest of the chain relies on; ``docs/capture.md``, "What process does"):

* **kind**: ``forward`` when every optical axis lies within ~25° of their mean
  (:func:`~.camera_sets.capture_kind`: ``|mean forward axis| >= FORWARD_THRESHOLD``), else
  ``360`` (an object seen from around it).
* **360**: up = the mean of the cameras' up axes (becomes world +z); centre = the point
  nearest to every optical axis; scale: median camera distance to it = ``CAMERA_RADIUS``
  (4, as in the Blender scenes). Box: the 0.5–99.5 % percentiles of the sparse points inside
  the camera sphere, padded by 10 % of their extent, as a cube about its own centre (which then
  becomes the world origin); with fewer than ``MIN_POINTS`` points the cube of half-size
  ``CAMERA_RADIUS / 2`` about the centre. When that cube reaches ``SURROUND_FRACTION`` of the
  camera distance the scene surrounds the cameras (a room: real/fox), and the cube grows to
  hold every camera with a margin (``CAMERA_MARGIN``): trained opaque, what lies outside the
  box would be painted on its walls, which no surface does for cameras inside and outside it
  (fox from its frames: 32 % of the cameras were outside the ±4 cube; the tree went from
  27.80 to 29.84 dB with the box alone, docs/capture.md).
* **forward**: LLFF's convention (:mod:`plenoctree.datasets.llff`): per-image depth bounds =
  0.1 / 99.9 % percentiles of the depths of the sparse points in front of it, then the
  smallest bound scaled to ``1 / BD_FACTOR``, recentred on the average camera; NDC rays.

Splits: every 8th image (sorted by name) is a test (and val) image, the others train; "all"
takes every image. Every problem raises :class:`~plenoctree.errors.DatasetError` naming the file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ConfigError, DatasetError
from ._images import CONTENT_NEAR, focus_point, load_images, near_far_from_box
from ._files import check_inside_dataset, check_load_options, confined, holdout_split, take_views
from .base import Dataset, DatasetFormat
from .camera_sets import FORWARD_THRESHOLD, capture_kind
from .cameras import Cameras
from .colmap_model import colmap_c2w, find_colmap_model, read_colmap_model

__all__ = ["load_colmap", "ColmapOptions", "normalize_scene", "SceneFrame", "depth_bounds",
           "capture_kind", "CAMERA_RADIUS", "FORWARD_THRESHOLD", "KINDS"]

CAMERA_RADIUS = 4.0
"""Median camera distance to the scene centre after normalising a 360° capture."""
MIN_POINTS = 50
SURROUND_FRACTION = 0.9
"""A 360° capture whose padded point box reaches this fraction of ``CAMERA_RADIUS`` surrounds
its cameras (a room, not an object on a table): its box then holds every camera."""
CAMERA_MARGIN = 1.1
"""Such a box's half-size: this times the farthest camera's largest coordinate about its centre."""
KINDS = ("auto", "360", "forward")


@dataclass
class SceneFrame:
    """A normalised capture. ``c2w`` float64 ``[N, 4, 4]`` OpenGL camera-to-world in the
    normalised world; ``transform`` float64 ``[4, 4]`` similarity (``x_norm = transform @
    x_in``, scale ``scale``); ``bbox`` float64 ``[2, 3]`` (360° only; forward: ``None``);
    ``bounds`` ``[N, 2]`` near / far depths (normalised units; forward only); ``kind``."""

    c2w: np.ndarray
    transform: np.ndarray
    scale: float
    kind: str
    bbox: np.ndarray | None
    bounds: np.ndarray | None


def _apply(transform: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    s = np.cbrt(np.linalg.det(transform[:3, :3]))
    out = transform[None] @ c2w
    out[:, :3, :3] /= s
    return out


def depth_bounds(c2w: np.ndarray, points: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
    """LLFF per-image near / far depths ``[N, 2]``: 0.1 / 99.9 % percentiles of the depths of
    the points in front of each camera (all cameras' median when a camera sees fewer than
    10). ``points``: ``[P, 3]`` shared by every camera, or one ``[P_i, 3]`` array per camera,
    the points it observes (LLFF's ``imgs2poses`` rule, which ``process`` follows)."""
    out = np.full((len(c2w), 2), np.nan)
    shared = isinstance(points, np.ndarray)
    for i, m in enumerate(np.asarray(c2w, dtype=np.float64)):
        pts = points if shared else np.asarray(points[i], dtype=np.float64).reshape(-1, 3)
        z = (pts - m[:3, 3]) @ (-m[:3, 2])
        z = z[z > 1e-9]
        if len(z) >= 10:
            out[i] = np.percentile(z, 0.1), np.percentile(z, 99.9)
    if np.all(np.isnan(out[:, 0])):
        raise DatasetError("no sparse point lies in front of any camera: cannot bound the depths")
    med = np.nanmedian(out, axis=0)
    out[np.isnan(out[:, 0])] = med
    return out


def _content_near_far(raw_c2w: np.ndarray, points: np.ndarray, scale: float, near: float,
                      far: float) -> tuple[float, float]:
    """``(near, far)`` of a 360° capture widened by its sparse points' depths (normalised
    units ``scale`` × raw): near ``CONTENT_NEAR`` of the smallest, far the largest; the box's
    ``near, far`` kept when no point lies in front of a camera."""
    try:
        b = depth_bounds(raw_c2w, points) * scale
    except DatasetError:
        return near, far
    return max(near, CONTENT_NEAR * float(b[:, 0].min())), max(far, float(b.max()))


def normalize_scene(c2w: np.ndarray, points: np.ndarray | None = None, kind: str = "auto"
                    ) -> SceneFrame:
    """Normalise cameras ``c2w [N, 4, 4]`` (OpenGL) and sparse ``points [P, 3]`` (module
    docstring). ``kind``: "auto", "360" or "forward"."""
    if kind not in KINDS:
        raise ConfigError(f"scene kind must be one of {', '.join(KINDS)}, got {kind!r}")
    c2w = np.asarray(c2w, dtype=np.float64)
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)
    if kind == "auto":
        kind = capture_kind(c2w)
    if kind == "forward":
        from .llff import BD_FACTOR, average_pose

        bounds = depth_bounds(c2w, pts)
        sc = 1.0 / (bounds.min() * BD_FACTOR)
        t = np.diag([sc, sc, sc, 1.0])
        t = np.linalg.inv(average_pose(_apply(t, c2w))) @ t
        return SceneFrame(_apply(t, c2w), t, sc, "forward", None, bounds * sc)
    up = c2w[:, :3, 1].sum(0)
    up /= np.linalg.norm(up)
    centre = focus_point(c2w)
    x = np.cross(np.array([0.1, 0.2, 0.3]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0]), up)
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(up, x), up])              # rows: new x, y, z (= up)
    dist = np.linalg.norm(c2w[:, :3, 3] - centre, axis=1)
    sc = CAMERA_RADIUS / max(float(np.median(dist)), 1e-12)
    t = np.eye(4)
    t[:3, :3] = sc * rot
    t[:3, 3] = -sc * rot @ centre
    moved = (pts @ t[:3, :3].T) + t[:3, 3] if len(pts) else pts
    inside = moved[np.linalg.norm(moved, axis=1) < CAMERA_RADIUS] if len(moved) else moved
    if len(inside) >= MIN_POINTS:
        lo, hi = np.percentile(inside, 0.5, axis=0), np.percentile(inside, 99.5, axis=0)
        pad = 0.1 * (hi - lo)
        lo, hi = lo - pad, hi + pad
        mid, half = 0.5 * (lo + hi), float(0.5 * (hi - lo).max())
        if half >= SURROUND_FRACTION * CAMERA_RADIUS:      # the scene surrounds the cameras
            cams = _apply(t, c2w)[:, :3, 3] - mid
            half = max(min(half, CAMERA_RADIUS), CAMERA_MARGIN * float(np.abs(cams).max()))
    else:
        mid, half = np.zeros(3), CAMERA_RADIUS / 2
    shift = np.eye(4)
    shift[:3, 3] = -mid
    t = shift @ t
    bbox = np.array([[-half] * 3, [half] * 3])
    return SceneFrame(_apply(t, c2w), t, sc, "360", bbox, None)


def _split(n: int, split: str, where: Path) -> list[int]:
    return holdout_split(n, split, where)


@dataclass(frozen=True)
class ColmapOptions:
    """What a COLMAP folder holds beyond the model (:func:`load_colmap`;
    ``load_dataset(root, options=ColmapOptions(...))``)."""

    scene: str = "auto"
    """"auto" (decided from the cameras), "360" or "forward" (NDC rays)."""
    images: str = "images"
    """Name of the image folder under the dataset folder."""


def load_colmap(root: str | os.PathLike, split: str = "train", downscale: int = 1,
                background: Sequence[float] | float = (1.0, 1.0, 1.0),
                limit: int | None = None, spread: bool = False,
                num_threads: int | None = None, options: ColmapOptions | None = None) -> Dataset:
    """Load one split of a COLMAP model folder (module docstring).

    Args:
        root: folder holding ``sparse/0`` (or ``sparse``) and ``images/``.
        split: "train", "val", "test" or "all". downscale: integer area-downscale factor
            (``images_<f>/`` used when present). background, limit, spread, num_threads: as the
            other loaders.
        options: the scene kind and the image folder's name (:class:`ColmapOptions`,
            defaults when None).

    Returns:
        A :class:`Dataset` in the normalised world of :func:`normalize_scene`.
    """
    bg = check_load_options(split, downscale, background, limit)
    opt = options or ColmapOptions()
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    folder = find_colmap_model(root)
    if folder is None:
        raise DatasetError(f"{root}: no COLMAP model (sparse/0/cameras.bin or .txt)")
    model = read_colmap_model(folder)
    order = sorted(model.images, key=lambda i: model.images[i][0])
    names = [model.images[i][0] for i in order]
    raw_c2w = np.stack([colmap_c2w(model.images[i][2], model.images[i][3]) for i in order])
    frame = normalize_scene(raw_c2w, model.points, opt.scene)
    sel = _split(len(order), split, folder)
    sel = take_views(sel, limit, spread)
    f = int(downscale)
    img_dir = root / opt.images
    pre = root / f"{opt.images}_{f}"
    for i in sel:
        check_inside_dataset(names[i], f"{folder / 'images'}: image name")
    use_pre = f > 1 and all((pre / names[i]).is_file() for i in sel)
    paths = [confined(root, (pre if use_pre else img_dir) / names[i]) for i in sel]
    for p in paths:
        if not p.is_file():
            raise DatasetError(f"{p}: image file not found (listed in {folder / 'images'})")
    cams_used = {model.images[order[i]][1] for i in sel}
    distorted = any(model.cameras[c].model not in ("SIMPLE_PINHOLE", "PINHOLE")
                    for c in cams_used)
    factor = 1 if use_pre else f
    imgs, alphas, (w0, h0) = load_images(paths, 1 if distorted else factor, bg, num_threads)
    intr = []
    if distorted:
        from .undistort import undistort_images

        cams = [model.cameras[model.images[order[i]][1]] for i in sel]
        scale = (w0 / cams[0].width) if use_pre else 1.0
        imgs, intr = undistort_images(imgs, cams, scale, paths)
        alphas = None
        if factor > 1:
            h, w = imgs.shape[1] // factor * factor, imgs.shape[2] // factor * factor
            imgs = imgs[:, :h, :w].reshape(len(imgs), h // factor, factor, w // factor, factor,
                                           3).mean(axis=(2, 4), dtype=np.float32)
            intr = intr / factor
    else:
        w, h = imgs.shape[2], imgs.shape[1]
        for i in sel:
            cam = model.cameras[model.images[order[i]][1]]
            p = cam.params
            fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model == "SIMPLE_PINHOLE" else p[:4]
            sx, sy = w / cam.width, h / cam.height
            intr.append((fx * sx, fy * sy, cx * sx, cy * sy))
        intr = np.array(intr)
    h, w = imgs.shape[1:3]
    c2w = frame.c2w[sel].astype(np.float32)
    ndc = frame.kind == "forward"
    try:
        cameras = Cameras(c2w, intr[:, 0], intr[:, 1], intr[:, 2], intr[:, 3], w, h, ndc=ndc)
    except ConfigError as e:
        raise DatasetError(f"{folder}: {e}") from None
    if ndc:
        from .ndc import ndc_bounds

        all_k = np.repeat(intr[:1], len(frame.c2w), 0)
        nfx, nfy = cameras.ndc_focal
        try:
            far, bbox = ndc_bounds(frame.c2w, all_k, w, h, nfx, nfy)
        except ConfigError as e:
            raise DatasetError(f"{folder}: cameras are not forward-facing ({e}); load with "
                               "scene='360'") from None
        near = 0.0
    else:
        bbox = frame.bbox
        near, far = near_far_from_box(frame.c2w, bbox)
        if len(model.points):       # the content's depths set the near plane (as LLFF's)
            near, far = _content_near_far(raw_c2w, model.points, frame.scale, near, far)
    return Dataset(images=imgs, cameras=cameras, near=near, far=far, scene_bbox=bbox,
                   split=split, root=root, background=tuple(float(v) for v in bg),
                   names=[Path(names[i]).stem for i in sel], alphas=alphas, unbounded=not ndc)


FORMAT = DatasetFormat("colmap", "sparse/0/cameras.bin|txt",
                       detect=lambda root: find_colmap_model(root) is not None,
                       load=load_colmap, photos=True, own_val=lambda root: False)
"""COLMAP in the registry of :mod:`plenoctree.datasets.dataset` (a split exists when loading
one of its views does not find it empty; ``val``, every 8th view as ``test``, is not one of
its own)."""
