"""The main job on the embedded procedural scene: the whole chain in a few minutes.

``plenoctree demo --out DIR`` (the README's first command) writes the procedural scene as a
Blender-format dataset, then runs :func:`plenoctree.pipeline.run_pipeline` on it with settings
scaled to the scene: NeRF-SH training (CPU preset), extraction, fine-tuning, evaluation,
compression, the web-viewer bundle and an orbit video. Stages already done are skipped, so a
killed demo resumes where it stopped.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ._util import atomic_save_json, check_output_dir, run_lock
from .errors import ConfigError
from .optim.finetuning import DEFAULT_EPOCHS

__all__ = ["DemoConfig", "run_demo"]


@dataclass
class DemoConfig:
    """Settings of ``plenoctree demo``."""

    out: Path = Path("out/demo")
    """output folder (dataset, NeRF-SH run, trees, renders, video, web bundle, tables)"""
    data: str = ""
    """run on this dataset (any supported format) instead of the procedural scene; images are
    downscaled to at most 400 px wide, and the grid raised to 256 for images of 256 px or more"""
    image_size: int = 128
    """width and height of the procedural dataset's images, pixels"""
    n_train: int = 40
    """training views of the procedural dataset"""
    n_test: int = 8
    """test views rendered and scored"""
    train_minutes: float = 3.0
    """NeRF-SH training budget in minutes (0 = use train_steps)"""
    train_steps: int = 0
    """NeRF-SH training steps (0 = the time budget decides)"""
    grid: int = 128
    """octree finest resolution at extraction (power of two)"""
    finetune_epochs: int = DEFAULT_EPOCHS
    """maximum fine-tuning epochs"""
    video_frames: int = 40
    """frames of the orbit video (0 = none)"""
    backend: str = "auto"
    """renderer backend: auto, numba, triton or torch"""
    device: str = "auto"
    """device of every stage: auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N"""
    seed: int = 0
    """seed of the dataset's cameras and of training"""


def run_demo(cfg: DemoConfig, log=print) -> dict:
    """Write the procedural dataset (once) and run the pipeline on it; returns its summary.

    Holds the lock of ``cfg.out`` (:func:`plenoctree._util.run_lock`) throughout.
    """
    if cfg.image_size < 8:
        raise ConfigError(f"--image-size must be >= 8, got {cfg.image_size}")
    if cfg.grid < 2 or cfg.grid & (cfg.grid - 1):
        raise ConfigError(f"--grid must be a power of two >= 2, got {cfg.grid}")
    out = Path(cfg.out)
    check_output_dir(out)
    out.mkdir(parents=True, exist_ok=True)
    with run_lock(out, "demo"):     # run_pipeline nests the same lock
        if cfg.data:
            return _run_on_dataset(cfg, out, log)
        return _run_procedural(cfg, out, log)


def _run_procedural(cfg: DemoConfig, out: Path, log) -> dict:
    """The demo chain on the procedural scene (dataset written once)."""
    from .datasets.procedural import write_procedural_dataset
    from .pipeline import PipelineConfig, run_pipeline

    data_dir = out / "data"
    settings = {"size": cfg.image_size, "n_train": cfg.n_train, "n_test": cfg.n_test,
                "seed": cfg.seed}
    stamp = out / ".stages" / "dataset.json"
    try:
        done = json.loads(stamp.read_text()) == settings
    except (OSError, ValueError):
        done = False
    if done and (data_dir / "transforms_test.json").exists():
        log("[dataset] up to date, skipped")
    else:
        log(f"[dataset] writing the procedural scene ({cfg.image_size}² px, {cfg.n_train} train "
            f"/ {cfg.n_test} test views) to {data_dir}")
        write_procedural_dataset(data_dir, n_train=cfg.n_train, n_val=4, n_test=cfg.n_test,
                                 width=cfg.image_size, height=cfg.image_size, seed=cfg.seed)
        atomic_save_json(stamp, settings)
    pcfg = PipelineConfig(
        data=str(data_dir), out=str(out), train_minutes=cfg.train_minutes,
        train_steps=cfg.train_steps, grid=cfg.grid, finetune_epochs=cfg.finetune_epochs,
        video_frames=cfg.video_frames, backend=cfg.backend, device=cfg.device, seed=cfg.seed,
        nerf_eval_views=cfg.n_test,  # the NeRF-SH row scores the same views as the octree rows
        extra={"train": {"val_views": 2, "val_split": "val"}},
    )
    summary = run_pipeline(pcfg, log=log)
    log(f"open the viewer: plenoctree view {out / 'tree_ft.plnz'}")
    return summary


def _run_on_dataset(cfg: DemoConfig, out: Path, log) -> dict:
    """The demo chain on a user dataset, with the resolution and grid scaled to its images."""
    from .datasets import common_downscale, load_dataset
    from .pipeline import PipelineConfig, run_pipeline

    probe = load_dataset(cfg.data, "train", limit=1)
    width = probe.cameras.width
    downscale = common_downscale(width, probe.cameras.height, max(1, -(-width // 400)))
    size = width // downscale
    grid = max(cfg.grid, 256) if size >= 256 else cfg.grid
    log(f"[demo] {cfg.data}: {width} px wide -> downscale {downscale} ({size} px), grid {grid}³")
    pcfg = PipelineConfig(data=str(cfg.data), out=str(out), downscale=downscale,
                          train_minutes=cfg.train_minutes, train_steps=cfg.train_steps,
                          grid=grid, finetune_epochs=cfg.finetune_epochs,
                          video_frames=cfg.video_frames, backend=cfg.backend, device=cfg.device,
                          seed=cfg.seed)
    summary = run_pipeline(pcfg, log=log)
    log(f"open the viewer: plenoctree view {out / 'tree_ft.plnz'}")
    return summary
