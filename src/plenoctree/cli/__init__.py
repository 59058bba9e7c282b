"""The ``plenoctree`` command line: parses arguments and calls the package's ``run`` functions.

Each command group lives in its own module of this package, exposing
``register(subparsers) -> None``; that function adds its sub-commands, each with
``set_defaults(func=...)`` where ``func(args) -> int`` does the work. Nothing else in the
package imports :mod:`plenoctree.cli`.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from ..errors import PlenOctreeError

# Preferred --help order of the command-group modules. Every module of this package that
# defines register(subparsers) is registered; the ones not listed here come after, by name.
_GROUPS = [
    "info",
    "demo",
    "train",
    "extract",
    "finetune",
    "render",
    "eval",
    "video",
    "compress",
    "viewer",
]


def _group_modules() -> list[str]:
    """Names of this package's command-group modules, in --help order."""
    found = [m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")]
    rank = {name: i for i, name in enumerate(_GROUPS)}
    return sorted(found, key=lambda n: (rank.get(n, len(rank)), n))


def build_parser() -> argparse.ArgumentParser:
    """Return the full argument parser with every command group registered."""
    from ._options import CommandParser, Parser

    parser = Parser(
        prog="plenoctree",
        description="PlenOctrees: train NeRF-SH, convert to an octree, fine-tune, render, view.",
    )
    from .. import __version__

    parser.add_argument("--version", action="version", version=f"plenoctree {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
    for name in _group_modules():
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``plenoctree`` console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # Every command may run torch and numba together: the OpenMP/malloc settings must precede
    # both runtimes, and nothing has imported them yet (the package root is lazy).
    from .. import runtime
    from .._log import configure_cli

    runtime.configure()
    configure_cli(quiet=bool(getattr(args, "quiet", False)))
    try:
        return int(args.func(args) or 0)
    except PlenOctreeError as e:
        print(f"plenoctree {args.command}: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:           # a file system refusal the checks could not foresee
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"plenoctree {args.command}: error: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"plenoctree {args.command}: error: out of memory (use a smaller image size, "
              "--views or --downscale)", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"plenoctree {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
