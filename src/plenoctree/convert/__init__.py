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

from .bbox import BoxResult, auto_bbox, fixed_bbox
from .extract import ExtractConfig, ExtractResult, estimate_grid_memory, extract
from .field import AnalyticField, AnalyticPlainField, NeRFField, RadianceField, as_field
from .grid import GridSpec, evaluate_density_grid
from .memory import StageMonitor
from .projection import project_sh, random_directions
from .sampling import sample_cells
from .visibility import candidates, max_ray_weights, sigma_mask, visibility_weights, weight_mask

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
    "fixed_bbox",
    "GridSpec",
    "evaluate_density_grid",
    "StageMonitor",
    "project_sh",
    "random_directions",
    "sample_cells",
    "candidates",
    "max_ray_weights",
    "visibility_weights",
    "weight_mask",
    "sigma_mask",
]
