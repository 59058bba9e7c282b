"""``plenoctree demo``: the whole chain on the embedded procedural scene."""

from __future__ import annotations

import argparse


def _config(args: argparse.Namespace):
    """The :class:`DemoConfig`: its defaults, then ``--config FILE``, then the flags given."""
    from ..demo import DemoConfig
    from ..pipeline import layer_settings
    from ._options import layered
    from ._output import quiet_progress

    return quiet_progress(layered(args, DemoConfig(), "demo", layer_settings), args)


def _run(args: argparse.Namespace) -> int:
    from ..demo import run_demo

    run_demo(_config(args))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``demo`` command (``run``'s flags, with the demo's defaults)."""
    from ..demo import DemoConfig
    from ._options import add_config_file
    from ._output import add_quiet
    from .run import add_pipeline_flags

    p = sub.add_parser("demo", help="the whole chain on the embedded procedural scene",
                       description="Write the procedural scene as a dataset, train a NeRF-SH, "
                                   "extract, fine-tune, evaluate, compress, export the viewer "
                                   "and an orbit video; prints one summary table. Takes "
                                   "`plenoctree run`'s options (--help-all).")
    add_config_file(p)
    add_quiet(p)
    dests = add_pipeline_flags(p, DemoConfig(), skip=("images", "nerf", "downscale",
                                                      "nerf_eval_views"))
    p.set_defaults(func=_run, _dests=dests, _resolve=_config)
