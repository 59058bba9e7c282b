"""The posed photos fine-tuning trains and validates on, and how they are scored.

:class:`ViewSet` makes a batch's rays on the CPU (numba); the device steppers
(:mod:`._device_stepper`) upload its photos and packed cameras once and make the same rays on
the device. :func:`render_views_psnr` scores a stepper's values on a view set, on the device
where the stepper lives there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["ViewSet", "render_views_psnr"]


@dataclass
class ViewSet:
    """Posed images to train or validate on: ``c2w [N, 4, 4]``, the intrinsics of the first
    camera, ``images [N, H, W, 3]``, and their names.

    ``images`` are float32 in [0, 1], or uint16 holding ``round(65535 · value)`` (what
    :meth:`from_dataset` keeps: half the memory, 0.77 GB less for lego's 2 × 100 views at 800²,
    within 7.6e-6 of the photo's values); :meth:`image` gives a view in float32.

    ``cameras`` (the dataset's :class:`~plenoctree.datasets.Cameras`; default: pinhole cameras
    from ``c2w`` and the intrinsics) and ``cam_index`` (int64 ``[N]``, view ``i`` is camera
    ``cam_index[i]``) are the source of truth for rays: each view's camera is packed once into
    ``packed_cameras`` (its own intrinsics; for an NDC set the NDC reference camera of all the
    cameras, which is why they are all kept) and one numba kernel makes a batch's rays, equal to
    ``cameras.rays(i)`` — pinhole or NDC, shared or per-camera intrinsics alike.
    """

    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    images: np.ndarray
    names: list[str]
    cameras: Any = None
    cam_index: np.ndarray | None = None
    packed_cameras: np.ndarray = field(init=False, repr=False)   # float64 [N, CAM_SIZE]

    def __post_init__(self) -> None:
        from ..datasets import Cameras
        from ..render._render_numba import pack_cameras

        if self.cameras is None:
            self.cameras = Cameras(self.c2w, float(self.fx), float(self.fy), float(self.cx),
                                   float(self.cy), int(self.width), int(self.height))
            self.cam_index = np.arange(len(self), dtype=np.int64)
        self.packed_cameras = pack_cameras(self.cameras, self.cam_index)
        if self.images.dtype not in (np.float32, np.uint16):
            raise TypeError(f"ViewSet images must be float32 or uint16, got {self.images.dtype}")

    @property
    def unit(self) -> float:
        """The value of one step of ``images`` (1 for float32, 1 / 65535 for uint16)."""
        return 1.0 / 65535.0 if self.images.dtype == np.uint16 else 1.0

    def image(self, i: int) -> np.ndarray:
        """View ``i``'s image, float32 ``[H, W, 3]`` in [0, 1]."""
        img = self.images[i]
        return img if img.dtype == np.float32 else img.astype(np.float32) * np.float32(self.unit)

    @classmethod
    def from_dataset(cls, data: Any, indices: Any = None) -> ViewSet:
        cams = data.cameras
        idx = np.arange(len(cams)) if indices is None else np.asarray(indices, dtype=np.int64)
        fx, fy, cx, cy = cams.intrinsics(int(idx[0]) if len(idx) else 0)
        images = np.empty((len(idx), cams.height, cams.width, 3), np.uint16)
        for j, i in enumerate(idx):          # one image at a time: no float-sized temporary
            np.rint(np.clip(np.asarray(data.images[i], np.float32), 0.0, 1.0) * 65535.0,
                    out=images[j], casting="unsafe")
        return cls(np.ascontiguousarray(cams.c2w[idx], dtype=np.float32), fx, fy, cx, cy,
                   cams.width, cams.height, images,
                   [data.names[i] for i in idx] if data.names else [f"view_{i}" for i in idx],
                   cams, idx)

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def n_rays(self) -> int:
        return len(self) * self.width * self.height

    def rays(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``origins, dirs, targets`` float32 ``[M, 3]`` of flat pixel indices ``index [M]``
        (``img * H * W + row * W + col``); the rays equal ``cameras.rays(img)[row, col]``."""
        from ._render_grad_numba import pixel_rays

        index = np.ascontiguousarray(index, np.int64)
        m = index.shape[0]
        o = np.empty((m, 3), np.float32)
        d = np.empty((m, 3), np.float32)
        t = np.empty((m, 3), np.float32)
        pixel_rays(self.packed_cameras, int(self.width), int(self.height), index, self.images,
                   self.unit, o, d, t)
        return o, d, t

    def n_tiles(self, k: int) -> int:
        """Number of ``k × k`` pixel tiles covering every image (partial tiles at the borders)."""
        return len(self) * (-(-self.height // k)) * (-(-self.width // k))

    def tile_pixels(self, tiles: np.ndarray, k: int) -> np.ndarray:
        """Flat pixel indices (``img * H * W + v * W + u``) of tiles ``tiles [T]``, tile by tile
        in raster order within each tile; pixels past the image border are dropped."""
        nty, ntx = -(-self.height // k), -(-self.width // k)
        tiles = np.asarray(tiles, dtype=np.int64)
        img, rem = np.divmod(tiles, nty * ntx)
        ty, tx = np.divmod(rem, ntx)
        dy, dx = np.divmod(np.arange(k * k, dtype=np.int64), k)
        v = ty[:, None] * k + dy
        u = tx[:, None] * k + dx
        flat = img[:, None] * (self.height * self.width) + v * self.width + u
        if self.height % k or self.width % k:
            return flat[(v < self.height) & (u < self.width)]
        return flat.reshape(-1)

    def view_rays(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``origins, dirs [H * W, 3]`` of view ``i`` (``cameras.rays``)."""
        o, d = self.cameras.rays(int(self.cam_index[i]))
        return o.reshape(-1, 3), d.reshape(-1, 3)


def render_views_psnr(stepper: Any, views: ViewSet, keep: bool = False) -> float:
    """Mean over views of the per-view PSNR (dB, each at most 100) of ``stepper``'s current
    values: rendered and scored on the device by a device stepper (``views_psnr``; ``keep``:
    it keeps the photos uploaded for the next call), else view by view on the host."""
    from ..evaluation import score_views

    on_device = getattr(stepper, "views_psnr", None)
    if on_device is not None:
        return on_device(views, keep=keep)

    res = score_views(lambda i: stepper.render(*views.view_rays(i)).reshape(
        views.height, views.width, 3), _Images(views), with_ssim=False)
    vals = [min(p, 100.0) for p in res.psnr]
    return float(np.mean(vals)) if vals else float("nan")


class _Images:
    """``views``' images as a sequence of float32 ``[H, W, 3]`` arrays, made one at a time."""

    def __init__(self, views: ViewSet) -> None:
        self.views = views

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.views.image(i)
