"""The main job on the embedded procedural scene: the whole chain in a few minutes.

``plenoctree demo --out DIR`` (the README's first command) writes the procedural scene as a
Blender-format dataset, then runs :func:`plenoctree.pipeline.run_pipeline` on it with settings
scaled to the scene: NeRF-SH training (CPU preset), extraction, fine-tuning, evaluation,
compression, the web-viewer bundle and an orbit video. Stages already done are skipped, so a
killed demo resumes where it stopped. :class:`DemoConfig` is ``run``'s
:class:`~plenoctree.pipeline.PipelineConfig` with the demo's defaults and the scene's size.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from ._util import atomic_save_json, check_output_dir, run_lock
from .convert.extraction import ExtractConfig
from .errors import ConfigError
from .nerf.config import TrainConfig
from .pipeline_config import UNLIMITED_STEPS, PipelineConfig, train_preset

__all__ = ["DemoConfig", "run_demo"]

logger = logging.getLogger(__name__)

#: The demo's NeRF-SH budget: the procedural scene reaches ~35 dB in it (``run --preset
#: quick``, 10 minutes, is for real captures).
DEMO_MINUTES = 3.0


@dataclass
class DemoConfig(PipelineConfig):
    """Settings of ``plenoctree demo``: ``run``'s, with the demo's defaults."""

    out: str = "out/demo"
    """output folder (dataset, NeRF-SH run, trees, renders, video, web bundle, tables)"""
    data: str = ""
    """run on this dataset (any supported format) instead of the procedural scene; images are
    downscaled to at most 400 px wide, and the grid raised to 256 for images of 256 px or more"""
    image_size: int = 128
    """width and height of the procedural dataset's images, pixels"""
    n_train: int = 40
    """training views of the procedural dataset"""
    n_test: int = 8
    """test views of the procedural dataset, every one scored (the NeRF-SH's too)"""
    video_frames: int = 40
    """frames of the orbit video (0 = no video)"""
    train: TrainConfig = field(default_factory=lambda: dataclasses.replace(
        train_preset("cpu"), minutes=DEMO_MINUTES, max_steps=UNLIMITED_STEPS))
    """NeRF-SH training (`plenoctree train`; on the procedural scene it validates on 2 views of
    its val split)"""
    extract: ExtractConfig = field(default_factory=lambda: ExtractConfig(grid=128, eval=False))
    """octree extraction (`plenoctree extract`)"""


DEMO_ONLY = ("image_size", "n_train", "n_test")
"""The :class:`DemoConfig` fields that are not :class:`PipelineConfig` fields."""


def run_demo(cfg: DemoConfig) -> dict:
    """Write the procedural dataset (once) and run the pipeline on it; returns its summary.

    Holds the lock of ``cfg.out`` (:func:`plenoctree._util.run_lock`) throughout.
    """
    if cfg.image_size < 8:
        raise ConfigError(f"--image-size must be >= 8, got {cfg.image_size}")
    out = Path(cfg.out)
    check_output_dir(out)
    out.mkdir(parents=True, exist_ok=True)
    run = PipelineConfig(**{f.name: getattr(cfg, f.name)
                            for f in dataclasses.fields(cfg) if f.name not in DEMO_ONLY})
    with run_lock(out, "demo"):     # run_pipeline nests the same lock
        if cfg.data:
            _scale_to_dataset(run)
        else:
            _procedural_scene(cfg, run, out)
        from .pipeline import run_pipeline

        summary = run_pipeline(run)
    logger.info(f"open the viewer: plenoctree view {out / 'tree_ft.plnz'}")
    return summary


def _procedural_scene(cfg: DemoConfig, run: PipelineConfig, out: Path) -> None:
    """Write the procedural scene to ``OUT/data`` (once) and point ``run`` at it: every test
    view scored by every row, training validated on 2 views of the val split."""
    from .datasets.procedural import write_procedural_dataset

    data_dir = out / "data"
    settings = {"size": cfg.image_size, "n_train": cfg.n_train, "n_test": cfg.n_test,
                "seed": cfg.seed}
    stamp = out / ".stages" / "dataset.json"
    try:
        done = json.loads(stamp.read_text()) == settings
    except (OSError, ValueError):
        done = False
    if done and (data_dir / "transforms_test.json").exists():
        logger.info("[dataset] up to date, skipped")
    else:
        logger.info(f"[dataset] writing the procedural scene ({cfg.image_size}² px, {cfg.n_train} "
                    f"train / {cfg.n_test} test views) to {data_dir}")
        write_procedural_dataset(data_dir, n_train=cfg.n_train, n_val=4, n_test=cfg.n_test,
                                 width=cfg.image_size, height=cfg.image_size, seed=cfg.seed)
        atomic_save_json(stamp, settings)
    run.data, run.nerf_eval_views = str(data_dir), cfg.n_test
    run.train.val_views, run.train.val_split = 2, "val"


def _scale_to_dataset(run: PipelineConfig) -> None:
    """The resolution and grid of ``run`` scaled to the images of its dataset."""
    from .datasets import common_downscale, load_dataset

    probe = load_dataset(run.data, "train", limit=1)
    width = probe.cameras.width
    run.downscale = common_downscale(width, probe.cameras.height, max(1, -(-width // 400)))
    size = width // run.downscale
    if size >= 256:
        run.extract.grid = max(run.extract.grid, 256)
    logger.info(f"[demo] {run.data}: {width} px wide -> downscale {run.downscale} ({size} px), "
                f"grid {run.extract.grid}³")
