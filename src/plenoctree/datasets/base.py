"""The :class:`Dataset` container and :class:`DatasetFormat`, the record of one dataset format.

Each loader module (``blender``, ``nerfstudio``, ``llff``, ``nsvf``, ``colmap``) describes its
format in a module-level ``FORMAT = DatasetFormat(...)``: how to recognise its folder, how to
load a split, which splits exist. :mod:`plenoctree.datasets.dataset` lists them in one table,
the registry, and :func:`~plenoctree.datasets.dataset.load_dataset`, ``detect_format`` and
``has_split`` dispatch through it; a new format is one module and one line there. This module
imports no loader (the loaders import it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import DatasetError
from .cameras import Cameras

__all__ = ["Dataset", "DatasetFormat"]


@dataclass
class Dataset:
    """Posed images of one split of a scene.

    Attributes:
        images: float32 ``[N, H, W, 3]`` in [0, 1], alpha already composited on ``background``.
        cameras: the ``N`` cameras (``cameras.width == W``, ``cameras.height == H``).
        near, far: ray-sampling bounds along unit directions, world units.
        scene_bbox: float32 ``[2, 3]`` min / max world corner of the box holding the content.
        split: "train", "val" or "test".
        root: dataset folder.
        background: RGB in [0, 1] that transparent pixels were composited onto.
        names: file stems of the ``N`` images (e.g. ``"r_0"``).
        alphas: float32 ``[N, H, W]`` opacity in [0, 1] (1 where the source had no alpha), or
            ``None`` when the loader did not keep it (or every image was opaque).
        masks: float32 ``[N, H, W]`` pixel validity in [0, 1] (the fraction of valid source
            pixels after downscaling; 0 = exclude from training losses), or ``None`` when the
            dataset has no masks (nerfstudio ``mask_path``).
        unbounded: the capture is of a place (a 360° walk-around with the world around the
            ``scene_bbox``): training adds a far field beyond the box (``nerf.far``).
    """

    images: np.ndarray
    cameras: Cameras
    near: float
    far: float
    scene_bbox: np.ndarray
    split: str
    root: Path
    background: tuple[float, float, float]
    names: list[str] = field(default_factory=list)
    alphas: np.ndarray | None = None
    masks: np.ndarray | None = None
    unbounded: bool = False

    def __post_init__(self) -> None:
        n, h, w = len(self.cameras), self.cameras.height, self.cameras.width
        if self.images.shape != (n, h, w, 3):
            raise DatasetError(f"{self.root}: images have shape {list(self.images.shape)}, "
                               f"cameras expect {[n, h, w, 3]}")
        if self.alphas is not None and self.alphas.shape != (n, h, w):
            raise DatasetError(f"{self.root}: alphas have shape {list(self.alphas.shape)}, "
                               f"expected {[n, h, w]}")
        if self.masks is not None and self.masks.shape != (n, h, w):
            raise DatasetError(f"{self.root}: masks have shape {list(self.masks.shape)}, "
                               f"expected {[n, h, w]}")
        if len(self.names) != n:
            raise DatasetError(f"{self.root}: {len(self.names)} names for {n} images")
        self.scene_bbox = np.asarray(self.scene_bbox, dtype=np.float32).reshape(2, 3)
        self.root = Path(self.root)

    def __len__(self) -> int:
        return len(self.cameras)


@dataclass(frozen=True)
class DatasetFormat:
    """One dataset format of the registry.

    Attributes:
        name: the ``format=`` / ``--format`` value (``"blender"``, ...).
        signature: what :attr:`detect` looks for, for error messages (``"poses_bounds.npy"``).
        detect: ``detect(root) -> bool``: whether folder ``root`` looks like this format.
        load: the loader, ``load(root, split, **options) -> Dataset``.
        has_split: ``has_split(root, split) -> bool`` from the files alone, or ``None`` when
            only loading one view of the split tells (the split then exists unless the loader
            says it is empty).
        photos: the format holds photographs of the real world (nothing in them is see-through
            to a backdrop), not renders with a backdrop baked in.
        own_val: ``own_val(root) -> bool``: whether the ``val`` split is not the test split
            (several formats hold every 8th image out as both), or ``None``: it never is.
    """

    name: str
    signature: str
    detect: Callable[[Path], bool]
    load: Callable[..., Dataset]
    has_split: Callable[[Path, str], bool] | None = None
    photos: bool = False
    own_val: Callable[[Path], bool] | None = None

