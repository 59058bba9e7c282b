"""``plenoctree demo``: the whole chain on the embedded procedural scene."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path


def _run(args: argparse.Namespace) -> int:
    from ..demo import DemoConfig, run_demo

    cfg = DemoConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(DemoConfig)})
    cfg.out = Path(cfg.out)
    run_demo(cfg)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` command (one flag per :class:`DemoConfig` field)."""
    from ..demo import DemoConfig
    from ..nerf.config import field_docs

    d, docs = DemoConfig(), field_docs(DemoConfig)
    p = sub.add_parser("demo", help="the whole chain on the embedded procedural scene",
                       description="Write the procedural scene as a dataset, train a NeRF-SH, "
                                   "extract, fine-tune, evaluate, compress, export the viewer "
                                   "and an orbit video; prints one summary table.")
    for f in dataclasses.fields(DemoConfig):
        default = getattr(d, f.name)
        kind = str if isinstance(default, Path) else type(default)
        p.add_argument("--" + f.name.replace("_", "-"), dest=f.name, type=kind,
                       default=str(default) if isinstance(default, Path) else default,
                       help=f"{docs.get(f.name, '')} (default {default})")
    p.set_defaults(func=_run)
