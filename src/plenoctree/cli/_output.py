"""The flags every command spells the same way: progress, quiet, JSON output, view counts.

- ``--progress / --no-progress``: progress bars (default: when stderr is a terminal);
- ``--quiet``: no progress bars and no per-step lines;
- ``--json [PATH]``: also write the command's result as JSON to PATH (``-`` or no value:
  stdout);
- ``--views N``: use N views of the dataset split (0 / omitted = all).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

__all__ = ["add_json", "add_quiet", "add_progress", "add_views", "write_json"]


def add_json(p: argparse.ArgumentParser, what: str = "the report") -> None:
    p.add_argument("--json", nargs="?", const="-", default=None, metavar="PATH",
                   help=f"also write {what} as JSON to PATH ('-' or no value: stdout)")


def add_quiet(p: argparse.ArgumentParser, text: str = "no progress bars or per-step lines"
              ) -> None:
    p.add_argument("--quiet", action="store_true", help=text)


def add_progress(p: argparse.ArgumentParser, dest: str = "show_progress") -> None:
    p.add_argument("--progress", dest=dest, action=argparse.BooleanOptionalAction,
                   default=None, help="progress bars (default: when stderr is a terminal)")


def add_views(p: argparse.ArgumentParser, dest: str = "views", legacy: str | None = None,
              text: str = "use only the first N views of the split (default: all)") -> None:
    names = ["--views"] + ([legacy] if legacy else [])
    p.add_argument(*names, dest=dest, type=int, default=None, metavar="N", help=text)


def write_json(path: str | None, obj: Any) -> None:
    """Write ``obj`` to ``path`` (atomic), to stdout for ``-``, nowhere for ``None``."""
    if path is None:
        return
    if path == "-":
        print(json.dumps(obj, indent=2, default=str))
        sys.stdout.flush()
        return
    from .._util import atomic_save_json

    atomic_save_json(path, obj)
