"""Posed-image datasets: cameras and ray generation, the Blender loader, the procedural scene.

``from plenoctree.datasets import Cameras, generate_rays, Dataset, load_blender, load_dataset``.
The procedural scene lives in :mod:`plenoctree.datasets.procedural`.
"""

from __future__ import annotations

from .blender import load_blender
from .cameras import Cameras, generate_rays
from .dataset import Dataset, detect_format, load_dataset

__all__ = ["Cameras", "generate_rays", "Dataset", "load_blender", "load_dataset", "detect_format"]
