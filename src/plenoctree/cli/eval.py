"""``plenoctree eval``: score a tree file on a dataset split (PSNR, SSIM, LPIPS, FPS, size).

Every option is a field of :class:`plenoctree.evaluation.EvalConfig`; ``--data`` defaults to
the dataset recorded next to the tree.
"""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from ..evaluation import EvalConfig, eval_markdown, eval_tree_file
    from ._options import layered
    from ._output import write_json
    from ._provenance import data_from_provenance

    cfg = layered(args, EvalConfig(tree=args.tree, data=""), "eval")
    if not cfg.data:
        cfg.data = data_from_provenance(cfg.tree, "eval")
    if args.json not in (None, "-"):
        cfg.json_path = args.json
    report = eval_tree_file(cfg)
    print(eval_markdown(report))
    print(f"-> {report['out']}/eval.json, eval.md")
    if args.json == "-":
        write_json("-", report)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``eval`` command."""
    from ..datasets import FORMATS
    from ..evaluation import EvalConfig
    from ._options import add_config, add_config_file
    from ._output import add_json

    p = sub.add_parser(
        "eval", help="score a tree on a dataset split: PSNR, SSIM, LPIPS, FPS, size (JSON + md)",
        description="Render every view of a dataset split with a tree (native, svox or "
                    "compressed) and report PSNR, SSIM, LPIPS (skipped unless its weights are "
                    "on disk), render FPS at the dataset resolution (median after a warm-up), "
                    "leaves, nodes and MB. Writes eval.json and eval.md.")
    p.add_argument("tree", help="tree file (.npz native/svox, .plnz or svox compressed .npz)")
    add_config_file(p)
    dests = add_config(p, EvalConfig, skip=("tree", "json_path"),
                       rename={"limit": "views", "show_progress": "progress"},
                       aliases={"limit": "--limit"},
                       choices={"format": FORMATS, "lpips_net": ("vgg", "alex", "squeeze")})
    add_json(p, "the report")
    p.set_defaults(func=_run, _dests=dests)
