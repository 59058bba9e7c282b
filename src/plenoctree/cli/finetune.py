"""``plenoctree finetune``: optimise a tree's leaf values on the training photos (paper §4.3)."""

from __future__ import annotations

import argparse
import dataclasses
import json


def _run(args: argparse.Namespace) -> int:
    from ..optim.finetune import FinetuneConfig, finetune
    from .render import parse_background

    cfg = FinetuneConfig(
        tree=args.tree, data=args.data, out=args.out, epochs=args.epochs, lr=args.lr,
        optimizer=args.optimizer, lr_sigma=args.lr_sigma, lr_decay=args.lr_decay,
        backoffs=args.backoffs, batch_rays=args.batch_rays, ray_tile=args.ray_tile,
        downscale=args.downscale,
        val_every=args.val_every, val_fraction=args.val_fraction, val_views=args.val_views,
        test_views=args.test_views, continue_on_decrease=args.continue_on_decrease,
        precision=args.precision, stop_thresh=args.stop_thresh,
        background=parse_background(args.background) if args.background else None,
        backend=args.backend, seed=args.seed, checkpoint=args.checkpoint, resume=args.resume,
        log=args.log, show_progress=None if args.progress is None else args.progress == "on",
        verbose=not args.quiet)
    res = finetune(cfg)
    fmt = lambda v: "n/a" if v is None else f"{v:.3f} dB"  # noqa: E731
    print(f"test PSNR before {fmt(res.test_psnr_before)}  after {fmt(res.test_psnr_after)}")
    print(f"{res.epochs_run} epochs ({res.steps} steps), best epoch {res.best_epoch}, "
          f"{res.wall_seconds:.1f} s, {res.train_rays_per_second / 1e6:.2f} M rays/s "
          f"({res.backend}); {res.stop_reason}")
    print(f"saved {res.out}")
    if args.json:
        print(json.dumps(res.to_json(), indent=2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``finetune`` command."""
    from ..optim.finetune import FinetuneConfig, config_help

    defaults = {f.name: f.default for f in dataclasses.fields(FinetuneConfig)}

    def h(name: str) -> str:
        v = defaults[name]
        shown = "" if v in (None, False) else f" (default {v})"
        return config_help(name) + shown

    def d(name: str):
        return defaults[name]

    p = sub.add_parser("finetune", help="fine-tune a tree's leaf values on the training images",
                       description="Optimise σ and the SH coefficients of every leaf on the "
                                   "training photos (tree structure fixed). Prints the test "
                                   "PSNR before and after.")
    p.add_argument("tree", help=h("tree"))
    p.add_argument("--data", required=True, help=h("data"))
    p.add_argument("--out", required=True, help=h("out"))
    p.add_argument("--epochs", type=int, default=d("epochs"), help=h("epochs"))
    p.add_argument("--lr", type=float, default=None, help=h("lr"))
    p.add_argument("--optimizer", choices=("sgd", "adam", "rmsprop"), default=d("optimizer"),
                   help=h("optimizer"))
    p.add_argument("--lr-sigma", type=float, default=None, help=h("lr_sigma"))
    p.add_argument("--lr-decay", type=float, default=d("lr_decay"), help=h("lr_decay"))
    p.add_argument("--backoffs", type=int, default=d("backoffs"), help=h("backoffs"))
    p.add_argument("--batch-rays", type=int, default=d("batch_rays"), help=h("batch_rays"))
    p.add_argument("--ray-tile", type=int, default=d("ray_tile"), help=h("ray_tile"))
    p.add_argument("--downscale", type=int, default=d("downscale"), help=h("downscale"))
    p.add_argument("--val-every", type=int, default=d("val_every"), help=h("val_every"))
    p.add_argument("--val-fraction", type=float, default=d("val_fraction"),
                   help=h("val_fraction"))
    p.add_argument("--val-views", type=int, default=d("val_views"), help=h("val_views"))
    p.add_argument("--test-views", type=int, default=d("test_views"), help=h("test_views"))
    p.add_argument("--continue-on-decrease", action="store_true", help=h("continue_on_decrease"))
    p.add_argument("--precision", choices=("auto", "fp16", "fp32"), default=d("precision"),
                   help=h("precision"))
    p.add_argument("--stop-thresh", type=float, default=d("stop_thresh"), help=h("stop_thresh"))
    p.add_argument("--background", default=None, help="white, black or R,G,B (default: white)")
    p.add_argument("--backend", choices=("auto", "numba", "torch"), default=d("backend"),
                   help=h("backend"))
    p.add_argument("--seed", type=int, default=d("seed"), help=h("seed"))
    p.add_argument("--checkpoint", default=None, help=h("checkpoint"))
    p.add_argument("--resume", action="store_true", help=h("resume"))
    p.add_argument("--log", default=None, help=h("log"))
    p.add_argument("--progress", choices=("on", "off"), default=None, help=h("show_progress"))
    p.add_argument("--quiet", action="store_true", help="no per-epoch lines on stderr")
    p.add_argument("--json", action="store_true", help="also print the result as JSON")
    p.set_defaults(func=_run)
