"""``plenoctree train`` and ``plenoctree render-nerf``: NeRF-SH training and its baseline renders.

``train`` builds a :class:`~plenoctree.nerf.config.TrainConfig` from a preset plus overrides
(every config field is a flag; its help is the field's docstring) and calls
:func:`plenoctree.nerf.train`. ``render-nerf`` renders a split with a trained network and
reports PSNR / SSIM and seconds per frame.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

from ..errors import ConfigError

_TRAIN_SKIP = ("out", "preset", "model")


@dataclass
class RenderNerfConfig:
    """Options of ``plenoctree render-nerf``."""

    run_dir: str = ""
    """training run directory (or a checkpoint.pt)"""
    split: str = "test"
    """dataset split"""
    data: str | None = None
    """dataset folder (default: the one trained on)"""
    downscale: int | None = None
    """image downscale (default: the training downscale)"""
    views: int = 0
    """render this many views evenly spaced over the split (0 = all)"""
    indices: str | None = None
    """comma-separated view indices instead"""
    rows: str | None = None
    """render only rows A:B of each view; seconds per frame are extrapolated"""
    chunk: int | None = None
    """rays per chunk"""
    amp: str | None = None
    """bf16 autocast of the MLP (default: as in training — off for the paper preset, bf16
    where supported for the cpu preset)"""
    ssim: bool = True
    """score SSIM too (--no-ssim: skip it)"""
    out: str | None = None
    """output folder (default RUN_DIR/render_<split>)"""
    threads: int = 0
    """CPU threads (0 = all)"""


def register(sub) -> None:
    """Add ``train`` and ``render-nerf`` to the CLI."""
    from ..datasets.dataset import FORMATS
    from ..nerf.config import ModelConfig, TrainConfig
    from ..pipeline_config import PRESETS, train_preset
    from ._options import add_command, add_config, add_config_file
    from ._output import add_progress, add_quiet

    p = sub.add_parser("train", help="train a NeRF-SH (paper §4.1) on posed images",
                       description="Train a NeRF-SH. Presets: 'cpu' (hash grid + occupancy "
                       "grid, most quality per minute on a few cores), 'paper' (the "
                       "paper's 8x256 NeRF-SH, 64+128 samples; for GPUs) and 'quick' (cpu for "
                       "10 minutes), as `plenoctree run --preset`. A killed run continues from "
                       "its last checkpoint with --resume. Every option below is a "
                       "TrainConfig/ModelConfig field; defaults shown are the cpu preset's.")
    p.add_argument("--out", required=True, help="run directory (checkpoint, logs, curve.png)")
    p.add_argument("--preset", choices=sorted(PRESETS), default=None,
                   help="starting configuration (default: cpu, or --config's)")
    add_config_file(p)
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its checkpoint (its configuration is "
                        "kept; model options may not change)")
    p.add_argument("--print-config", action="store_true",
                   help="print the resolved configuration as JSON and exit")
    add_quiet(p)
    add_progress(p)
    shown = train_preset("cpu")
    dests = add_config(p.add_argument_group("training (TrainConfig)"), TrainConfig, shown=shown,
                       skip=_TRAIN_SKIP, fields={"format": {"choices": FORMATS}})
    dests += add_config(p.add_argument_group("network (ModelConfig)"), ModelConfig,
                        dest_prefix="model.", shown=shown.model)
    p.set_defaults(func=run_train, _dests=dests)

    add_command(sub, "render-nerf", RenderNerfConfig, run_render_nerf,
                help="render a split with a trained NeRF-SH (the baseline)",
                description="Render views with the network itself (no octree), in chunks, and "
                "report PSNR, SSIM and seconds per frame.", positional=("run_dir",),
                fields={"amp": {"choices": ("auto", "bf16", "off")}})


def build_config(args: argparse.Namespace):
    """The :class:`TrainConfig` of parsed ``train`` arguments: preset, then ``--config FILE``,
    then the flags given. Returns ``(config, given flags)``."""
    from ..nerf.config import validate
    from ..pipeline_config import time_budget, train_preset
    from ._options import apply, given, load_config_file

    file = load_config_file(args._config_file)
    cfg = train_preset(args.preset or file.get("preset", "cpu"))
    apply(cfg, {k: v for k, v in file.items() if k != "preset"},
          where=str(args._config_file or "config"))
    cfg.out = args.out
    flags = given(args, args._dests)
    apply(cfg, flags, where="train")
    flat = {**flags, **flags.get("model", {})}
    if "batch_rays" in flat and "max_rays" not in flat:
        cfg.max_rays = cfg.batch_rays
    time_budget(cfg, flags)
    return validate(cfg), flags


def _resume_config(args: argparse.Namespace, given: dict):
    """The checkpoint's configuration with the flags given on this command line applied."""
    from ..nerf.checkpoint import CHECKPOINT_NAME, read_checkpoint
    from ..nerf.config import validate
    from ..pipeline_config import time_budget
    from ._options import apply

    ck = read_checkpoint(Path(args.out) / CHECKPOINT_NAME)
    cfg = ck["config"]
    cfg.out = args.out
    apply(cfg, given, where="train")
    time_budget(cfg, given)
    return validate(cfg)


def run_train(args: argparse.Namespace) -> int:
    from ..nerf import train
    from ..nerf.config import config_json

    cfg, given = build_config(args)
    if args.resume:
        cfg = _resume_config(args, given)
    if args.print_config:
        print(config_json(cfg))
        return 0
    if not cfg.data:
        raise ConfigError("--data is required (the dataset folder)")
    progress = args.show_progress if args.show_progress is not None else (
        False if args.quiet else None)
    quiet = None if progress is None else not progress
    res = train(cfg, resume=args.resume, quiet=quiet)
    from ..nerf.distributed import rank_from_env

    if rank_from_env() == 0:        # under torchrun one line for the run, not one per rank
        val = ("no validation views" if math.isnan(res.val_psnr)
               else f"validation PSNR {res.val_psnr:.2f} dB")
        print(f"trained {res.step} steps in {res.train_time_s / 60:.1f} min of training; "
              f"{val}; run directory {res.run_dir}")
    return 0


def _parse_rows(text: str | None) -> slice | None:
    if not text:
        return None
    try:
        a, b = (int(v) for v in text.split(":"))
    except ValueError:
        raise ConfigError(f"--rows: expected A:B, got {text!r}") from None
    if not 0 <= a < b:
        raise ConfigError(f"--rows: need 0 <= A < B, got {text!r}")
    return slice(a, b)


def run_render_nerf(cfg: RenderNerfConfig, args: argparse.Namespace) -> int:
    from ..nerf.evaluate import render_nerf_views

    if cfg.indices:
        try:
            idx = [int(v) for v in cfg.indices.split(",")]
        except ValueError:
            raise ConfigError(f"--indices: expected comma-separated integers, got "
                              f"{cfg.indices!r}") from None
    else:
        idx = None
    rows = _parse_rows(cfg.rows)
    res = render_nerf_views(cfg.run_dir, split=cfg.split, views=cfg.views, indices=idx,
                            data=cfg.data, downscale=cfg.downscale, out=cfg.out,
                            with_ssim=cfg.ssim, amp=cfg.amp, chunk=cfg.chunk,
                            rows=rows, threads=cfg.threads)
    w, h, frac = res["width"], res["height"], res["rows_fraction"]
    spf = res["seconds_per_full_frame"]
    for n, p, s, t in zip(res["names"], res["psnr"], res["ssim"], res["seconds"]):
        print(f"{n}: PSNR {p:.2f} dB  SSIM {s:.4f}  {t:.2f} s")
    print(f"{len(res['names'])} views at {w}x{h}{'' if rows is None else f' (rows {cfg.rows})'}: "
          f"mean PSNR {res['mean_psnr']:.2f} dB, SSIM {res['mean_ssim']:.4f}, "
          f"{spf:.2f} s per {w}x{h} frame ({1 / spf:.3f} FPS), "
          f"{sum(res['n_samples']) / len(res['n_samples']) / max(frac, 1e-9) / (w * h):.1f} "
          f"network samples per ray")
    return 0
