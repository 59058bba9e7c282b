"""Shared helpers of the tests: a tiny procedural dataset, tiny NeRF-SH configurations, a
scratch copy of a dataset folder."""

from __future__ import annotations

import shutil
from pathlib import Path

from plenoctree.nerf.config import TrainConfig, preset


def copy_dataset(src: Path, tmp_path: Path) -> Path:
    """A copy of dataset folder ``src`` at ``tmp_path / "scene"`` (to damage in a test)."""
    dst = tmp_path / "scene"
    shutil.copytree(src, dst)
    return dst


def tiny_dataset(root: Path, size: int = 24, n_train: int = 12) -> Path:
    """Write (once) a small Blender-format dataset of the procedural scene under ``root``."""
    from plenoctree.datasets.procedural import write_procedural_dataset

    if not (root / "transforms_train.json").exists():
        write_procedural_dataset(root, n_train=n_train, n_val=2, n_test=2, width=size,
                                 height=size, n_samples=192)
    return root


def tiny_cpu_config(data: Path, out: Path, steps: int = 10) -> TrainConfig:
    """The CPU preset shrunk to run a step in milliseconds on a 24x24 scene."""
    cfg = preset("cpu")
    cfg.data, cfg.out = str(data), str(out)
    m = cfg.model
    m.grid_levels, m.grid_base_res, m.grid_max_res, m.grid_log2_table = 6, 8, 96, 12
    m.net_width = 32
    cfg.occ_res, cfg.render_step = 32, 0.03
    real_every = cfg.occ_update_every
    cfg.occ_warmup_steps, cfg.occ_update_every = 16, 4
    # the preset's decay per step at this faster cadence (0.8 an update every 16 steps is
    # 0.946 every 4; 0.8 every 4 steps forgets 4x faster than a real run, and on
    # test_ndc_chain's scene the photos' opacity fell from 0.935 to 0.898)
    cfg.occ_decay = cfg.occ_decay ** (cfg.occ_update_every / real_every)
    cfg.batch_rays, cfg.max_rays, cfg.target_samples = 256, 1024, 1 << 13
    cfg.sparsity_points = 512
    cfg.max_steps, cfg.log_every = steps, 5
    cfg.val_views, cfg.val_split, cfg.val_every_s = 1, "test", 0.0
    cfg.ckpt_every_s, cfg.ckpt_every_steps = 0.0, 0
    cfg.threads = 1
    cfg.chunk = 1024
    return cfg


def tiny_paper_config(data: Path, out: Path, steps: int = 3) -> TrainConfig:
    """The paper preset (coarse + fine positional-encoding MLPs) shrunk for tests."""
    cfg = preset("paper")
    cfg.data, cfg.out = str(data), str(out)
    m = cfg.model
    m.pe_freqs, m.net_depth, m.net_width, m.skip_layer = 4, 3, 32, 2
    cfg.n_coarse, cfg.n_fine, cfg.batch_rays = 8, 8, 64
    cfg.sparsity_points = 256
    cfg.max_steps, cfg.log_every = steps, 1
    cfg.val_views, cfg.val_every_s, cfg.ckpt_every_s = 1, 0.0, 0.0
    cfg.threads = 1
    cfg.chunk = 256
    return cfg


def tiny_run(root: Path, val_log: list | None = None) -> tuple[Path, Path]:
    """``(data, run)``: a 16x16 procedural dataset under ``root / "data"`` and an untrained tiny
    NeRF-SH run of it at ``root / "run"`` (``val_log``: its recorded validation entries)."""
    import torch

    from plenoctree.datasets import procedural
    from plenoctree.nerf.checkpoint import TrainProgress, save_checkpoint
    from plenoctree.nerf.config import ModelConfig
    from plenoctree.nerf.model import NeRFModel

    data = procedural.write_procedural_dataset(root / "data", n_train=3, n_val=0, n_test=2,
                                               width=16, height=16, n_samples=64)
    cfg = preset("cpu")
    cfg.data, cfg.out, cfg.occ_res = str(data), str(root / "run"), 8
    cfg.model = ModelConfig(encoding="posenc", pe_freqs=2, net_depth=1, net_width=16)
    torch.manual_seed(0)
    model = NeRFModel(cfg.model, [[-1.5] * 3, [1.5] * 3], occ_res=cfg.occ_res)
    save_checkpoint(root / "run" / "checkpoint.pt", cfg, model,
                    TrainProgress(log={"train": [], "val": list(val_log or [])}))
    return data, root / "run"


def tiny_run_and_tree(tmp_path: Path) -> tuple[Path, Path, Path]:
    """``(data, run, tree)``: :func:`tiny_run` under ``tmp_path`` and its 16³ extracted tree
    (``tmp_path / "tree.npz"``)."""
    from plenoctree.cli import main

    data, run = tiny_run(tmp_path)
    tree = tmp_path / "tree.npz"
    assert main(["extract", str(run), "--out", str(tree), "--grid", "16",
                 "--samples", "2", "--bbox", "fixed", "--masking", "sigma",
                 "--mask-alpha-thresh", "1e-12", "--no-eval", "--no-progress"]) == 0
    return data, run, tree


def ff_tree(folder: Path, n_images: int = 4, n_samples: int = 32, grid: int = 32,
            precision: str = "fp32"):
    """A forward-facing (LLFF, NDC) procedural capture written in ``folder/ff`` and its NDC
    tree of ``grid`` cells across saved as ``folder/ff.npz``: ``(root, tree, path)``."""
    from plenoctree.datasets.forward_facing import forward_facing_tree, write_forward_facing_dataset
    from plenoctree.octree.io import save_tree

    root = write_forward_facing_dataset(folder / "ff", n_images=n_images, width=48, height=36,
                                        n_samples=n_samples)
    tree = forward_facing_tree(root, grid)
    save_tree(tree, folder / "ff.npz", precision=precision)
    return root, tree, folder / "ff.npz"
