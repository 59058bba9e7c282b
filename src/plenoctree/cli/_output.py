"""The flags every command spells the same way: progress, quiet, JSON output.

- ``--progress / --no-progress``: progress bars (default: when stderr is a terminal); the
  ``show_progress`` field of a command's config, or :func:`add_progress`;
- ``--quiet``: only warnings and errors: no per-step lines and, unless ``--progress`` is
  given, no progress bars (every command built by :func:`~._options.add_command`);
- ``--json [PATH]``: also write the command's result as JSON to PATH (``-`` or no value:
  stdout);
- ``--overwrite``: replace an existing output file that does not look like plenoctree's.

A count of views is ``--views N`` wherever it selects views of a dataset split, and 0 means
all of them.

Every command that writes a file or folder checks it *before* the work with
:func:`output_file` / :func:`output_dir` (writable, not a folder, not an unrelated file) and
holds a lock on it while it writes, so two commands writing one path cannot mix their results:
the second is refused naming the first.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path
from typing import Any, Iterator

__all__ = ["add_json", "add_quiet", "add_progress", "quiet_progress", "add_overwrite",
           "write_json", "check_json", "output_file", "output_dir", "VIEWS", "views_or_all"]

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


def add_overwrite(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output file even if plenoctree did not write it")


def check_json(args: argparse.Namespace) -> None:
    """Check ``--json PATH`` before the work: a writable file that is not a folder nor an
    unrelated existing file (``--overwrite`` allows that). ``-`` / absent: nothing to check."""
    path = getattr(args, "json", None)
    if path not in (None, "-"):
        from .._util import check_output_file

        check_output_file(path, "--json", getattr(args, "overwrite", False), kind="json")


@contextlib.contextmanager
def output_file(path: str | Path, command: str, flag: str = "--out",
                overwrite: bool = False, kind: str | None = None) -> Iterator[Path]:
    """Check an output file before the work and hold its lock while the block writes it.

    ``kind``: what an existing file must be to be replaced without ``overwrite`` (``"tree"``,
    ``"json"``, ``None``: the suffix's kind). A second process writing the same path gets a
    ``ConfigError`` naming the holder.
    """
    from .._util import check_output_file, run_lock

    p = check_output_file(path, flag, overwrite, kind=kind)
    with run_lock(p, command, folder=False):
        yield p


@contextlib.contextmanager
def output_dir(path: str | Path, command: str, flag: str = "--out") -> Iterator[Path]:
    """Check an output folder before the work (nothing is created until the block writes) and
    hold its lock (``<folder>/.plenoctree.lock``) while the block runs."""
    from .._util import check_output_dir, run_lock

    p = check_output_dir(path, flag)
    with run_lock(p, command):
        yield p

