"""The :class:`Dataset` container and format auto-detection (:func:`load_dataset`)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from .cameras import Cameras

__all__ = ["Dataset", "load_dataset", "detect_format"]


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
            ``None`` when the loader did not keep it.
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

    def __post_init__(self) -> None:
        n, h, w = len(self.cameras), self.cameras.height, self.cameras.width
        if self.images.shape != (n, h, w, 3):
            raise DatasetError(f"{self.root}: images have shape {list(self.images.shape)}, "
                               f"cameras expect {[n, h, w, 3]}")
        if self.alphas is not None and self.alphas.shape != (n, h, w):
            raise DatasetError(f"{self.root}: alphas have shape {list(self.alphas.shape)}, "
                               f"expected {[n, h, w]}")
        if len(self.names) != n:
            raise DatasetError(f"{self.root}: {len(self.names)} names for {n} images")
        self.scene_bbox = np.asarray(self.scene_bbox, dtype=np.float32).reshape(2, 3)
        self.root = Path(self.root)

    def __len__(self) -> int:
        return len(self.cameras)


def detect_format(root: str | os.PathLike) -> str:
    """Name of the dataset format of folder ``root`` ("blender"), or :class:`DatasetError`."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    if any((root / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        return "blender"
    raise DatasetError(f"{root}: unknown dataset format (expected transforms_<split>.json "
                       "files of a Blender / NeRF-synthetic dataset)")


def load_dataset(root: str | os.PathLike, split: str = "train", **kw) -> Dataset:
    """Load split ``split`` of the dataset at ``root``, detecting its format.

    Keyword arguments go to the format's loader (for Blender: ``downscale``, ``background``,
    ``limit``; see :func:`plenoctree.datasets.blender.load_blender`).
    """
    fmt = detect_format(root)
    if fmt == "blender":
        from .blender import load_blender

        return load_blender(root, split, **kw)
    raise DatasetError(f"{root}: unsupported dataset format {fmt!r}")  # pragma: no cover
