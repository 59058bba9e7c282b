"""``plenoctree plot``: the stage plot of a run, or the curve of a fine-tuning log, as a PNG."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import ConfigError


@dataclass
class PlotConfig:
    """Options of ``plenoctree plot``."""

    file: str = ""
    """summary.json, paper_table.json or <tree>.log.jsonl"""
    out: str | None = None
    """PNG (default: stages.png beside the summary, <tree>.curve.png)"""
    title: str | None = None
    """plot title"""


def _run(cfg: PlotConfig, args: argparse.Namespace) -> int:
    from ..plots import plot_finetune_curve, plot_stages

    src = Path(cfg.file)
    if not src.is_file():
        raise ConfigError(f"{src}: no such file")
    if src.name.endswith(".jsonl"):
        out = Path(cfg.out) if cfg.out else src.with_name(src.name.removesuffix(".log.jsonl")
                                                            .removesuffix(".jsonl") + ".curve.png")
        ok = plot_finetune_curve(src, out, title=cfg.title)
        what = "fine-tuning curve"
    else:
        try:
            obj = json.loads(src.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as e:
            raise ConfigError(f"{src}: not a JSON file ({e})") from None
        from ..plots import stage_rows

        try:
            rows, title = stage_rows(obj)
        except ValueError as e:
            raise ConfigError(f"{src}: {e}") from None
        out = Path(cfg.out) if cfg.out else src.with_name("stages.png")
        ok = plot_stages(rows, out, title=cfg.title or title)
        what = "stage plot"
    if not ok:
        raise ConfigError(f"{src}: nothing to plot (no values), or matplotlib is missing "
                          "(pip install 'plenoctree[plot]')")
    print(f"{what} -> {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``plot`` command (one flag per :class:`PlotConfig` field)."""
    from ._options import add_command

    add_command(sub, "plot", PlotConfig, _run,
                help="plot a run's stages (PSNR vs FPS and MB) or a fine-tuning log's PSNR curve",
                description="FILE: a run's summary.json, benchmarks/paper_table.py's "
                "paper_table.json (or a JSON list of rows with stage, psnr, fps, mb) -> stage "
                "plot; a fine-tuning <tree>.log.jsonl -> train/validation PSNR per epoch. "
                "Needs matplotlib (the plot extra).",
                positional=("file",))
