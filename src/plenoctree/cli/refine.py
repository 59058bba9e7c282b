"""``plenoctree refine TREE --run RUN_DIR``: subdivide leaves where one value cannot represent the
NeRF-SH, merge siblings that agree (:mod:`plenoctree.convert.refine`).

Every option is a field of :class:`plenoctree.convert.refine.RefineConfig`; its docstring is the
``--help`` text.
"""

from __future__ import annotations

import argparse
import dataclasses


def _run(args: argparse.Namespace) -> int:
    from ..convert.refine import RefineConfig, refine

    kw = {f.name: getattr(args, f.name) for f in dataclasses.fields(RefineConfig)
          if hasattr(args, f.name)}
    res = refine(RefineConfig(**kw))
    line = (f"{res.leaves_before} -> {res.leaves_after} leaves ({res.nodes_after} nodes, depth "
            f"{res.max_depth}), {res.file_bytes / 2**20:.1f} MB, {res.seconds:.1f} s")
    print(line)
    if res.psnr_before is not None:
        print(f"test PSNR before {res.psnr_before:.3f} dB  after {res.psnr_after:.3f} dB "
              f"({res.eval_views} views)")
    print(f"saved {res.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``refine`` command."""
    from ..convert.refine import RefineConfig
    from ..nerf.config import field_docs

    docs = field_docs(RefineConfig)
    p = sub.add_parser("refine", help="adapt a tree's leaves to the NeRF-SH it came from",
                       description="Score every leaf by the spread of the NeRF-SH inside it, "
                                   "subdivide the worst (one level per pass), optionally merge "
                                   "sibling leaves that agree; the tree stays svox-compatible.")
    for f in dataclasses.fields(RefineConfig):
        help_ = docs.get(f.name, "").replace("%", "%%")
        if f.name == "tree":
            p.add_argument("tree", help=help_)
        elif f.name == "run_dir":
            p.add_argument("--run", dest="run_dir", required=True, help=help_)
        elif f.name == "show_progress":
            p.add_argument("--progress", dest="show_progress",
                           action=argparse.BooleanOptionalAction, default=None, help=help_)
        else:
            flag = "--" + f.name.replace("_", "-")
            p.add_argument(flag, dest=f.name, type=type(f.default), default=f.default,
                           help=f"{help_} (default: {f.default!r})" if f.default != "" else help_)
    p.set_defaults(func=_run)
