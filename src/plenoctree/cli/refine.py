"""``plenoctree refine TREE --run-dir RUN_DIR``: subdivide leaves where one value cannot
represent the NeRF-SH, merge siblings that agree (:mod:`plenoctree.convert.refine`).

Every option is a field of :class:`plenoctree.convert.refine.RefineConfig`; its docstring is the
``--help`` text.
"""

from __future__ import annotations

import argparse


def _run(cfg, args: argparse.Namespace) -> int:
    from ..convert.refine import refine

    res = refine(cfg)
    print(f"{res.leaves_before} -> {res.leaves_after} leaves ({res.nodes_after} nodes, depth "
          f"{res.max_depth}), {res.file_bytes / 2**20:.1f} MB, {res.seconds:.1f} s")
    if res.psnr_before is not None:
        print(f"test PSNR before {res.psnr_before:.3f} dB  after {res.psnr_after:.3f} dB "
              f"({res.eval_views} views)")
    print(f"saved {res.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``refine`` command."""
    from ..convert.refine import RefineConfig
    from ._options import add_command

    add_command(sub, "refine", RefineConfig, _run,
                help="adapt a tree's leaves to the NeRF-SH it came from",
                description="Score every leaf by the spread of the NeRF-SH inside it, "
                            "subdivide the worst (one level per pass), optionally merge "
                            "sibling leaves that agree; the tree stays svox-compatible.",
                positional=("tree",), fields={"out": {"short": "-o"}})
