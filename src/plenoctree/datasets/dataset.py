"""Format detection and loading through the registry of dataset formats (:func:`load_dataset`).

The registry is one table, :data:`REGISTRY`: each loader module's ``FORMAT`` record
(:class:`~plenoctree.datasets.base.DatasetFormat`), in detection order. ``Dataset`` lives in
:mod:`.base` and is re-exported here.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

from ..errors import ConfigError, DatasetError
from . import blender, colmap, llff, nerfstudio, nsvf
from .llff import llff_matches_colmap
from ._files import evenly_spaced
from .base import Dataset, DatasetFormat

__all__ = ["Dataset", "DatasetFormat", "REGISTRY", "FORMATS", "load_dataset", "load_cameras",
           "common_downscale", "detect_format", "has_split", "evenly_spaced", "holds_photos",
           "default_background", "PHOTO_BACKGROUND", "RENDER_BACKGROUND"]

logger = logging.getLogger(__name__)

REGISTRY: dict[str, DatasetFormat] = {
    f.name: f for f in (blender.FORMAT, nerfstudio.FORMAT, llff.FORMAT, nsvf.FORMAT,
                        colmap.FORMAT)}
"""Every dataset format by name, in detection order (:func:`detect_format`)."""

FORMATS = tuple(REGISTRY)
"""Dataset formats :func:`load_dataset` reads (values of its ``format`` argument)."""


def _format(name: str) -> DatasetFormat:
    """The registered format ``name``; ``ConfigError`` listing the known ones otherwise."""
    if not isinstance(name, str) or name not in REGISTRY:
        raise ConfigError(f"unknown dataset format {name!r}; expected one of "
                          f"{', '.join(FORMATS)}")
    return REGISTRY[name]


def detect_format(root: str | os.PathLike) -> str:
    """Name of the dataset format of folder ``root`` (one of :data:`FORMATS`).

    Signatures: Blender ``transforms_<split>.json``; nerfstudio / instant-ngp
    ``transforms.json``; LLFF ``poses_bounds.npy``; NSVF ``intrinsics.txt`` and ``pose/``;
    COLMAP a model folder ``sparse/0`` (or ``sparse``, or the folder itself) with ``cameras``.
    An LLFF folder with a COLMAP model of the same photos (mip-NeRF 360's layout) is LLFF.
    Raises :class:`DatasetError` when none or several match (then pass ``format=``).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder does not exist")
    found = [f.name for f in REGISTRY.values() if f.detect(root)]
    if len(found) == 1:
        return found[0]
    if sorted(found) == ["colmap", "llff"]:
        if llff_matches_colmap(root):       # mip-NeRF 360's layout: one capture, posed twice
            logger.info("%s: poses_bounds.npy and the COLMAP model pose the same photos; "
                        "reading it as LLFF (--format colmap reads the model)", root)
            return "llff"
        raise DatasetError(f"{root}: ambiguous dataset format: poses_bounds.npy and the COLMAP "
                           "model beside it do not pose the same photos (or one is "
                           "unreadable); choose one with format= (--format llff reads "
                           "poses_bounds.npy and images_<N>/, --format colmap the model and "
                           "images/)")
    expected = "; ".join(f"{f.name}: {f.signature}" for f in REGISTRY.values())
    if not found:
        raise DatasetError(f"{root}: unknown dataset format (expected one of {expected})")
    raise DatasetError(f"{root}: ambiguous dataset format, the folder looks like "
                       f"{' and '.join(found)}; choose one with format= (--format)")


PHOTO_BACKGROUND = (0.0, 0.0, 0.0)
"""Default background of real photos (:attr:`DatasetFormat.photos`): black, NeRF's LLFF
convention. Photos have no transparent pixels; the background only shows where a ray ends
see-through, i.e. where no training view looked (the edges of outlying views), and black costs
less there than white (flower's tree fine-tuned on white scores 26.31 dB on white, 27.79 on
black; fine-tuned on black 27.86: docs/capture.md)."""

RENDER_BACKGROUND = (1.0, 1.0, 1.0)
"""Default background of renders with alpha or a baked backdrop (Blender, NSVF): white."""


def default_background(root: str | os.PathLike, format: str | None = None
                       ) -> tuple[float, float, float]:
    """The background of dataset ``root`` when none is asked for: :data:`PHOTO_BACKGROUND`
    for real photos, :data:`RENDER_BACKGROUND` otherwise."""
    return PHOTO_BACKGROUND if holds_photos(root, format) else RENDER_BACKGROUND


def holds_photos(root: str | os.PathLike, format: str | None = None) -> bool:
    """Whether dataset folder ``root`` (of ``format``, default detected) holds real photographs
    (:attr:`DatasetFormat.photos`: LLFF, COLMAP, nerfstudio) rather than renders."""
    return _format(format if format is not None else detect_format(root)).photos


def load_dataset(root: str | os.PathLike, split: str = "train", format: str | None = None,
                 **kw) -> Dataset:
    """Load split ``split`` of the dataset at ``root``, detecting its format unless given.

    Args:
        root: dataset folder. split: "train", "val", "test" (LLFF / NSVF / nerfstudio also
            "all").
        format: one of :data:`FORMATS` to skip detection (:func:`detect_format`).
        **kw: options of the format's loader; all take ``downscale``, ``background`` (None or
            absent: :func:`default_background`),
            ``limit``, ``spread`` and ``num_threads`` (see
            :func:`~plenoctree.datasets.blender.load_blender`,
            :func:`~plenoctree.datasets.llff.load_llff` (``llffhold``, ``ndc``, ``spherify``,
            ...), :func:`~plenoctree.datasets.nsvf.load_nsvf`,
            :func:`~plenoctree.datasets.nerfstudio.load_nerfstudio`,
            :func:`~plenoctree.datasets.colmap.load_colmap` (``scene``)).
    """
    fmt = detect_format(root) if format is None else _format(format).name
    loader = REGISTRY[fmt].load
    if kw.get("background") is None:
        kw["background"] = default_background(root, fmt)
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
    full size first to learn it), or at the first of 2, 4, 8, 16 that loads when the full size
    cannot (an LLFF folder may hold only ``images_8/``, as LLFF's flower). The poses and the
    field of view (fx, fy relative to width, height) are those of any downscale; ``images``
    are small and not meant to be used."""
    try:
        probe = load_dataset(root, split=split, format=format, limit=1)
    except DatasetError as first:
        for f in (2, 4, 8, 16):
            try:
                return load_dataset(root, split=split, format=format, downscale=f)
            except (ConfigError, DatasetError):
                continue
        raise first from None
    factor = common_downscale(probe.cameras.width, probe.cameras.height, 4)
    return load_dataset(root, split=split, format=format, downscale=factor)


def has_split(root: str | os.PathLike, split: str, format: str | None = None) -> bool:
    """Whether the dataset at ``root`` has a non-empty split ``split`` of its own, by its
    loader's rules: Blender ``transforms_<split>.json``; LLFF ``train`` and ``test`` (every
    ``llffhold``-th image); NSVF images named ``0_`` / ``1_`` / ``2_`` (test falls back to
    ``1_``); nerfstudio ``<split>_filenames`` or every 8th frame; COLMAP every 8th view held
    out. A ``val`` that loads the test views (LLFF, COLMAP, nerfstudio without a list of its
    own, NSVF without ``2_``: the formats' ``own_val``) is not a split of its own: False. A broken dataset still raises
    its ``DatasetError``."""
    root = Path(root)
    fmt = _format(format) if format else REGISTRY[detect_format(root)]
    if split == "val" and fmt.own_val is not None and not fmt.own_val(root):
        return False
    if fmt.has_split is not None:
        return fmt.has_split(root, split)
    try:
        load_dataset(root, split, format=fmt.name, limit=1)
    except DatasetError as e:
        if f"split {split!r} is empty" in str(e):
            return False
        raise
    return True
