"""The main job on the embedded procedural scene: dataset → octree → renders + metrics table.

``plenoctree demo --out DIR`` calls :func:`run_demo`. Every artefact is written atomically, and
a stage whose artefact already exists with the same settings is skipped, so a killed demo
resumes where it stopped.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from ._util import atomic_save_json, atomic_write
from .errors import ConfigError

__all__ = ["DemoConfig", "run_demo"]


@dataclass
class DemoConfig:
    """Settings of ``plenoctree demo``."""

    out: Path = Path("out/demo")
    """output folder (dataset, tree, renders, tables)"""
    image_size: int = 128
    """width and height of the procedural dataset's images, pixels"""
    grid: int = 256
    """resolution of the octree's finest level (power of two)"""
    n_train: int = 30
    """training views of the procedural dataset"""
    n_test: int = 8
    """test views rendered and scored"""
    backend: str = "auto"
    """renderer backend: auto, numba or torch"""
    seed: int = 0
    """seed of the procedural dataset's cameras"""


def _stage_done(stamp: Path, settings: dict) -> bool:
    try:
        return json.loads(stamp.read_text()) == settings
    except (OSError, ValueError):
        return False


def run_demo(cfg: DemoConfig, log=print) -> dict:
    """Run the demo chain; returns the summary dict also written to ``summary.json``.

    Stages: (1) write the procedural Blender-format dataset, (2) build its octree from the
    analytic fields at ``cfg.grid``³ and save it (fp16), (3) render the test views with the
    fast backend, writing colour/depth PNGs, ``metrics.json`` and a markdown table.
    """
    from .datasets import load_dataset
    from .datasets.procedural import procedural_tree, write_procedural_dataset
    from .evaluation import evaluate_tree, metrics_markdown
    from .octree import load_tree, save_tree

    if cfg.grid < 2 or cfg.grid & (cfg.grid - 1):
        raise ConfigError(f"--grid must be a power of two >= 2, got {cfg.grid}")
    if cfg.image_size < 8:
        raise ConfigError(f"--image-size must be >= 8, got {cfg.image_size}")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}

    data_dir = out / "data"
    settings = {"size": cfg.image_size, "n_train": cfg.n_train, "n_test": cfg.n_test,
                "seed": cfg.seed}
    t0 = time.perf_counter()
    if not ((data_dir / "transforms_test.json").exists()
            and _stage_done(out / ".stage_data.json", settings)):
        log(f"[1/3] writing the procedural dataset ({cfg.image_size}² px) to {data_dir}")
        write_procedural_dataset(data_dir, n_train=cfg.n_train, n_val=2, n_test=cfg.n_test,
                                 width=cfg.image_size, height=cfg.image_size, seed=cfg.seed)
        atomic_save_json(out / ".stage_data.json", settings)
    else:
        log("[1/3] dataset up to date, skipped")
    times["dataset_s"] = time.perf_counter() - t0

    tree_path = out / "tree.npz"
    settings = {"grid": cfg.grid}
    t0 = time.perf_counter()
    if not (tree_path.exists() and _stage_done(out / ".stage_tree.json", settings)):
        log(f"[2/3] building the octree at {cfg.grid}³ from the analytic fields")
        tree = procedural_tree(cfg.grid)
        save_tree(tree, tree_path, precision="fp16")
        atomic_save_json(out / ".stage_tree.json", settings)
    else:
        log("[2/3] tree up to date, skipped")
    tree = load_tree(tree_path)
    times["tree_s"] = time.perf_counter() - t0

    log(f"[3/3] rendering {cfg.n_test} test views ({cfg.backend} backend)")
    t0 = time.perf_counter()
    test = load_dataset(data_dir, split="test")
    res = evaluate_tree(tree, test, out / "renders", backend=cfg.backend)
    times["render_s"] = time.perf_counter() - t0

    summary = {
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()},
        "tree": {"leaves": int(tree.n_leaves), "nodes": int(tree.n_nodes),
                 "file_mb": tree_path.stat().st_size / 2**20},
        "test": res.to_json()["mean"],
        "times": times,
    }
    atomic_save_json(out / "summary.json", summary)
    table = summary_markdown(summary)
    with atomic_write(out / "summary.md", "w") as f:
        f.write(table + "\n" + metrics_markdown(res))
    log("")
    log(table)
    log(f"renders, depth maps and metrics: {out / 'renders'}")
    return summary


def summary_markdown(summary: dict) -> str:
    """One markdown table: PSNR/SSIM, FPS, size and time per stage."""
    t, tr, tm = summary["test"], summary["tree"], summary["times"]
    rows = [
        "| stage | PSNR (dB) | SSIM | FPS | MB | time (s) |",
        "|---|---|---|---|---|---|",
        f"| dataset | | | | | {tm['dataset_s']:.1f} |",
        f"| octree ({tr['leaves']:,} leaves) | {t['psnr']:.2f} | {t['ssim']:.4f} | "
        f"{t['fps']:.1f} | {tr['file_mb']:.1f} | {tm['tree_s'] + tm['render_s']:.1f} |",
    ]
    return "\n".join(rows)
