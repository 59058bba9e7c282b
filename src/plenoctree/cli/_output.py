"""The flags every command spells the same way: progress, quiet, JSON output.

- ``--progress / --no-progress``: progress bars (default: when stderr is a terminal); the
  ``show_progress`` field of a command's config, or :func:`add_progress`;
- ``--quiet``: only warnings and errors: no per-step lines and, unless ``--progress`` is
  given, no progress bars (every command built by :func:`~._options.add_command`);
- ``--json [PATH]``: also write the command's result as JSON to PATH (``-`` or no value:
  stdout).

A count of views is ``--views N`` wherever it selects views of a dataset split, and 0 means
all of them.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

__all__ = ["add_json", "add_quiet", "add_progress", "quiet_progress", "write_json", "VIEWS",
           "views_or_all"]

VIEWS = {"flag": "views", "metavar": "N"}
"""The flag options of a config field counting the views of a split to use (``fields=`` of
:func:`~._options.add_command`): ``--views N``, 0 = all."""


def add_json(p: argparse.ArgumentParser, what: str = "the report") -> None:
    p.add_argument("--json", nargs="?", const="-", default=None, metavar="PATH",
                   help=f"also write {what} as JSON to PATH ('-' or no value: stdout)")


def add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true",
                   help="only warnings and errors: no per-step lines, no progress bars unless "
                        "--progress")


def add_progress(p: argparse.ArgumentParser) -> None:
    """``--progress/--no-progress`` for a command whose config has no ``show_progress``."""
    p.add_argument("--progress", dest="show_progress", action=argparse.BooleanOptionalAction,
                   default=None, help="progress bars (default: when stderr is a terminal)")


def quiet_progress(cfg: Any, args: argparse.Namespace) -> Any:
    """``cfg`` with ``show_progress`` off under ``--quiet`` unless ``--progress`` was given."""
    if (getattr(args, "quiet", False) and hasattr(cfg, "show_progress")
            and getattr(args, "show_progress", None) is None):
        cfg.show_progress = False
    return cfg


def views_or_all(n: int | None) -> int | None:
    """The value of ``--views N`` as a view limit: ``None`` (all) for 0 or not given."""
    if n is not None and n < 0:
        from ..errors import ConfigError

        raise ConfigError(f"--views must be >= 0 (0 = all), got {n}")
    return n or None


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
