"""NeRF-SH → PlenOctree conversion (paper §4.2).

::

    from plenoctree.convert import ExtractConfig, extract
    res = extract(ExtractConfig(run_dir="runs/lego", grid=256, samples=8))
    res.tree, res.out, res.stages, res.psnr

Building blocks, one module each: the radiance-field protocol and adapters (``field``), the
auto box (``bbox``), σ grid evaluation (``grid``), the max-ray-weight visibility filter
(``visibility``, numba kernel in ``_visibility_numba`` with a torch twin), per-voxel sampling
(``sampling``), SH projection of plain NeRFs (``projection``), memory accounting (``memory``)
and the pipeline (``extract``). Importing this package compiles nothing.
"""

from __future__ import annotations

from .._lazy import lazy_package

_LAZY = {
    'BoxResult': '.bbox',
    'auto_bbox': '.bbox',
    'AutoBoxOptions': '.bbox',
    'fixed_bbox': '.bbox',
    'ExtractConfig': '.extraction',
    'ExtractResult': '.extraction',
    'estimate_grid_memory': '.extraction',
    'extract': '.extraction',
    'AnalyticField': '.field',
    'AnalyticPlainField': '.field',
    'NeRFField': '.field',
    'RadianceField': '.field',
    'as_field': '.field',
    'GridSpec': '.grid',
    'evaluate_density_grid': '.grid',
    'StageMonitor': '.memory',
    'project_sh': '.projection',
    'random_directions': '.projection',
    'sample_cells': '.sampling',
    'SampleOptions': '.sampling',
    'candidates': '.visibility',
    'max_ray_weights': '.visibility',
    'sigma_mask': '.visibility',
    'visibility_weights': '.visibility',
    'weight_mask': '.visibility',
}
lazy_package(__name__, _LAZY)

__all__ = [
    "ExtractConfig",
    "ExtractResult",
    "extract",
    "estimate_grid_memory",
    "RadianceField",
    "AnalyticField",
    "AnalyticPlainField",
    "NeRFField",
    "as_field",
    "BoxResult",
    "auto_bbox",
    "AutoBoxOptions",
    "fixed_bbox",
    "GridSpec",
    "evaluate_density_grid",
    "StageMonitor",
    "project_sh",
    "random_directions",
    "sample_cells",
    "SampleOptions",
    "candidates",
    "max_ray_weights",
    "visibility_weights",
    "weight_mask",
    "sigma_mask",
]
