"""The :class:`Dataset` container and format auto-detection (:func:`load_dataset`)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ._files import evenly_spaced
from .cameras import Cameras

__all__ = ["Dataset", "load_dataset", "load_cameras", "common_downscale", "detect_format",
           "has_split", "evenly_spaced", "FORMATS"]


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


FORMATS = ("blender", "llff", "nsvf", "nerfstudio", "colmap")
"""Dataset formats :func:`load_dataset` reads (values of its ``format`` argument)."""

_SIGNATURES = {
    "blender": "transforms_<split>.json",
    "nerfstudio": "transforms.json",
    "llff": "poses_bounds.npy",
    "nsvf": "intrinsics.txt + pose/",
    "colmap": "sparse/0/cameras.bin|txt",
}


def _matches(root: Path) -> list[str]:
    found = []
    if any((root / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        found.append("blender")
    if (root / "transforms.json").is_file():
        found.append("nerfstudio")
    if (root / "poses_bounds.npy").is_file():
        found.append("llff")
    if (root / "intrinsics.txt").is_file() and (root / "pose").is_dir():
        found.append("nsvf")
    from .colmap_model import find_colmap_model

    if find_colmap_model(root) is not None:
        found.append("colmap")
    return found


def detect_format(root: str | os.PathLike) -> str:
    """Name of the dataset format of folder ``root`` (one of :data:`FORMATS`).

    Signatures: Blender ``transforms_<split>.json``; nerfstudio / instant-ngp
    ``transforms.json``; LLFF ``poses_bounds.npy``; NSVF ``intrinsics.txt`` and ``pose/``;
    COLMAP a model folder ``sparse/0`` (or ``sparse``, or the folder itself) with ``cameras``.
    Raises :class:`DatasetError` when none or several match (then pass ``format=``).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    found = _matches(root)
    if len(found) == 1:
        return found[0]
    expected = "; ".join(f"{k}: {v}" for k, v in _SIGNATURES.items())
    if not found:
        raise DatasetError(f"{root}: unknown dataset format (expected one of {expected})")
    raise DatasetError(f"{root}: ambiguous dataset format, the folder looks like "
                       f"{' and '.join(found)}; choose one with format= (--format)")


def load_dataset(root: str | os.PathLike, split: str = "train", format: str | None = None,
                 **kw) -> Dataset:
    """Load split ``split`` of the dataset at ``root``, detecting its format unless given.

    Args:
        root: dataset folder. split: "train", "val", "test" (LLFF / NSVF / nerfstudio also
            "all").
        format: one of :data:`FORMATS` to skip detection (:func:`detect_format`).
        **kw: options of the format's loader; all take ``downscale``, ``background``,
            ``limit``, ``spread`` and ``num_threads`` (see
            :func:`~plenoctree.datasets.blender.load_blender`,
            :func:`~plenoctree.datasets.llff.load_llff` (``llffhold``, ``ndc``, ``spherify``,
            ...), :func:`~plenoctree.datasets.nsvf.load_nsvf`,
            :func:`~plenoctree.datasets.nerfstudio.load_nerfstudio`,
            :func:`~plenoctree.datasets.colmap.load_colmap` (``scene``)).
    """
    from ..errors import ConfigError

    if format is None:
        fmt = detect_format(root)
    elif format in FORMATS:
        fmt = format
    else:
        raise ConfigError(f"unknown dataset format {format!r}; expected one of "
                          f"{', '.join(FORMATS)}")
    if fmt == "blender":
        from .blender import load_blender as loader
    elif fmt == "llff":
        from .llff import load_llff as loader
    elif fmt == "nsvf":
        from .nsvf import load_nsvf as loader
    elif fmt == "colmap":
        from .colmap import load_colmap as loader
    else:
        from .nerfstudio import load_nerfstudio as loader
    try:
        return loader(root, split, **kw)
    except TypeError as e:
        if "unexpected keyword argument" in str(e):
            raise ConfigError(f"{fmt} loader: {e}") from None
        raise


def common_downscale(width: int, height: int, target: int) -> int:
    """An integer downscale factor for ``width × height`` images near ``target``: the smallest
    one ≥ ``target`` that divides both sizes (the loaders' area downscale needs that), else the
    largest one below it (1 at worst). E.g. 504×378, target 4 → 6; 800×800, target 4 → 4."""
    g = math.gcd(int(width), int(height))
    divisors = [d for d in range(1, g + 1) if g % d == 0]
    above = [d for d in divisors if d >= target]
    return min(above) if above else max(d for d in divisors if d <= target)


def load_cameras(root: str | os.PathLike, split: str = "train", format: str | None = None
                 ) -> Dataset:
    """Split ``split`` loaded only for its cameras and names, cheaply: the images at a
    downscale near 4 that divides their size (:func:`common_downscale`; one image is read at
    full size first to learn it). The poses and the field of view (fx, fy relative to width,
    height) are those of any downscale; ``images`` are small and not meant to be used."""
    probe = load_dataset(root, split=split, format=format, limit=1)
    factor = common_downscale(probe.cameras.width, probe.cameras.height, 4)
    return load_dataset(root, split=split, format=format, downscale=factor)


def has_split(root: str | os.PathLike, split: str, format: str | None = None) -> bool:
    """Whether the dataset at ``root`` has a non-empty split ``split``, by its loader's rules:
    Blender ``transforms_<split>.json``; LLFF ``train`` and ``test`` (every ``llffhold``-th
    image; its ``val`` is the test set, so not a separate split); NSVF images named ``0_`` /
    ``1_`` / ``2_`` (test falls back to ``1_``); nerfstudio ``<split>_filenames`` or the 90 %
    rule; COLMAP the held-out views. A broken dataset still raises its ``DatasetError``."""
    root = Path(root)
    fmt = format or detect_format(root)
    if fmt == "blender":
        return (root / f"transforms_{split}.json").is_file()
    if fmt == "llff":
        return split in ("train", "test")
    if fmt == "nsvf":
        from .nsvf import NSVF_SPLIT_PREFIX

        names = [p.name for p in (root / "rgb").iterdir()] if (root / "rgb").is_dir() else []
        prefixes = [NSVF_SPLIT_PREFIX[split]] if split in NSVF_SPLIT_PREFIX else []
        if split == "test":
            prefixes.append(NSVF_SPLIT_PREFIX["val"])
        return any(n.startswith(p) for n in names for p in prefixes)
    try:
        load_dataset(root, split, format=fmt, limit=1)
    except DatasetError as e:
        if f"split {split!r} is empty" in str(e):
            return False
        raise
    return True
