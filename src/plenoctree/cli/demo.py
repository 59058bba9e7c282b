"""``plenoctree demo``: the whole chain on the embedded procedural scene."""

from __future__ import annotations

import argparse
from pathlib import Path


def _run(cfg, args: argparse.Namespace) -> int:
    from ..demo import run_demo

    cfg.out = Path(cfg.out)
    run_demo(cfg)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` command (one flag per :class:`DemoConfig` field)."""
    from ..demo import DemoConfig
    from ._options import add_command

    add_command(sub, "demo", DemoConfig, _run,
                help="the whole chain on the embedded procedural scene",
                description="Write the procedural scene as a dataset, train a NeRF-SH, "
                            "extract, fine-tune, evaluate, compress, export the viewer and an "
                            "orbit video; prints one summary table.")
