"""``plenoctree train`` and ``plenoctree render-nerf``: NeRF-SH training and its baseline renders.

``train`` builds a :class:`~plenoctree.nerf.config.TrainConfig` from a preset plus overrides
(every config field is a flag; its help is the field's docstring) and calls
:func:`plenoctree.nerf.train`. ``render-nerf`` renders a split with a trained network and
reports PSNR / SSIM and seconds per frame.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

from ..errors import ConfigError

# Flags with their own, shorter names (flag -> config field).
_ALIASES = {"steps": "max_steps", "batch_size": "batch_rays"}
_SKIP = {"data", "out", "preset", "model", "background"}


def _field_types():
    from ..nerf.config import ModelConfig, TrainConfig, field_docs

    out = []
    for cls in (TrainConfig, ModelConfig):
        docs = field_docs(cls)
        for f in dataclasses.fields(cls):
            if f.name in _SKIP:
                continue
            out.append((cls.__name__, f.name, f.type, docs.get(f.name, "")))
    return out


def _bool(text: str) -> bool:
    t = text.lower()
    if t in ("1", "true", "yes", "on"):
        return True
    if t in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true/false, got {text!r}")


_TYPES = {"int": int, "float": float, "str": str, "bool": _bool}


def _add_config_flags(p: argparse.ArgumentParser) -> None:
    inverse = {v: k for k, v in _ALIASES.items()}
    g = p.add_argument_group("configuration overrides (default: the preset's value)")
    for owner, name, typ, doc in _field_types():
        flag = "--" + inverse.get(name, name).replace("_", "-")
        extra = " [alias of " + name + "]" if name in inverse else ""
        if name == "batch_rays":
            doc += " With the occupancy sampler it also caps the adaptive rays per step."
        g.add_argument(flag, dest=f"cfg_{name}", type=_TYPES[str(typ)], default=None,
                       metavar=str(typ).upper(), help=doc.replace("%", "%%") + extra)


def register(sub) -> None:
    """Add ``train`` and ``render-nerf`` to the CLI."""
    p = sub.add_parser("train", help="train a NeRF-SH (paper §4.1) on posed images",
                       description="Train a NeRF-SH. Presets: 'cpu' (hash grid + occupancy "
                       "grid, most quality per minute on a few cores) and 'paper' (the "
                       "paper's 8x256 NeRF-SH, 64+128 samples; for GPUs). A killed run "
                       "continues from its last checkpoint with --resume.")
    p.add_argument("--data", help="dataset folder (Blender / NeRF-synthetic layout)")
    p.add_argument("--out", required=True, help="run directory (checkpoint, logs, curve.png)")
    p.add_argument("--preset", choices=["cpu", "paper"], default="cpu",
                   help="starting configuration (default: cpu)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its checkpoint (its configuration is "
                        "kept; model options may not change)")
    p.add_argument("--background", default=None, help="white, black or R,G,B (default white)")
    p.add_argument("--print-config", action="store_true",
                   help="print the resolved configuration as JSON and exit")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_config_flags(p)
    p.set_defaults(func=run_train)

    r = sub.add_parser("render-nerf", help="render a split with a trained NeRF-SH (the baseline)",
                       description="Render views with the network itself (no octree), in "
                       "chunks, and report PSNR, SSIM and seconds per frame.")
    r.add_argument("run_dir", help="training run directory (or a checkpoint.pt)")
    r.add_argument("--split", default="test", help="dataset split (default test)")
    r.add_argument("--data", default=None, help="dataset folder (default: the one trained on)")
    r.add_argument("--downscale", type=int, default=None,
                   help="image downscale (default: the training downscale)")
    r.add_argument("--views", type=int, default=0,
                   help="render this many views evenly spaced over the split (0 = all)")
    r.add_argument("--indices", default=None, help="comma-separated view indices instead")
    r.add_argument("--rows", default=None,
                   help="render only rows A:B of each view; seconds per frame are extrapolated")
    r.add_argument("--chunk", type=int, default=None, help="rays per chunk")
    r.add_argument("--amp", choices=["auto", "bf16", "off"], default=None,
                   help="bf16 autocast of the MLP (default: as in training — off for the "
                        "paper preset, bf16 where supported for the cpu preset)")
    r.add_argument("--no-ssim", action="store_true", help="skip SSIM")
    r.add_argument("--out", default=None, help="output folder (default RUN_DIR/render_<split>)")
    r.add_argument("--threads", type=int, default=0, help="CPU threads (0 = all)")
    r.set_defaults(func=run_render_nerf)


def reexec_with_runtime_env(command: str) -> None:
    """Re-run this command line with :data:`plenoctree.nerf.trainer.RUNTIME_ENV` set.

    The OpenMP and malloc settings only take effect when set before torch loads, so a
    ``plenoctree`` command started without them replaces itself (``execve``)
    with the same command line and those variables added (values already in the environment
    win). Skipped when ``PLENOCTREE_NO_REEXEC`` is set, when everything is already set, off
    POSIX, or when the command was not started from the command line (e.g. ``main([...])``).
    """
    from ..nerf.trainer import RUNTIME_ENV

    if os.name != "posix" or os.environ.get("PLENOCTREE_NO_REEXEC"):
        return
    if all(k in os.environ for k in RUNTIME_ENV):
        return
    if sys.argv[1:2] != [command] or Path(sys.argv[0]).name not in ("plenoctree", "__main__.py"):
        return
    env = {**RUNTIME_ENV, **os.environ, "PLENOCTREE_NO_REEXEC": "1"}
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        os.execve(sys.executable, [sys.executable, "-m", "plenoctree.cli", *sys.argv[1:]], env)
    except OSError:  # pragma: no cover - keep going without the tuned runtime
        return


def build_config(args: argparse.Namespace):
    """The :class:`TrainConfig` of parsed ``train`` arguments (preset + overrides)."""
    from ..nerf.config import preset, validate
    from .render import parse_background

    cfg = preset(args.preset)
    cfg.data = args.data or ""
    cfg.out = args.out
    if args.background:
        cfg.background = parse_background(args.background)
    model_fields = {f.name for f in dataclasses.fields(cfg.model)}
    given = {k[4:]: v for k, v in vars(args).items() if k.startswith("cfg_") and v is not None}
    for name, val in given.items():
        setattr(cfg.model if name in model_fields else cfg, name, val)
    if "batch_rays" in given and "max_rays" not in given:
        cfg.max_rays = cfg.batch_rays
    if "minutes" in given and "max_steps" not in given:
        cfg.max_steps = 10**9
    return validate(cfg), given


def _resume_config(args: argparse.Namespace, given: dict):
    """The checkpoint's configuration with the flags given on this command line applied."""
    from ..nerf.checkpoint import CHECKPOINT_NAME, read_checkpoint
    from ..nerf.config import validate

    ck = read_checkpoint(Path(args.out) / CHECKPOINT_NAME)
    cfg = ck["config"]
    cfg.out = args.out
    if args.data:
        cfg.data = args.data
    model_fields = {f.name for f in dataclasses.fields(cfg.model)}
    for name, val in given.items():
        setattr(cfg.model if name in model_fields else cfg, name, val)
    if "minutes" in given and "max_steps" not in given:
        cfg.max_steps = 10**9
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
    res = train(cfg, resume=args.resume, quiet=True if args.quiet else None)
    print(f"trained {res.step} steps in {res.train_time_s / 60:.1f} min of training; "
          f"validation PSNR {res.val_psnr:.2f} dB; run directory {res.run_dir}")
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


def run_render_nerf(args: argparse.Namespace) -> int:
    from ..nerf.evaluate import render_nerf_views

    if args.indices:
        try:
            idx = [int(v) for v in args.indices.split(",")]
        except ValueError:
            raise ConfigError(f"--indices: expected comma-separated integers, got "
                              f"{args.indices!r}") from None
    else:
        idx = None
    rows = _parse_rows(args.rows)
    res = render_nerf_views(args.run_dir, split=args.split, views=args.views, indices=idx,
                            data=args.data, downscale=args.downscale, out=args.out,
                            with_ssim=not args.no_ssim, amp=args.amp, chunk=args.chunk,
                            rows=rows, threads=args.threads)
    w, h, frac = res["width"], res["height"], res["rows_fraction"]
    spf = res["seconds_per_full_frame"]
    for n, p, s, t in zip(res["names"], res["psnr"], res["ssim"], res["seconds"]):
        print(f"{n}: PSNR {p:.2f} dB  SSIM {s:.4f}  {t:.2f} s")
    print(f"{len(res['names'])} views at {w}x{h}{'' if rows is None else f' (rows {args.rows})'}: "
          f"mean PSNR {res['mean_psnr']:.2f} dB, SSIM {res['mean_ssim']:.4f}, "
          f"{spf:.2f} s per {w}x{h} frame ({1 / spf:.3f} FPS), "
          f"{sum(res['n_samples']) / len(res['n_samples']) / max(frac, 1e-9) / (w * h):.1f} "
          f"network samples per ray")
    return 0
