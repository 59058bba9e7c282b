"""``plenoctree demo``: the whole chain on the embedded procedural scene."""

from __future__ import annotations

import argparse
from pathlib import Path


def _run(args: argparse.Namespace) -> int:
    from ..demo import DemoConfig, run_demo
    from ._options import layered

    cfg = layered(args, DemoConfig(), "demo")
    cfg.out = Path(cfg.out)
    run_demo(cfg)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` command (one flag per :class:`DemoConfig` field)."""
    from ..demo import DemoConfig
    from ._options import add_config

    p = sub.add_parser("demo", help="the whole chain on the embedded procedural scene",
                       description="Write the procedural scene as a dataset, train a NeRF-SH, "
                                   "extract, fine-tune, evaluate, compress, export the viewer "
                                   "and an orbit video; prints one summary table.")
    p.set_defaults(func=_run, _dests=add_config(p, DemoConfig))
