"""``plenoctree eval``: score a tree file on a dataset split (PSNR, SSIM, LPIPS, FPS, size).

Every option is a field of :class:`plenoctree.evaluation.EvalConfig`; ``--data`` defaults to
the dataset recorded next to the tree.
"""

from __future__ import annotations

import argparse


def _run(cfg, args: argparse.Namespace) -> int:
    from ..evaluation import eval_markdown, eval_tree_file
    from ._output import views_or_all, write_json
    from ._provenance import data_from_provenance

    from ._output import check_json

    cfg.limit = views_or_all(cfg.limit)
    check_json(args)
    if cfg.out is not None:
        from .._util import check_output_dir

        check_output_dir(cfg.out)
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
    from ._options import add_command
    from ._output import VIEWS, add_json, add_overwrite

    p = add_command(
        sub, "eval", EvalConfig, _run,
        help="score a tree on a dataset split: PSNR, SSIM, LPIPS, FPS, size (JSON + md)",
        description="Render every view of a dataset split with a tree (native, svox or "
                    "compressed) and report PSNR, SSIM, LPIPS (skipped unless its weights are "
                    "on disk), render FPS at the dataset resolution (median after a warm-up), "
                    "leaves, nodes and MB. Writes eval.json and eval.md.",
        base=lambda: EvalConfig(tree="", data=""), positional=("tree",), skip=("json_path",),
        fields={"limit": VIEWS, "format": {"choices": FORMATS},
                "lpips_net": {"choices": ("vgg", "alex", "squeeze")}})
    add_json(p, "the report")
    add_overwrite(p)
