"""plenoctree: PlenOctrees for real-time rendering of neural radiance fields.

The flat public API; every name in ``__all__`` is tested to resolve. Importing the package
compiles nothing (numba kernels compile on first use and are cached on disk).
"""

from __future__ import annotations

__version__ = "0.1.0"

from .errors import BackendError, ConfigError, DatasetError, PlenOctreeError, TreeFormatError
from .octree import Octree, export_svox, import_svox, load_tree, save_tree
from .sh import eval_sg_bases, eval_sh_bases, num_sh_bases, sh_degree_from_bases
from .datasets import Cameras, Dataset, generate_rays, load_blender, load_dataset
from .datasets.procedural import procedural_grid, procedural_tree, write_procedural_dataset
from .metrics import lpips, lpips_available, psnr, ssim
from .render import RenderOptions, RenderOutput, available_backends, render_image, render_rays

__all__ = [
    "__version__",
    "PlenOctreeError",
    "DatasetError",
    "TreeFormatError",
    "BackendError",
    "ConfigError",
    # sh
    "eval_sh_bases",
    "eval_sg_bases",
    "num_sh_bases",
    "sh_degree_from_bases",
    # datasets
    "Cameras",
    "Dataset",
    "generate_rays",
    "load_blender",
    "load_dataset",
    "write_procedural_dataset",
    "procedural_grid",
    "procedural_tree",
    # metrics
    "psnr",
    "ssim",
    "lpips",
    "lpips_available",
    # octree
    "Octree",
    "save_tree",
    "load_tree",
    "export_svox",
    "import_svox",
    # render
    "RenderOptions",
    "RenderOutput",
    "render_rays",
    "render_image",
    "available_backends",
]
