"""Lens undistortion with COLMAP's own undistorter (pycolmap; no hand-written lens model).

:func:`undistort_images` resamples images taken by distorting cameras (COLMAP's
SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE, FULL_OPENCV, ...) into pinhole images; the
output camera is COLMAP's ``undistort_camera`` choice (every output pixel valid, the field of
view kept as wide as that allows). Needs the ``colmap`` extra.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import DatasetError

__all__ = ["undistort_images", "pinhole_camera", "NERFSTUDIO_MODELS"]

NERFSTUDIO_MODELS = {"OPENCV": ("k1", "k2", "p1", "p2"),
                     "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
                     "RADIAL": ("k1", "k2"), "SIMPLE_RADIAL": ("k1",)}
"""nerfstudio camera models with distortion, and their coefficients in COLMAP's order."""


def _pycolmap(where: Any) -> Any:
    try:
        import pycolmap
    except ImportError:
        raise DatasetError(f"{where}: the images need undistortion (lens distortion in the "
                           "camera model), which uses pycolmap: pip install "
                           "'plenoctree[colmap]'") from None
    return pycolmap


def _camera(pycolmap: Any, model: str, params: np.ndarray, width: int, height: int) -> Any:
    return pycolmap.Camera(model=model, width=int(width), height=int(height),
                           params=np.asarray(params, dtype=np.float64))


#: Undistortion must keep at least this share of each image side: absurd coefficients
#: (``k1 = 1e6``) shrink a photo to a few pixels, which is refused rather than trained on.
MIN_KEPT_SIDE = 0.5


def check_kept_size(where: Any, model: str, params: np.ndarray, size: tuple[int, int],
                    kept: tuple[int, int]) -> None:
    """DatasetError if undistorting a ``size`` (w, h) image of ``model`` keeps less than
    :data:`MIN_KEPT_SIDE` of either side (``kept``: the undistorted w, h)."""
    (w, h), (uw, uh) = size, kept
    if uw < MIN_KEPT_SIDE * w or uh < MIN_KEPT_SIDE * h:
        coeffs = ", ".join(f"{v:g}" for v in np.asarray(params, dtype=np.float64)[
            _N_FOCAL_CENTRE.get(model, 4):])
        raise DatasetError(f"{where}: the {model} distortion ({coeffs}) leaves {uw}x{uh} of "
                           f"the {w}x{h} image after undistortion (less than "
                           f"{MIN_KEPT_SIDE:.0%} of a side): the coefficients are implausible; "
                           "check the camera model and its distortion values")


def pinhole_camera(model: str, params: np.ndarray, width: int, height: int,
                   where: Any = "camera") -> tuple[int, int, np.ndarray]:
    """COLMAP's undistorted pinhole camera for a distorting one: ``(width, height,
    [fx, fy, cx, cy])`` (pixels). DatasetError if it keeps too little of the image."""
    pycolmap = _pycolmap(where)
    cam = _camera(pycolmap, model, params, width, height)
    out = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
    check_kept_size(where, model, params, (width, height), (int(out.width), int(out.height)))
    return int(out.width), int(out.height), np.array(out.params[:4], dtype=np.float64)


#: Leading focal / principal-point parameters of each COLMAP model (the rest: distortion).
_N_FOCAL_CENTRE = {"SIMPLE_PINHOLE": 3, "SIMPLE_RADIAL": 3, "RADIAL": 3,
                   "SIMPLE_RADIAL_FISHEYE": 3, "RADIAL_FISHEYE": 3, "FOV": 4}


def _scaled(model: str, params: np.ndarray, s: float) -> np.ndarray:
    """Params of ``model`` for images scaled by ``s`` (focal and principal point only)."""
    p = np.array(params, dtype=np.float64)
    p[:_N_FOCAL_CENTRE.get(model, 4)] *= s
    return p


def undistort_images(images: np.ndarray, cameras: Sequence[Any], scale: float = 1.0,
                     paths: Sequence[Path] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Undistort float images ``[N, H, W, 3]`` in [0, 1].

    Args:
        cameras: per image an object with ``model``, ``params``, ``width``, ``height`` (the
            full-size camera, as :class:`~plenoctree.datasets.colmap_model.ColmapCamera`).
        scale: the images' size / the cameras' size (pre-downscaled copies).
        paths: image files, for messages.

    Returns:
        ``(images [N, H', W', 3] float32, intrinsics [N, 4] (fx, fy, cx, cy))`` of the pinhole
        cameras, at the images' scale.

    Raises:
        DatasetError: pycolmap missing, or the cameras come out at different sizes.
    """
    where = paths[0] if paths else "images"
    pycolmap = _pycolmap(where)
    opts = pycolmap.UndistortCameraOptions()
    out, intr, size = [], [], None
    n, h, w = images.shape[:3]
    for i in range(n):
        c = cameras[i]
        cam = _camera(pycolmap, c.model, _scaled(c.model, c.params, scale), w, h)
        img8 = np.clip(np.round(images[i] * 255.0), 0, 255).astype(np.uint8)
        bmp, ucam = pycolmap.undistort_image(opts, pycolmap.Bitmap.from_array(img8), cam)
        arr = bmp.to_array()
        if size is None:
            size = arr.shape[:2]
            check_kept_size(paths[i] if paths else f"image {i}", c.model, c.params, (w, h),
                            (arr.shape[1], arr.shape[0]))
        elif arr.shape[:2] != size:
            p = paths[i] if paths else f"image {i}"
            raise DatasetError(f"{p}: undistorts to {arr.shape[1]}x{arr.shape[0]} pixels, the "
                               f"first image to {size[1]}x{size[0]}; all cameras must share one "
                               "undistorted size")
        out.append(arr[..., :3].astype(np.float32) / 255.0)
        intr.append(np.array(ucam.params[:4], dtype=np.float64))
    return np.stack(out), np.stack(intr)
