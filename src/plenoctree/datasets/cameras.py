"""Pinhole cameras and ray generation (OpenGL / Blender convention).

Camera space: x right, y up, the camera looks down -z. ``c2w`` is the 4x4 camera-to-world
matrix. Pixel ``(u, v)`` (column ``u``, row ``v``, row 0 at the top of the image) has its centre
at ``(u + 0.5, v + 0.5)`` pixels; its ray direction in camera space is

    d_cam = ((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1)

normalised, then rotated into world space by ``c2w[:3, :3]``; the origin is ``c2w[:3, 3]``.
"""

from __future__ import annotations

import dataclasses

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError

__all__ = ["Cameras", "generate_rays", "check_image_size", "MAX_IMAGE_PIXELS"]

#: Most pixels of one image, read or rendered: 2^27 (134 MP, e.g. 11585 x 11585). A render of
#: that size already needs ~6 GB for its rays; an image header or a ``--width/--height``
#: beyond it is refused before anything is allocated.
MAX_IMAGE_PIXELS = 1 << 27
#: Plausible intrinsics: focal lengths within [1e-3, 1e3] x the larger image side (fields of
#: view from ~0.06 to ~179.9 degrees), principal point within one image size of the image.
FOCAL_RANGE = (1e-3, 1e3)


def check_image_size(width: Any, height: Any, what: str = "image size") -> tuple[int, int]:
    """``(width, height)`` as ints if both are positive integers whose product is at most
    :data:`MAX_IMAGE_PIXELS`; ``ConfigError`` naming ``what`` otherwise."""
    for v in (width, height):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise ConfigError(f"{what} must be positive integers, got {width!r} x {height!r}")
    w, h = int(width), int(height)
    if w * h > MAX_IMAGE_PIXELS:
        raise ConfigError(f"{what} {w}x{h} is {w * h / 1e6:.0f} MP; at most "
                          f"{MAX_IMAGE_PIXELS / 1e6:.0f} MP per image (e.g. 8192x8192)")
    return w, h


def _check_plausible(fx: Any, fy: Any, cx: Any, cy: Any, width: int, height: int) -> None:
    """ConfigError for intrinsics no real camera has (see :data:`FOCAL_RANGE`)."""
    side = max(width, height)
    lo, hi = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    for name, v in (("fx", fx), ("fy", fy)):
        v = np.asarray(v, dtype=np.float64)
        if not ((v >= lo) & (v <= hi)).all():
            raise ConfigError(f"camera {name} = {float(v.flat[0]):g} px is implausible for a "
                              f"{width}x{height} image (expected {lo:g} to {hi:g} px)")
    for name, v, size in (("cx", cx, width), ("cy", cy, height)):
        v = np.asarray(v, dtype=np.float64)
        if not ((v >= -size) & (v <= 2 * size)).all():
            raise ConfigError(f"camera {name} = {float(v.flat[0]):g} px is implausible for a "
                              f"{width}x{height} image (expected -{size} to {2 * size} px)")


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
    bad = degenerate_rotations(arr.reshape(-1, 4, 4))
    if bad.size:
        raise ConfigError(f"c2w{f'[{int(bad[0])}]' if batched else ''}: the rotation part "
                          "c2w[:3, :3] is singular (e.g. all zeros); every camera needs three "
                          "independent axes")
    return arr


def degenerate_rotations(c2w: np.ndarray) -> np.ndarray:
    """Indices of the ``[N, 4, 4]`` matrices whose ``[:3, :3]`` block is singular.

    Scale-invariant: ``|det R| <= 1e-6 · Π |column|`` (an all-zero, rank-deficient or
    nearly flat rotation); scaled or mirrored rotations pass.
    """
    r = np.asarray(c2w, dtype=np.float64)[:, :3, :3]
    norms = np.linalg.norm(r, axis=1).prod(axis=-1)
    det = np.abs(np.linalg.det(r))
    return np.flatnonzero(~(det > 1e-6 * norms) | (norms == 0))


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


def _intrinsic(name: str, val: Any, n: int, positive: bool) -> float | np.ndarray:
    """One intrinsic: a float, or a float64 ``[n]`` array when the cameras' values differ."""
    arr = None
    if not isinstance(val, (int, float, np.floating, np.integer)) or isinstance(val, bool):
        try:
            arr = np.asarray(val, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.ndim > 1 or (arr.ndim == 1 and arr.shape != (n,)):
            raise ConfigError(f"camera {name} must be a number or an array of {n} numbers "
                              f"(one per camera), got {val!r}")
        if arr.ndim == 0:
            val, arr = float(arr), None
    vals = np.atleast_1d(np.asarray(val if arr is None else arr, dtype=np.float64))
    what = "a finite positive number of pixels" if positive else "a finite number of pixels"
    if not np.all(np.isfinite(vals)) or (positive and not np.all(vals > 0)):
        raise ConfigError(f"camera {name} must be {what}, got {val!r}")
    if arr is None or bool(np.all(arr == arr[0])):
        return float(vals[0])
    out = arr.copy()
    out.flags.writeable = False
    return out


def _pick(v: float | np.ndarray, i: Any) -> float | np.ndarray:
    return v if isinstance(v, float) else v[i]


@dataclass
class Cameras:
    """A set of ``N`` pinhole cameras of one image size (OpenGL / Blender convention).

    Attributes:
        c2w: float32 ``[N, 4, 4]`` camera-to-world matrices (world units).
        fx, fy, cx, cy: focal lengths and principal point, pixels: a float shared by all
            cameras, or a read-only float64 ``[N]`` array when the cameras differ (per-frame
            intrinsics, e.g. nerfstudio files). Arrays whose values are all equal are stored
            as a float, so code reading ``cameras.fx`` keeps working for shared intrinsics;
            :meth:`intrinsics` gives camera ``i``'s four values in every case.
        width, height: image size, pixels (shared).
        ndc: forward-facing scene: :meth:`rays` returns rays in normalised device coordinates
            (:mod:`plenoctree.datasets.ndc`) of the reference camera at the world origin with
            the focal lengths :attr:`ndc_focal` and this image size, near plane ``z = -ndc_near``.
        ndc_near: world distance of the NDC near plane (NeRF: 1).
        ndc_ref: ``(2 fx / W, 2 fy / H)`` of the NDC reference camera when it is not these
            cameras' own (rendering an NDC tree from other cameras, e.g. a camera path:
            ``tree.ndc.apply(cameras)``); None = from these cameras' focal lengths and size.
        ndc_clip: any camera draws (``to_ndc_rays(..., clip=True)``: rays that never reach
            the NDC volume miss it, a camera past the near plane starts where it stands); set
            for views of a tree (``tree.ndc.apply``). False (datasets): NeRF's rays, and a ray
            that does not point down -z is an error.

    Invalid values raise :class:`~plenoctree.errors.ConfigError`.
    """

    c2w: np.ndarray
    fx: float | np.ndarray
    fy: float | np.ndarray
    cx: float | np.ndarray
    cy: float | np.ndarray
    width: int
    height: int
    ndc: bool = False
    ndc_near: float = 1.0
    ndc_ref: tuple[float, float] | None = None
    ndc_clip: bool = False

    def __post_init__(self) -> None:
        for name, val in (("width", self.width), ("height", self.height)):
            if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val <= 0:
                raise ConfigError(f"camera {name} must be a positive integer, got {val!r}")
        check_image_size(self.width, self.height, "camera size")
        self.c2w = _check_c2w(self.c2w, batched=True).astype(np.float32)
        n = len(self)
        self.fx = _intrinsic("fx", self.fx, n, True)
        self.fy = _intrinsic("fy", self.fy, n, True)
        self.cx = _intrinsic("cx", self.cx, n, False)
        self.cy = _intrinsic("cy", self.cy, n, False)
        self.width, self.height = int(self.width), int(self.height)
        _check_plausible(self.fx, self.fy, self.cx, self.cy, self.width, self.height)
        self.ndc = bool(self.ndc)
        self.ndc_clip = bool(self.ndc_clip)
        near = self.ndc_near
        if isinstance(near, bool) or not isinstance(near, (int, float, np.floating, np.integer)) \
                or not math.isfinite(near) or near <= 0:
            raise ConfigError(f"camera ndc_near must be a finite positive number, got {near!r}")
        self.ndc_near = float(near)
        if self.ndc_ref is not None:
            ref = tuple(float(v) for v in np.asarray(self.ndc_ref, dtype=np.float64).reshape(-1))
            if len(ref) != 2 or not all(math.isfinite(v) and v > 0 for v in ref):
                raise ConfigError(f"camera ndc_ref must be two positive numbers, got "
                                  f"{self.ndc_ref!r}")
            self.ndc_ref = ref

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Cameras):
            return NotImplemented
        return (np.array_equal(self.c2w, other.c2w)
                and all(np.array_equal(a, b) for a, b in zip(self._intr(), other._intr()))
                and (self.width, self.height, self.ndc, self.ndc_near, self.ndc_ref, self.ndc_clip)
                == (other.width, other.height, other.ndc, other.ndc_near, other.ndc_ref,
                    other.ndc_clip))

    def _intr(self) -> tuple:
        return (self.fx, self.fy, self.cx, self.cy)

    @property
    def per_camera_intrinsics(self) -> bool:
        """True when at least one of fx, fy, cx, cy differs between cameras (is an array)."""
        return any(not isinstance(v, float) for v in self._intr())

    def intrinsics(self, index: int) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` of camera ``index``, pixels."""
        i = self._index(index)
        return tuple(float(_pick(v, i)) for v in self._intr())  # type: ignore[return-value]

    def intrinsics_array(self) -> np.ndarray:
        """float64 ``[N, 4]``: ``(fx, fy, cx, cy)`` of every camera."""
        n = len(self)
        return np.stack([np.broadcast_to(np.asarray(v, dtype=np.float64), (n,))
                         for v in self._intr()], -1).copy()

    @property
    def ndc_focal(self) -> tuple[float, float]:
        """``(fx, fy)`` of the NDC reference camera at this image size: from ``ndc_ref`` when
        set, else the shared focal lengths (their mean over the cameras when they differ)."""
        if self.ndc_ref is not None:
            return 0.5 * self.ndc_ref[0] * self.width, 0.5 * self.ndc_ref[1] * self.height
        return float(np.mean(self.fx)), float(np.mean(self.fy))

    def _index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            raise ConfigError(f"camera index must be an integer, got {index!r}")
        n = len(self)
        if not -n <= index < n:
            raise ConfigError(f"camera index {index} out of range for {n} cameras")
        return int(index) % n

    def rays(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Rays of camera ``index``: ``origins [H, W, 3]``, unit ``dirs [H, W, 3]`` (float32).

        See :func:`generate_rays` for the pixel convention. With ``ndc=True`` the rays are in
        NDC space (:func:`~plenoctree.datasets.ndc.to_ndc_rays`): origins on ``z' = -1``,
        unit NDC directions, so distances along them are NDC lengths.
        """
        i = self._index(index)
        fx, fy, cx, cy = self.intrinsics(i)
        o, d = generate_rays(self.c2w[i], fx, fy, cx, cy, self.width, self.height)
        if self.ndc:
            from .ndc import to_ndc_rays

            nfx, nfy = self.ndc_focal
            o, d = to_ndc_rays(o, d, nfx, nfy, self.width, self.height, self.ndc_near,
                               clip=self.ndc_clip)
        return o, d

    def device_tables(self, device: Any) -> tuple[Any, Any]:
        """``(c2w, intrinsics)`` float64 torch tensors ``[N, 3|4, 4]``, ``[N, 4]`` on
        ``device``: what :meth:`pixel_rays` reads, uploaded once by a caller that makes rays
        every step (each upload is a host round trip on a GPU)."""
        import torch

        return (torch.as_tensor(self.c2w, device=device, dtype=torch.float64),
                torch.as_tensor(self.intrinsics_array(), device=device))

    def pixel_rays(self, image: Any, col: Any, row: Any,
                   tables: tuple[Any, Any] | None = None) -> tuple[Any, Any]:
        """Rays through individual pixels, vectorised (the training ray sampler's path).

        Args:
            image: int ``[B]`` camera indices. col, row: ``[B]`` pixel column / row indices
                (the ray goes through the pixel centre ``(col + 0.5, row + 0.5)``; fractional
                values give sub-pixel rays). numpy arrays or torch tensors (all three of one
                kind; torch results are float32 on the tensors' device).
            tables: torch inputs only: :meth:`device_tables` on their device (None: made
                here, two uploads).

        Returns:
            ``(origins [B, 3], unit dirs [B, 3])``, identical to ``rays(image[b])[row[b],
            col[b]]`` (NDC rays when ``ndc``).
        """
        torch_in = type(image).__module__.startswith("torch")
        if torch_in:
            import torch

            dev = image.device
            idx = image.long()
            c2w_all, k_all = tables if tables is not None else self.device_tables(dev)
            c2w, k = c2w_all[idx], k_all[idx]
            u, v = col.to(torch.float64), row.to(torch.float64)
            d_cam = torch.stack([(u + 0.5 - k[:, 2]) / k[:, 0], -(v + 0.5 - k[:, 3]) / k[:, 1],
                                 -torch.ones_like(u)], -1)
            dirs = (c2w[:, :3, :3] @ d_cam[:, :, None])[:, :, 0]
            dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
            origins = c2w[:, :3, 3]
        else:
            idx = np.asarray(image, dtype=np.int64)
            if idx.size and (idx.min() < 0 or idx.max() >= len(self)):
                raise ConfigError(f"camera index out of range for {len(self)} cameras")
            c2w = self.c2w[idx].astype(np.float64)
            k = self.intrinsics_array()[idx]
            u = np.asarray(col, dtype=np.float64)
            v = np.asarray(row, dtype=np.float64)
            d_cam = np.stack([(u + 0.5 - k[:, 2]) / k[:, 0], -(v + 0.5 - k[:, 3]) / k[:, 1],
                              -np.ones_like(u)], -1)
            dirs = np.einsum("bij,bj->bi", c2w[:, :3, :3], d_cam)
            dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
            origins = c2w[:, :3, 3]
        if self.ndc:
            from .ndc import to_ndc_rays

            nfx, nfy = self.ndc_focal
            origins, dirs = to_ndc_rays(origins, dirs, nfx, nfy, self.width, self.height,
                                        self.ndc_near, clip=self.ndc_clip)
        if torch_in:
            return origins.float().contiguous(), dirs.float().contiguous()
        return origins.astype(np.float32), dirs.astype(np.float32)

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
        ``(u' + 0.5) f``. The NDC space (if any) is unchanged.
        """
        if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
            raise ConfigError(f"downscale factor must be a positive integer, got {factor!r}")
        if self.width % factor or self.height % factor:
            raise ConfigError(f"downscale factor {factor} does not divide the image size "
                              f"{self.width}x{self.height}")
        f = float(factor)
        return Cameras(self.c2w.copy(), self.fx / f, self.fy / f, self.cx / f, self.cy / f,
                       self.width // factor, self.height // factor, self.ndc, self.ndc_near,
                       self.ndc_ref, self.ndc_clip)

    def resized(self, width: int, height: int) -> "Cameras":
        """The same cameras rendering ``width`` x ``height`` images: focal lengths and
        principal point scale per axis with the size (the field of view is kept). The one
        intrinsics rescale (:meth:`scaled` is the integer-downscale case, exact to the bit)."""
        if width == self.width and height == self.height:
            return self
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx,
                                   cy=self.cy * sy, width=int(width), height=int(height))

    def select(self, indices: Sequence[int] | np.ndarray | slice) -> "Cameras":
        """A new :class:`Cameras` holding the cameras ``c2w[indices]`` (and their intrinsics)."""
        c2w = self.c2w[indices]
        single = c2w.ndim == 2
        if single:
            c2w = c2w[None]

        def sub(v: float | np.ndarray) -> float | np.ndarray:
            if isinstance(v, float):
                return v
            return np.atleast_1d(v[indices])

        return Cameras(c2w.copy(), *(sub(v) for v in self._intr()), self.width, self.height,
                       self.ndc, self.ndc_near, self.ndc_ref, self.ndc_clip)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres in world coordinates, float32 ``[N, 3]``."""
        return self.c2w[:, :3, 3].copy()
