"""Pinhole cameras and ray generation (OpenGL / Blender convention).

Camera space: x right, y up, the camera looks down -z. ``c2w`` is the 4x4 camera-to-world
matrix. Pixel ``(u, v)`` (column ``u``, row ``v``, row 0 at the top of the image) has its centre
at ``(u + 0.5, v + 0.5)`` pixels; its ray direction in camera space is

    d_cam = ((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1)

normalised, then rotated into world space by ``c2w[:3, :3]``; the origin is ``c2w[:3, 3]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import ConfigError

__all__ = ["Cameras", "generate_rays"]


def _check_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> None:
    for name, val in (("fx", fx), ("fy", fy)):
        if not (isinstance(val, (int, float, np.floating, np.integer)) and math.isfinite(val) and val > 0):
            raise ConfigError(f"camera {name} must be a finite positive number of pixels, got {val!r}")
    for name, val in (("cx", cx), ("cy", cy)):
        if not (isinstance(val, (int, float, np.floating, np.integer)) and math.isfinite(val)):
            raise ConfigError(f"camera {name} must be a finite number of pixels, got {val!r}")
    for name, val in (("width", width), ("height", height)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val <= 0:
            raise ConfigError(f"camera {name} must be a positive integer, got {val!r}")


def _check_c2w(c2w: np.ndarray, batched: bool) -> np.ndarray:
    try:
        arr = np.asarray(c2w, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"c2w: not a numeric array ({e})") from None
    want = "[N, 4, 4]" if batched else "[4, 4]"
    if (batched and (arr.ndim != 3 or arr.shape[1:] != (4, 4))) or (not batched and arr.shape != (4, 4)):
        raise ConfigError(f"c2w: expected shape {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError("c2w: contains NaN or infinite values")
    return arr


def generate_rays(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                  width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays through every pixel centre of one pinhole camera.

    Args:
        c2w: ``[4, 4]`` camera-to-world matrix (OpenGL: camera looks down -z, y up).
        fx, fy: focal lengths in pixels. cx, cy: principal point in pixels (``W/2, H/2`` for a
            centred camera; pixel ``(u, v)`` spans ``[u, u+1) x [v, v+1)``).
        width, height: image size in pixels.

    Returns:
        ``origins [H, W, 3]`` (world units, all equal to ``c2w[:3, 3]``) and unit
        ``dirs [H, W, 3]``, both float32 numpy arrays; element ``[v, u]`` is pixel column ``u``,
        row ``v`` (row 0 = top).
    """
    _check_intrinsics(fx, fy, cx, cy, width, height)
    m = _check_c2w(c2w, batched=False)
    u = (np.arange(width, dtype=np.float64) + 0.5 - cx) / fx
    v = -(np.arange(height, dtype=np.float64) + 0.5 - cy) / fy
    d_cam = np.empty((height, width, 3), dtype=np.float64)
    d_cam[..., 0] = u[None, :]
    d_cam[..., 1] = v[:, None]
    d_cam[..., 2] = -1.0
    dirs = d_cam @ m[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = np.broadcast_to(m[:3, 3], dirs.shape).astype(np.float32)
    return origins, dirs.astype(np.float32)


@dataclass
class Cameras:
    """A set of ``N`` pinhole cameras sharing intrinsics (OpenGL / Blender convention).

    Attributes:
        c2w: float32 ``[N, 4, 4]`` camera-to-world matrices (world units).
        fx, fy, cx, cy: focal lengths and principal point, pixels.
        width, height: image size, pixels.
        ndc: forward-facing scene in normalised device coordinates (not supported yet:
            :meth:`rays` raises :class:`ConfigError` for NDC cameras).

    Invalid values raise :class:`~plenoctree.errors.ConfigError`.
    """

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    ndc: bool = False

    def __post_init__(self) -> None:
        _check_intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)
        self.c2w = _check_c2w(self.c2w, batched=True).astype(np.float32)
        self.fx, self.fy, self.cx, self.cy = (float(self.fx), float(self.fy),
                                              float(self.cx), float(self.cy))
        self.width, self.height = int(self.width), int(self.height)
        self.ndc = bool(self.ndc)

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Cameras):
            return NotImplemented
        return (np.array_equal(self.c2w, other.c2w)
                and (self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.ndc)
                == (other.fx, other.fy, other.cx, other.cy, other.width, other.height, other.ndc))

    def _index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            raise ConfigError(f"camera index must be an integer, got {index!r}")
        n = len(self)
        if not -n <= index < n:
            raise ConfigError(f"camera index {index} out of range for {n} cameras")
        return int(index) % n

    def rays(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Rays of camera ``index``: ``origins [H, W, 3]``, unit ``dirs [H, W, 3]`` (float32).

        See :func:`generate_rays` for the pixel convention.
        """
        i = self._index(index)
        if self.ndc:
            raise ConfigError("NDC (forward-facing) cameras are not supported yet")
        return generate_rays(self.c2w[i], self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def all_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays of every camera: ``origins [N, H, W, 3]``, unit ``dirs [N, H, W, 3]`` (float32)."""
        shape = (len(self), self.height, self.width, 3)
        origins = np.empty(shape, np.float32)
        dirs = np.empty(shape, np.float32)
        for i in range(len(self)):
            origins[i], dirs[i] = self.rays(i)
        return origins, dirs

    def scaled(self, factor: int) -> "Cameras":
        """Cameras for images downscaled by an integer ``factor`` (area averaging of blocks).

        Focal lengths and principal point are divided by ``factor``; the size must be divisible
        by ``factor`` (otherwise :class:`ConfigError`). Pixel ``u'`` of the result covers pixels
        ``[u' f, (u'+1) f)`` of the original, and its centre ray is the original ray through
        ``(u' + 0.5) f``.
        """
        if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
            raise ConfigError(f"downscale factor must be a positive integer, got {factor!r}")
        if self.width % factor or self.height % factor:
            raise ConfigError(f"downscale factor {factor} does not divide the image size "
                              f"{self.width}x{self.height}")
        f = float(factor)
        return Cameras(self.c2w.copy(), self.fx / f, self.fy / f, self.cx / f, self.cy / f,
                       self.width // factor, self.height // factor, self.ndc)

    def select(self, indices: Sequence[int] | np.ndarray | slice) -> "Cameras":
        """A new :class:`Cameras` holding the cameras ``c2w[indices]`` with the same intrinsics."""
        c2w = self.c2w[indices]
        if c2w.ndim == 2:
            c2w = c2w[None]
        return Cameras(c2w.copy(), self.fx, self.fy, self.cx, self.cy, self.width, self.height,
                       self.ndc)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in world coordinates, float32 ``[N, 3]``."""
        return self.c2w[:, :3, 3].copy()
