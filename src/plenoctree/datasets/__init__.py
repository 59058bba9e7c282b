"""Posed-image datasets: cameras and ray generation (incl. NDC), the Blender, LLFF, NSVF and
nerfstudio loaders, format detection, the procedural scene.

``from plenoctree.datasets import Cameras, generate_rays, Dataset, load_dataset, ...``.
The procedural scene lives in :mod:`plenoctree.datasets.procedural`, its forward-facing (LLFF)
variant in :mod:`plenoctree.datasets.forward_facing`.
"""

from __future__ import annotations

from .._lazy import lazy_package

_LAZY = {
    'load_blender': '.blender',
    'Cameras': '.cameras',
    'generate_rays': '.cameras',
    'FORMATS': '.dataset',
    'Dataset': '.dataset',
    'detect_format': '.dataset',
    'load_dataset': '.dataset',
    'llff_render_cameras': '.llff',
    'load_llff': '.llff',
    'to_ndc_rays': '.ndc',
    'load_nerfstudio': '.nerfstudio',
    'load_nsvf': '.nsvf',
}
lazy_package(__name__, _LAZY)

__all__ = ["Cameras", "generate_rays", "Dataset", "load_blender", "load_dataset", "detect_format",
           "FORMATS", "load_llff", "load_nsvf", "load_nerfstudio", "llff_render_cameras",
           "to_ndc_rays"]
