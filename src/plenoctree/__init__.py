"""plenoctree: PlenOctrees for real-time rendering of neural radiance fields.

The flat public API; every name in ``__all__`` is tested to resolve. Importing the package is
lazy (PEP 562): it imports neither torch nor numba and compiles nothing; each name loads its
module on first use (numba kernels compile on first call and are cached on disk).

The stages of the chain, photos to viewer::

    train(TrainConfig(...))            -> run directory with a NeRF-SH checkpoint
    load_nerf(run_dir)                 -> NeRFModel
    extract(ExtractConfig(...))        -> ExtractResult (.tree: an Octree)
    finetune(FinetuneConfig(...))      -> FinetuneResult
    compress(tree) / decompress(ctree) -> CompressedTree / Octree
    load_any_tree(path)                -> Octree (native, svox, .plnz)
    evaluate_tree(tree, dataset)       -> EvalResult (PSNR, SSIM, LPIPS, FPS)
    export_web(tree_path, out_dir)     -> a static WebGL viewer bundle
    run_pipeline(PipelineConfig(...))  -> every stage, with summary.md

Library functions change no process-wide setting (threads, malloc, OpenMP) unless a config
asks (``threads``); :func:`plenoctree.runtime.configure` is what the CLI calls.
"""

from __future__ import annotations

from ._lazy import lazy_package
from .errors import BackendError, ConfigError, DatasetError, PlenOctreeError, TreeFormatError

__version__ = "0.1.0"

_LAZY = {
    # sh
    "eval_sh_bases": ".sh", "eval_sg_bases": ".sh", "num_sh_bases": ".sh",
    "sh_degree_from_bases": ".sh",
    # datasets
    "Cameras": ".datasets", "Dataset": ".datasets", "generate_rays": ".datasets",
    "load_blender": ".datasets", "load_dataset": ".datasets",
    "write_procedural_dataset": ".datasets.procedural", "procedural_grid": ".datasets.procedural",
    "procedural_tree": ".datasets.procedural",
    # metrics
    "psnr": ".metrics", "ssim": ".metrics", "lpips": ".metrics", "lpips_available": ".metrics",
    # octree
    "Octree": ".octree", "save_tree": ".octree", "load_tree": ".octree",
    "export_svox": ".octree", "import_svox": ".octree",
    # render
    "RenderOptions": ".render", "RenderOutput": ".render", "render_rays": ".render",
    "render_image": ".render", "available_backends": ".render",
    # stages
    "TrainConfig": ".nerf.config", "train": ".nerf.trainer", "load_nerf": ".nerf.checkpoint",
    "ExtractConfig": ".convert.extraction", "extract": ".convert.extraction",
    "FinetuneConfig": ".optim.finetuning", "finetune": ".optim.finetuning",
    "CompressOptions": ".compression.codec", "compress": ".compression.codec",
    "decompress": ".compression.codec", "save_compressed": ".compression.fileio",
    "load_compressed": ".compression.fileio", "load_any_tree": ".compression.fileio",
    "evaluate_tree": ".evaluation", "EvalConfig": ".evaluation",
    "eval_tree_file": ".evaluation", "export_web": ".viewer.export",
    "PipelineConfig": ".pipeline", "run_pipeline": ".pipeline",
}

lazy_package(__name__, _LAZY)

__all__ = ["__version__", "PlenOctreeError", "DatasetError", "TreeFormatError", "BackendError",
           "ConfigError", *_LAZY]
