"""The viewer of a run folder (``plenoctree view OUT``, issue 49): the newest tree of a run
that is still going, swapped for a newer one as it lands.

What the run writes (:mod:`plenoctree.live`): ``live.json`` with its stage, step, PSNR, ETA
and newest tree (the trainer's coarse previews, then the extracted, refined, fine-tuned and
compressed trees). The server answers, per request:

- ``/live.json``: that status plus ``version`` (the newest tree's name, size and mtime) and
  ``tree`` (``data/<name>``, or null before the first tree);
- ``/config.json``: the page's configuration for the newest tree (``live: true``, its
  ``version``; in CPU mode the description of the tree the server draws);
- ``/data/<name>``: the newest tree's file.

The page polls ``live.json`` and, when the version changes, reloads itself keeping its camera
(``static/main.js``); in CPU mode the server loads the new tree (:class:`~.frames.FrameRenderer`)
when the page first asks for its configuration or a frame, and keeps drawing the old one until
then. A tree that cannot be read (a run that wrote something broken) is reported in the status
and the last good one stays.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Any

from ..errors import PlenOctreeError

__all__ = ["LiveTrees"]

logger = logging.getLogger(__name__)


def _version(path: Path | None) -> str:
    if path is None:
        return ""
    try:
        st = path.stat()
    except OSError:
        return ""
    return f"{path.name}:{st.st_size}:{st.st_mtime_ns}"


class LiveTrees:
    """The trees of the run in ``folder`` for a :class:`~.server.ViewerServer`.

    Args:
        folder: the run folder (``run --out`` or ``train --out``).
        cpu: the server draws frames (render modes ``cpu`` and ``auto``).
    """

    def __init__(self, folder: str | os.PathLike, cpu: bool) -> None:
        self.folder = Path(folder)
        self.cpu = cpu
        self._lock = threading.Lock()
        self._frames: Any = None
        self._frames_version = ""
        self._path: Path | None = None
        self.error: str | None = None

    def newest(self) -> tuple[Path | None, str]:
        """``(path, version)`` of the run's newest tree (None, "" before the first)."""
        from ..live import newest_tree

        path = newest_tree(self.folder)
        return path, _version(path)

    def shown(self) -> tuple[Path | None, str]:
        """``(path, version)`` of the tree the page gets now: the newest, or in CPU mode the
        newest the server could load (a broken newest tree does not make the page reload)."""
        if not self.cpu:
            return self.newest()
        frames, version = self.frames()
        return (self._path if frames is not None else None), version

    def status(self) -> dict[str, Any]:
        """``live.json`` of the run with the shown tree's ``version`` and URL."""
        from ..live import read_live

        live = read_live(self.folder) or {}
        path, version = self.shown()
        live.pop("tree", None)
        live.update(version=version, tree=None if path is None else f"data/{path.name}",
                    error=self.error)
        return live

    def file(self, name: str) -> Path | None:
        """The newest tree's path when ``name`` is its file name (None otherwise)."""
        path, _ = self.newest()
        return path if path is not None and path.name == name else None

    def frames(self) -> tuple[Any, str]:
        """``(FrameRenderer, version)`` of the newest readable tree (loads a newer tree first;
        ``(None, "")`` before the first)."""
        from ..compression.fileio import load_any_tree      # (server.check_servable's check)
        from .frames import FrameRenderer

        path, version = self.newest()
        with self._lock:
            if path is not None and version != self._frames_version:
                try:
                    self._frames = FrameRenderer(load_any_tree(path))
                    self._frames_version, self._path, self.error = version, path, None
                except (PlenOctreeError, OSError, ValueError) as e:
                    self.error = f"{path.name}: {e}"
                    logger.warning("viewer: the run's newest tree is not readable yet: %s", e)
            return self._frames, self._frames_version
