"""Loader for LLFF captures (``poses_bounds.npy`` + ``images[_N]/``): forward-facing ones, and
inward-facing 360° ones in the same layout (mip-NeRF 360's scenes ship it).

Layout::

    root/poses_bounds.npy   float [N, 17]: per image a 3x5 matrix (row-major, 15 values) then
                            the near / far depth bounds of its content
    root/images/            the N images (JPEG or PNG), sorted by name = pose order
    root/images_4/ ...      optional pre-downscaled copies (used for ``downscale=4``)

The 3x5 matrix is ``[R | t | hwf]``: camera-to-world rotation whose columns are the camera's
(down, right, backwards) axes, its centre ``t``, and ``hwf = (H, W, focal)`` of the
full-resolution images. The standard conversion (NeRF's LLFF loader, reimplemented here):

1. columns reordered to the OpenGL (right, up, backwards) axes: ``(x, y, z) = (c1, -c0, c2)``;
2. scaled so that the smallest near bound becomes ``1 / bd_factor`` (``bd_factor = 0.75``),
   which puts every point in front of the NDC near plane ``z = -1``;
3. recentred: the "average" camera (mean centre, mean backwards axis, mean up) becomes the
   identity, so the scene is seen looking down the world -z axis;
4. (``spherify``, for inward-facing 360° captures) re-centred on the point nearest to all
   optical axes, up axis = mean camera offset, and scaled to unit camera distance.

Which kind a folder holds is decided by its cameras unless :class:`LLFFOptions` says
(``spherify=None``, the default): cameras whose optical axes spread as around an object are a
360° capture (``camera_sets.capture_kind``, the rule ``process`` applies to photos), which is
spherified and gets no NDC; the decision is logged.

Forward-facing scenes use NDC rays (:mod:`plenoctree.datasets.ndc`, near plane 1): the
dataset's near/far are 0 and the NDC length of the longest ray, and its ``scene_bbox`` is the
NDC box holding every camera's rays (z in [-1, 1]). ``llffhold = 8``: images 0, 8, 16, ...
form the test (and val) split, the rest the training split. :func:`llff_render_cameras` gives
the spiral (or, spherified, circular) video path. Every problem raises
:class:`~plenoctree.errors.DatasetError` naming the file; nothing is returned half-loaded.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ConfigError, DatasetError
from ._images import CONTENT_NEAR, image_files, load_images, probe_size
from ._files import HOLDOUT, check_load_options, holdout_split, take_views
from .base import Dataset, DatasetFormat
from .cameras import Cameras
from .ndc import ndc_bounds
from .padding import border_padding, crop_padding

__all__ = ["load_llff", "LLFFOptions", "read_llff", "LLFFScene", "llff_render_cameras",
           "spiral_path", "average_pose", "write_llff", "llff_matches_colmap", "LLFF_HOLD",
           "BD_FACTOR"]

logger = logging.getLogger(__name__)

LLFF_HOLD = HOLDOUT
"""Every ``LLFF_HOLD``-th image (0, 8, 16, ...) is held out for testing (``_files.HOLDOUT``)."""
BD_FACTOR = 0.75
"""The smallest near bound is scaled to ``1 / BD_FACTOR``."""
POSES_FILE = "poses_bounds.npy"


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _view_matrix(back: np.ndarray, up: np.ndarray, center: np.ndarray) -> np.ndarray:
    """OpenGL c2w ``[4, 4]`` with backwards axis ``back``, up close to ``up``, at ``center``."""
    z = _normalize(back)
    x = _normalize(np.cross(up, z))
    y = _normalize(np.cross(z, x))
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, center
    return m


def average_pose(c2w: np.ndarray) -> np.ndarray:
    """The LLFF "average" camera of ``c2w [N, 4, 4]``: mean centre, backwards axis along the
    sum of backwards axes, up as close as possible to the sum of up axes (float64 ``[4, 4]``)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return _view_matrix(c2w[:, :3, 2].sum(0), c2w[:, :3, 1].sum(0), c2w[:, :3, 3].mean(0))


def _apply(transform: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Apply a similarity ``transform`` (``s R | t``) to camera-to-world matrices, keeping the
    rotation parts orthonormal."""
    s = np.cbrt(np.linalg.det(transform[:3, :3]))
    out = transform[None] @ c2w
    out[:, :3, :3] /= s
    return out


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse ``poses_bounds.npy``: OpenGL ``c2w [N, 4, 4]``, ``bounds [N, 2]``, ``hwf [N, 3]``
    (all float64, file coordinates, no rescaling). DatasetError naming ``path`` when invalid."""
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except Exception as e:  # noqa: BLE001 - corrupt / pickled / not an npy file
        raise DatasetError(f"{path}: not a readable .npy array ({type(e).__name__}: {e})") from None
    if not isinstance(arr, np.ndarray) or not (np.issubdtype(arr.dtype, np.floating)
                                               or np.issubdtype(arr.dtype, np.integer)):
        raise DatasetError(f"{path}: expected a float array, got dtype {getattr(arr, 'dtype', '?')}")
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] < 1:
        raise DatasetError(f"{path}: expected shape [N, 17] (3x5 pose + near/far per image), "
                           f"got {list(arr.shape)}")
    arr = arr.astype(np.float64)
    bad = np.nonzero(~np.all(np.isfinite(arr), axis=1))[0]
    if bad.size:
        raise DatasetError(f"{path}: pose/bounds row {int(bad[0])} contains non-finite values")
    m = arr[:, :15].reshape(-1, 3, 5)
    hwf = m[:, :, 4].copy()
    bounds = arr[:, 15:17].copy()
    if np.any(hwf <= 0):
        raise DatasetError(f"{path}: image height, width and focal (column 5) must be positive")
    if np.any(hwf[:, :2] != hwf[0, :2]):
        i = int(np.nonzero(np.any(hwf[:, :2] != hwf[0, :2], axis=1))[0][0])
        raise DatasetError(f"{path}: images of mixed sizes: row {i} says "
                           f"{hwf[i, 1]:g}x{hwf[i, 0]:g}, row 0 {hwf[0, 1]:g}x{hwf[0, 0]:g}")
    if np.any(bounds[:, 0] <= 0) or np.any(bounds[:, 1] < bounds[:, 0]):
        i = int(np.nonzero((bounds[:, 0] <= 0) | (bounds[:, 1] < bounds[:, 0]))[0][0])
        raise DatasetError(f"{path}: row {i}: depth bounds must satisfy 0 < near <= far, got "
                           f"{bounds[i].tolist()}")
    rot = m[:, :, :3]
    if np.any(np.abs(np.einsum("nji,njk->nik", rot, rot) - np.eye(3)) > 1e-2):
        raise DatasetError(f"{path}: pose rotations are not orthonormal")
    c2w = np.tile(np.eye(4), (len(arr), 1, 1))
    c2w[:, :3, 0] = rot[:, :, 1]          # right
    c2w[:, :3, 1] = -rot[:, :, 0]         # up = -down
    c2w[:, :3, 2] = rot[:, :, 2]          # backwards
    c2w[:, :3, 3] = m[:, :, 3]
    return c2w, bounds, hwf


@dataclass
class LLFFScene:
    """All cameras of an LLFF capture after the standard normalisation.

    Attributes:
        c2w: float64 ``[N, 4, 4]`` OpenGL camera-to-world, normalised world.
        bounds: float64 ``[N, 2]`` near / far content depths, normalised world units.
        hwf: float64 ``[N, 3]`` (H, W, focal) from the file (full-resolution pixels).
        transform: float64 ``[4, 4]`` similarity taking file coordinates to normalised ones
            (``x_norm = transform @ x_file``); its scale is ``scale``.
        scale: the overall length scale of ``transform``.
        spherify: whether the spherical normalisation was applied.
    """

    c2w: np.ndarray
    bounds: np.ndarray
    hwf: np.ndarray
    transform: np.ndarray
    scale: float
    spherify: bool


def _spherify(c2w: np.ndarray) -> np.ndarray:
    """The similarity of the spherical normalisation (see module docstring, step 4)."""
    from ._images import focus_point

    center = focus_point(c2w)
    up = _normalize((c2w[:, :3, 3] - center).mean(0))
    x = _normalize(np.cross(np.array([0.1, 0.2, 0.3]), up))
    y = _normalize(np.cross(up, x))
    frame = np.eye(4)
    frame[:3, 0], frame[:3, 1], frame[:3, 2], frame[:3, 3] = x, y, up, center
    reset = np.linalg.inv(frame)
    moved = _apply(reset, c2w)
    rad = math.sqrt(float(np.mean(np.sum(moved[:, :3, 3] ** 2, axis=1))))
    if not rad > 0:
        raise DatasetError("spherify: all cameras sit at the focus point")
    return np.diag([1.0 / rad] * 3 + [1.0]) @ reset


#: ``poses_bounds.npy`` files already said to be 360° captures in this process.
_SAID_360: set[str] = set()


def read_llff(root: str | os.PathLike, recenter: bool = True, bd_factor: float | None = BD_FACTOR,
              spherify: bool | None = False) -> LLFFScene:
    """Read ``root/poses_bounds.npy`` and normalise it (module docstring, steps 1-4).

    ``bd_factor=None`` skips the rescaling, ``recenter=False`` the recentring (then the file's
    world frame is kept, up to the scale). ``spherify=None``: when the cameras surround the
    scene (:func:`~.camera_sets.capture_kind` of the file's poses), said in the log; the
    result's ``spherify`` says what was done.
    """
    from .camera_sets import capture_kind

    root = Path(root)
    path = root / POSES_FILE
    c2w, bounds, hwf = read_poses_bounds(path)
    if spherify is None:
        spherify = capture_kind(c2w) == "360"
        if spherify and str(path) not in _SAID_360:      # once a file: a run loads it often
            _SAID_360.add(str(path))
            logger.info("%s: the cameras surround the scene: a 360° capture (spherical "
                        "normalisation, no NDC rays)", path)
    transform = np.eye(4)
    if bd_factor is not None:
        if not (isinstance(bd_factor, (int, float)) and 0 < bd_factor and math.isfinite(bd_factor)):
            raise ConfigError(f"bd_factor must be a positive number or None, got {bd_factor!r}")
        sc = 1.0 / (bounds.min() * bd_factor)
        transform = np.diag([sc, sc, sc, 1.0])
    if recenter:
        transform = np.linalg.inv(average_pose(_apply(transform, c2w))) @ transform
    if spherify:
        transform = _spherify(_apply(transform, c2w)) @ transform
    scale = float(np.cbrt(np.linalg.det(transform[:3, :3])))
    return LLFFScene(_apply(transform, c2w), bounds * scale, hwf, transform, scale, spherify)


def spiral_path(c2w: np.ndarray, bounds: np.ndarray, n_frames: int = 120, n_rots: int = 2,
                zrate: float = 0.5) -> np.ndarray:
    """The LLFF spiral video path around the average camera: ``[n_frames, 4, 4]`` float64.

    Cameras move on an elliptic spiral (radii: 90th percentile of the camera offsets per
    axis, ``n_rots`` turns, depth oscillating at ``zrate`` of the turn rate) and look at a
    focus point at the harmonic blend ``1 / (0.25 / near + 0.75 / far)`` of the content depths
    (``near = 0.9 min bound``, ``far = 5 max bound``).
    """
    avg = average_pose(c2w)
    up = _normalize(c2w[:, :3, 1].sum(0))
    close, inf = bounds.min() * 0.9, bounds.max() * 5.0
    focus = 1.0 / (0.25 / close + 0.75 / inf)
    rads = np.append(np.percentile(np.abs(c2w[:, :3, 3]), 90, axis=0), 1.0)
    out = []
    for theta in np.linspace(0.0, 2.0 * math.pi * n_rots, n_frames + 1)[:-1]:
        c = avg[:3, :4] @ (np.array([math.cos(theta), -math.sin(theta),
                                     -math.sin(theta * zrate), 1.0]) * rads)
        target = avg[:3, :4] @ np.array([0.0, 0.0, -focus, 1.0])
        out.append(_view_matrix(c - target, up, c))
    return np.stack(out) if out else np.zeros((0, 4, 4))


def _circle_path(c2w: np.ndarray, n_frames: int) -> np.ndarray:
    """Spherified scenes: a circle at the cameras' mean height, looking at the z axis."""
    t = c2w[:, :3, 3]
    zh = float(t[:, 2].mean())
    rad = math.sqrt(max(float(np.mean(np.sum(t ** 2, 1))) - zh * zh, 1e-12))
    out = []
    for th in np.linspace(0.0, 2.0 * math.pi, n_frames, endpoint=False):
        pos = np.array([rad * math.cos(th), rad * math.sin(th), zh])
        back = np.array([pos[0], pos[1], 0.0])
        out.append(_view_matrix(back, np.array([0.0, 0.0, 1.0]), pos))
    return np.stack(out) if out else np.zeros((0, 4, 4))


def _images_for(root: Path, n_poses: int, downscale: int) -> tuple[Path, list[Path], int]:
    """Image folder, its files and the on-the-fly factor for ``downscale``."""
    folder, factor = root / "images", downscale
    if downscale > 1 and (root / f"images_{downscale}").is_dir():
        folder, factor = root / f"images_{downscale}", 1
    if not folder.is_dir():
        raise DatasetError(f"{folder}: image folder not found (LLFF datasets keep their images "
                           f"in images/ or images_<factor>/ next to {POSES_FILE})")
    files = image_files(folder)
    if len(files) != n_poses:
        raise DatasetError(f"{root / POSES_FILE}: {n_poses} poses but {folder} holds "
                           f"{len(files)} images (counts must match)")
    return folder, files, factor


def _intrinsics(hwf: np.ndarray, size: tuple[int, int], where: Path) -> tuple[np.ndarray, ...]:
    """fx, fy ``[N]`` and cx, cy for images of ``size`` (W, H) given the file's ``hwf``."""
    w, h = size
    sx, sy = w / hwf[0, 1], h / hwf[0, 0]
    if abs(sx - sy) > 0.01 * max(sx, sy) + 1.0 / min(w, h):
        raise DatasetError(f"{where}: images are {w}x{h} but {POSES_FILE} says "
                           f"{hwf[0, 1]:g}x{hwf[0, 0]:g} (different aspect ratio)")
    return hwf[:, 2] * sx, hwf[:, 2] * sy, w / 2.0, h / 2.0


def _frustum_box(c2w: np.ndarray, k: np.ndarray, w: int, h: int, near: float,
                 far: float) -> np.ndarray:
    """Box around every camera's viewing frustum between depths ``near`` and ``far``."""
    us = np.array([0.0, w, 0.0, w])
    vs = np.array([0.0, 0.0, h, h])
    d = np.stack([(us[None] - k[:, 2:3]) / k[:, 0:1], -(vs[None] - k[:, 3:4]) / k[:, 1:2],
                  -np.ones((len(k), 4))], -1)
    d = np.einsum("nij,nkj->nki", c2w[:, :3, :3], d)
    pts = np.concatenate([c2w[:, None, :3, 3] + depth * d for depth in (near, far)], 1)
    pts = pts.reshape(-1, 3)
    return np.stack([pts.min(0), pts.max(0)])


@dataclass(frozen=True)
class LLFFOptions:
    """How an LLFF capture is split and normalised (:func:`load_llff`,
    :func:`llff_render_cameras`; ``load_dataset(root, options=LLFFOptions(...))``)."""

    llffhold: int = LLFF_HOLD
    """Every ``llffhold``-th image is a test image (0: none; :func:`llff_render_cameras`
    ignores it)."""
    ndc: bool | None = None
    """NDC rays (None: yes unless ``spherify``)."""
    spherify: bool | None = None
    """Spherical normalisation for inward-facing 360° captures (no NDC); None: when the
    cameras surround the scene (:func:`read_llff`) and ``ndc`` is not given."""
    recenter: bool = True
    """Recentre on the average pose (:func:`read_llff`); False keeps the file's world frame."""
    bd_factor: float | None = BD_FACTOR
    """Rescale so the nearest depth bound is ``1 / bd_factor`` (:func:`read_llff`); None keeps
    the file's scale."""


def llff_matches_colmap(root: str | os.PathLike) -> bool:
    """Whether ``root/poses_bounds.npy`` and the COLMAP model beside it (``sparse/0``, as
    mip-NeRF 360's scenes ship both) pose the same photos: the model holds every photo of the
    LLFF image folder (by file stem) and the two sets of cameras agree up to a similarity
    (:func:`~plenoctree.datasets.camera_sets.same_cameras`). Then the folder is one dataset, read
    as LLFF (``poses_bounds.npy`` with its ``images_<N>/``). False when anything is missing
    or unreadable."""
    from .camera_sets import same_cameras
    from .colmap_model import colmap_c2w, find_colmap_model, read_colmap_model

    root = Path(root)
    try:
        c2w, _, _ = read_poses_bounds(root / POSES_FILE)
        folders = sorted(root.glob("images*"), key=lambda p: (p.name != "images", p.name))
        files = next((image_files(f) for f in folders if f.is_dir()), [])
        model = find_colmap_model(root)
        if len(files) != len(c2w) or model is None:
            return False
        poses = {Path(name).stem: colmap_c2w(q, t)
                 for name, _, q, t in read_colmap_model(model).images.values()}
    except DatasetError:
        return False
    if any(f.stem not in poses for f in files):
        return False
    return same_cameras(np.stack([poses[f.stem] for f in files]), c2w)


def _spherify_option(opt: LLFFOptions) -> bool | None:
    """``opt.spherify``; when unset, False if ``opt.ndc`` is given (either way), else None
    (:func:`read_llff` decides by the cameras)."""
    if opt.spherify is not None:
        return bool(opt.spherify)
    return False if opt.ndc is not None else None


def load_llff(root: str | os.PathLike, split: str = "train", downscale: int = 1,
              background: Sequence[float] | float = (1.0, 1.0, 1.0),
              limit: int | None = None, spread: bool = False,
              num_threads: int | None = None, options: LLFFOptions | None = None) -> Dataset:
    """Load one split of an LLFF capture.

    Args:
        root: folder holding ``poses_bounds.npy`` and ``images/``.
        split: "train", "test", "val" (= test, as in JaxNeRF) or "all".
        downscale: integer factor; ``images_<downscale>/`` is used when present, otherwise
            ``images/`` is area-downscaled on the fly (the factor must divide the size).
        background: RGB for transparent pixels (PNGs with alpha). limit: first ``limit``
            images of the split (``spread``: evenly spaced). num_threads: decoding threads.
        options: the split (``llffhold``) and the normalisation (``ndc``, ``spherify``,
            ``recenter``, ``bd_factor``): :class:`LLFFOptions`, defaults when None.

    Returns:
        A :class:`Dataset`. NDC: cameras with ``ndc=True``, near 0, far = longest NDC ray,
        ``scene_bbox`` = NDC box of all cameras' rays. Otherwise near/far = 0.9 × smallest /
        largest depth bound and ``scene_bbox`` the box of all viewing frusta (spherified:
        ``[-1, 1]^3``, the cameras' unit sphere).

    Raises:
        DatasetError: bad ``poses_bounds.npy``, image count different from the pose count,
            unreadable or mixed-size images, size inconsistent with the poses' ``hwf``.
        ConfigError: bad option values.
    """
    bg = check_load_options(split, downscale, background, limit)
    opt = options or LLFFOptions()
    if opt.ndc and opt.spherify:
        raise ConfigError("LLFF: ndc and spherify exclude each other (NDC is for forward-facing "
                          "captures, spherify for 360° ones)")
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    scene = read_llff(root, recenter=opt.recenter, bd_factor=opt.bd_factor,
                      spherify=_spherify_option(opt))
    spherify = scene.spherify
    ndc = (not spherify) if opt.ndc is None else opt.ndc
    n = len(scene.c2w)
    folder, files, factor = _images_for(root, n, int(downscale))
    sel = holdout_split(n, split, root / POSES_FILE, opt.llffhold)
    sel = take_views(sel, limit, spread)
    size = probe_size(files[sel[0]])
    fx, fy, cx, cy = _intrinsics(scene.hwf, size, folder)
    images, alphas, size2 = load_images([files[i] for i in sel], factor, bg, num_threads)
    if size2 != size:   # pragma: no cover - header and decoder disagree
        raise DatasetError(f"{files[sel[0]]}: header and pixels disagree on the size")
    w, h = size
    try:
        all_cams = Cameras(scene.c2w.astype(np.float32), fx, fy, cx, cy, w, h, ndc=ndc)
        all_cams = all_cams.scaled(factor)
    except ConfigError as e:
        raise DatasetError(f"{root / POSES_FILE}: {e}") from None
    images, alphas, all_cams = crop_padding(images, alphas, all_cams, *border_padding(files),
                                            factor)
    cams = all_cams.select(sel)
    k = all_cams.intrinsics_array()
    if ndc:
        nfx, nfy = all_cams.ndc_focal
        try:
            far, bbox = ndc_bounds(all_cams.c2w, k, all_cams.width, all_cams.height, nfx, nfy)
        except ConfigError as e:
            raise DatasetError(f"{root / POSES_FILE}: cameras are not forward-facing after "
                               f"recentring, NDC impossible ({e}); try spherify=True") from None
        near = 0.0
    else:
        near, far = float(scene.bounds.min() * CONTENT_NEAR), float(scene.bounds.max())
        if spherify:
            bbox = np.array([[-1.0] * 3, [1.0] * 3])
        else:
            bbox = _frustum_box(all_cams.c2w.astype(np.float64), k, all_cams.width,
                                all_cams.height, near, far)
    return Dataset(images=images, cameras=cams, near=near, far=far, scene_bbox=bbox,
                   split=split, root=root, background=tuple(float(v) for v in bg),
                   names=[files[i].stem for i in sel], alphas=alphas, unbounded=spherify)


def llff_render_cameras(root: str | os.PathLike, n_frames: int = 120, downscale: int = 1,
                        n_rots: int = 2, zrate: float = 0.5,
                        options: LLFFOptions | None = None) -> Cameras:
    """The video path of an LLFF capture as :class:`Cameras` matching :func:`load_llff`'s
    with the same ``options`` (same normalisation, intrinsics of the first image at
    ``downscale``, NDC flag): the spiral of :func:`spiral_path` (``n_rots`` turns, ``zrate``),
    or a circle when ``options.spherify``."""
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise ConfigError(f"n_frames must be a positive integer, got {n_frames!r}")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise ConfigError(f"downscale must be a positive integer, got {downscale!r}")
    root = Path(root)
    opt = options or LLFFOptions()
    scene = read_llff(root, recenter=opt.recenter, bd_factor=opt.bd_factor,
                      spherify=_spherify_option(opt))
    spherify = scene.spherify
    folder, files, factor = _images_for(root, len(scene.c2w), int(downscale))
    size = probe_size(files[0])
    fx, fy, cx, cy = _intrinsics(scene.hwf, size, folder)
    path = (_circle_path(scene.c2w, n_frames) if spherify
            else spiral_path(scene.c2w, scene.bounds, n_frames, n_rots, zrate))
    ndc = (not spherify) if opt.ndc is None else opt.ndc
    try:
        cams = Cameras(path.astype(np.float32), float(np.mean(fx)), float(np.mean(fy)), cx, cy,
                       size[0], size[1], ndc=ndc)
        return crop_padding(None, None, cams.scaled(factor), *border_padding(files), factor)[2]
    except ConfigError as e:
        raise DatasetError(f"{root / POSES_FILE}: {e}") from None


def write_llff(out_dir: str | os.PathLike, c2w: np.ndarray, images: np.ndarray, focal: float,
               bounds: np.ndarray, suffix: str = ".png") -> Path:
    """Write an LLFF capture: ``poses_bounds.npy`` and ``images/<i>.<suffix>``.

    Args:
        c2w: ``[N, 4, 4]`` OpenGL camera-to-world (the file stores (down, right, back) axes).
        images: ``[N, H, W, 3]`` uint8, or float in [0, 1]. focal: pixels (square pixels,
            principal point at the centre, as LLFF assumes).
        bounds: ``[N, 2]`` near / far content depths per image.
        suffix: ".png" (lossless) or ".jpg".

    Files are written atomically; returns ``Path(out_dir)``.
    """
    from PIL import Image

    from .._util import atomic_write

    c2w = np.asarray(c2w, dtype=np.float64)
    n, h, w = images.shape[:3]
    bounds = np.asarray(bounds, dtype=np.float64).reshape(n, 2)
    m = np.zeros((n, 3, 5))
    m[:, :, 0] = -c2w[:, :3, 1]
    m[:, :, 1] = c2w[:, :3, 0]
    m[:, :, 2] = c2w[:, :3, 2]
    m[:, :, 3] = c2w[:, :3, 3]
    m[:, :, 4] = [h, w, focal]
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    width = max(3, len(str(n - 1)))
    fmt = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}[suffix.lower()]
    for i in range(n):
        img = images[i]
        if img.dtype != np.uint8:
            img = np.clip(np.round(np.asarray(img, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
        with atomic_write(out / "images" / f"{i:0{width}d}{suffix}") as fh:
            Image.fromarray(np.ascontiguousarray(img)).save(fh, format=fmt, quality=95)
    with atomic_write(out / POSES_FILE) as fh:
        np.save(fh, np.concatenate([m.reshape(n, 15), bounds], 1))
    return out


FORMAT = DatasetFormat("llff", "poses_bounds.npy",
                       detect=lambda root: (root / "poses_bounds.npy").is_file(),
                       load=load_llff, has_split=lambda root, split: split in ("train", "test"),
                       photos=True)
"""LLFF in the registry of :mod:`plenoctree.datasets.dataset`: ``train`` and ``test`` (every
``llffhold``-th image; its ``val`` is the test set, so not a separate split)."""
