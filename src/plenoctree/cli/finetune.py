"""``plenoctree finetune``: optimise a tree's leaf values on the training photos (paper §4.3).

Every option is a field of :class:`plenoctree.optim.finetuning.FinetuneConfig` (help = the
field's ``help``); ``--data`` defaults to the dataset recorded next to the tree.
"""

from __future__ import annotations

import argparse


def _run(cfg, args: argparse.Namespace) -> int:
    from ..optim.finetuning import finetune
    from ._output import write_json
    from ._provenance import data_from_provenance

    if args.quiet:
        cfg.verbose = False
    if not cfg.data and cfg.tree:
        cfg.data = data_from_provenance(cfg.tree, "finetune")
    res = finetune(cfg)
    fmt = lambda v: "n/a" if v is None else f"{v:.3f} dB"  # noqa: E731
    print(f"test PSNR before {fmt(res.test_psnr_before)}  after {fmt(res.test_psnr_after)}")
    print(f"{res.epochs_run} epochs ({res.steps} steps), best epoch {res.best_epoch}, "
          f"{res.wall_seconds:.1f} s, {res.train_rays_per_second / 1e6:.2f} M rays/s "
          f"({res.backend}); {res.stop_reason}")
    print(f"saved {res.out}")
    write_json(args.json, res.to_json())
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``finetune`` command."""
    from ..optim.finetuning import FinetuneConfig
    from ._options import add_command
    from ._output import add_json

    p = add_command(sub, "finetune", FinetuneConfig, _run,
                    help="fine-tune a tree's leaf values on the training images",
                    description="Optimise σ and the SH coefficients of every leaf on the "
                                "training photos (tree structure fixed). Prints the test "
                                "PSNR before and after.",
                    positional=("tree",), skip=("verbose",))
    add_json(p, "the result")
