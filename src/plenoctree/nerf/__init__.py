"""NeRF-SH (§3, §4.1): the network, its rendering, training, checkpoints and evaluation.

Public entry points::

    from plenoctree.nerf import preset, train, load_nerf
    cfg = preset("cpu"); cfg.data, cfg.out = "lego", "runs/lego"
    train(cfg)                                   # writes runs/lego/checkpoint.pt, logs, plot
    model = load_nerf("runs/lego")               # for the conversion step
    run = load_run("runs/lego")                  # the model with its TrainConfig and step
    sigma, coeffs = model.query(points)          # [N], [N, 3 * basis_dim] pre-sigmoid

Importing this package compiles nothing: the numba kernels (hash-grid encoding, occupancy
marching) are imported on first use.
"""

from __future__ import annotations

from .._lazy import lazy_package

_LAZY = {
    'CheckpointError': '.checkpoint',
    'load_nerf': '.checkpoint',
    'load_run': '.checkpoint',
    'NeRFRun': '.checkpoint',
    'read_checkpoint': '.checkpoint',
    'ModelConfig': '.config',
    'TrainConfig': '.config',
    'preset': '.config',
    'HashGridEncoding': '.encoding',
    'PositionalEncoding': '.encoding',
    'evaluate_views': '.evaluate',
    'NeRFModel': '.model',
    'RadianceField': '.model',
    'OccupancyGrid': '.occupancy',
    'render_image': '.renderer',
    'render_rays': '.renderer',
    'TrainingError': '.training',
    'TrainResult': '.trainer',
    'train': '.trainer',
}
lazy_package(__name__, _LAZY)

__all__ = [
    "ModelConfig",
    "TrainConfig",
    "preset",
    "NeRFModel",
    "RadianceField",
    "HashGridEncoding",
    "PositionalEncoding",
    "OccupancyGrid",
    "render_rays",
    "render_image",
    "evaluate_views",
    "train",
    "TrainResult",
    "TrainingError",
    "load_nerf",
    "load_run",
    "NeRFRun",
    "read_checkpoint",
    "CheckpointError",
]
