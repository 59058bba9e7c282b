"""Posed-image datasets: cameras and ray generation (incl. NDC), the Blender, LLFF, NSVF,
nerfstudio and COLMAP loaders, format detection through one registry of formats
(:data:`~plenoctree.datasets.dataset.REGISTRY`), camera trajectories
(:mod:`plenoctree.datasets.trajectories`), the procedural scene.

``from plenoctree.datasets import Cameras, generate_rays, Dataset, load_dataset, ...``.
The procedural scene lives in :mod:`plenoctree.datasets.procedural`, its forward-facing (LLFF)
variant in :mod:`plenoctree.datasets.forward_facing`.
"""

from __future__ import annotations

from ._files import check_frame_count, take_views
from .blender import load_blender
from .cameras import MAX_IMAGE_PIXELS, Cameras, check_image_size, generate_rays
from .colmap import ColmapOptions, load_colmap
from .dataset import (FORMATS, Dataset, common_downscale, detect_format, evenly_spaced,
                      load_cameras, load_dataset)
from .llff import LLFFOptions, llff_render_cameras, load_llff
from .ndc import to_ndc_rays
from .nerfstudio import load_nerfstudio
from .nsvf import load_nsvf

__all__ = ["Cameras", "generate_rays", "Dataset", "load_blender", "load_dataset", "load_cameras",
           "common_downscale", "detect_format",
           "evenly_spaced", "FORMATS", "load_colmap", "load_llff", "load_nsvf", "load_nerfstudio",
           "llff_render_cameras", "LLFFOptions", "ColmapOptions", "take_views",
           "to_ndc_rays", "check_image_size", "check_frame_count", "MAX_IMAGE_PIXELS"]
