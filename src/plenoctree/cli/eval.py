"""``plenoctree eval``: score a tree file on a dataset split (PSNR, SSIM, LPIPS, FPS, size)."""

from __future__ import annotations

import argparse

from .render import add_render_options, parse_background


def _run(args: argparse.Namespace) -> int:
    from ..evaluation import EvalConfig, eval_markdown, eval_tree_file

    cfg = EvalConfig(
        tree=args.tree, data=args.data, split=args.split, format=args.format,
        downscale=args.downscale, limit=args.limit, out=args.out, json_path=args.json,
        save_images=args.save_images, backend=args.backend, device=args.device, stop_thresh=args.stop_thresh,
        background=parse_background(args.background) if args.background else None,
        lpips_net=args.lpips_net)
    report = eval_tree_file(cfg)
    print(eval_markdown(report))
    print(f"-> {report['out']}/eval.json, eval.md")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``eval`` command."""
    from ..datasets import FORMATS

    p = sub.add_parser(
        "eval", help="score a tree on a dataset split: PSNR, SSIM, LPIPS, FPS, size (JSON + md)",
        description="Render every view of a dataset split with a tree (native, svox or "
                    "compressed) and report PSNR, SSIM, LPIPS (skipped unless its weights are "
                    "on disk), render FPS at the dataset resolution (median after a warm-up), "
                    "leaves, nodes and MB. Writes eval.json and eval.md.")
    p.add_argument("tree", help="tree file (.npz native/svox, .plnz or svox compressed .npz)")
    p.add_argument("--data", required=True, help="dataset folder")
    p.add_argument("--split", default="test", help="dataset split (default: test)")
    p.add_argument("--format", default=None, choices=FORMATS,
                   help="dataset format (default: detected)")
    p.add_argument("--downscale", type=int, default=1, help="integer area downscale of the images")
    p.add_argument("--limit", type=int, default=None, help="only the first N views")
    p.add_argument("--out", default=None,
                   help="folder for eval.json / eval.md (default: <tree>_eval_<split> next to "
                        "the tree)")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the JSON report here")
    p.add_argument("--save-images", action="store_true",
                   help="also write the renders and depth maps under <out>/renders/")
    p.add_argument("--lpips-net", default="vgg", choices=("vgg", "alex", "squeeze"),
                   help="LPIPS backbone (default: vgg, as the paper)")
    add_render_options(p)
    p.set_defaults(func=_run)
