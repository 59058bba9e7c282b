"""The package's logging: one ``plenoctree`` logger tree, configured by the CLI alone.

Library modules log through ``logging.getLogger(__name__)`` (children of ``plenoctree``) and
never print; a library user sees warnings through Python's default handler and turns on the
rest with ``logging.basicConfig(level=logging.INFO)``. The command line calls
:func:`configure_cli` once: INFO and up go to standard output as plain lines (the message only,
as the old print callbacks wrote them), ``--quiet`` keeps warnings and errors. Progress bars
are not log lines: they stay on stderr (:func:`plenoctree._util.progress`).
"""

from __future__ import annotations

import logging
import sys

__all__ = ["LOGGER_NAME", "configure_cli"]

LOGGER_NAME = "plenoctree"


class _StdoutHandler(logging.StreamHandler):
    """A handler writing to whatever ``sys.stdout`` is at emit time (pytest's capture too)."""

    def __init__(self) -> None:
        super().__init__(sys.stdout)

    @property  # type: ignore[override]
    def stream(self):  # noqa: D401 - the current stdout
        return sys.stdout

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it; ignored
        pass


def configure_cli(quiet: bool = False) -> logging.Logger:
    """Route the ``plenoctree`` logger to stdout as bare messages (idempotent).

    ``quiet``: only WARNING and above. Returns the logger.
    """
    logger = logging.getLogger(LOGGER_NAME)
    handler = next((h for h in logger.handlers if isinstance(h, _StdoutHandler)), None)
    if handler is None:
        handler = _StdoutHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    logger.propagate = False
    return logger
