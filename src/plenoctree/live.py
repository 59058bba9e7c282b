"""Where a run stands, for a live view (issue 49): ``live.json`` in the run folder.

The trainer (``plenoctree train``, and the NeRF-SH stage of ``run`` in ``OUT/nerf``) and the
stages of ``run`` (in ``OUT``) write it atomically whenever something a viewer should show
changes: the stage, the step and its total, the PSNR, the estimated seconds left, and the
newest tree (a path relative to the folder of the ``live.json``: the trainer's coarse preview
``preview.npz``, then ``tree.npz``, the refined and the fine-tuned trees as they land).
``plenoctree view OUT`` reads it (:func:`read_live`) and shows that tree, reloading when a
newer one lands.

Example ``live.json``::

    {"stage": "training", "step": 1200, "steps": null, "psnr": 24.1, "eta_s": 610.0,
     "tree": "preview.npz", "updated": 1765031234.5}
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from ._util import atomic_save_json

__all__ = ["LIVE_NAME", "write_live", "read_live", "newest_tree", "RUN_TREES"]

LIVE_NAME = "live.json"

#: The trees of a run folder, newest stage last: what a viewer shows of a folder without a
#: ``live.json`` (a run made before it existed), the last one that exists.
RUN_TREES = ("nerf/preview.npz", "preview.npz", "tree.npz", "tree_refined.npz", "tree_ft.npz",
             "tree_ft.plnz")


def write_live(folder: str | os.PathLike, **fields: Any) -> None:
    """Merge ``fields`` into ``folder/live.json`` (atomically) with the time of the update.
    Fields: ``stage`` (str), ``step``/``steps`` (int; ``steps`` None for a time budget),
    ``psnr`` (dB), ``eta_s`` (seconds), ``tree`` (relative path). Never raises for a folder
    that cannot be written (a live view is a convenience, not part of the run)."""
    path = Path(folder) / LIVE_NAME
    try:
        old = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        old = {}
    old.update({k: v for k, v in fields.items()})
    old["updated"] = time.time()
    try:
        atomic_save_json(path, old)
    except OSError:
        pass


def _load(path: Path) -> dict | None:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def read_live(folder: str | os.PathLike) -> dict | None:
    """The status of the run in ``folder``: the newer of ``folder/live.json`` and
    ``folder/nerf/live.json`` (``run``'s training stage), with ``tree`` made an absolute
    :class:`Path` (None when it names no file). None without either file."""
    folder = Path(folder)
    found = []
    for sub in (folder, folder / "nerf"):
        d = _load(sub / LIVE_NAME)
        if d is not None:
            found.append((float(d.get("updated") or 0.0), sub, d))
    if not found:
        return None
    _, sub, d = max(found, key=lambda x: x[0])
    d["tree"] = _tree_in(sub, d.get("tree"))
    return d


def _tree_in(folder: Path, name: Any) -> Path | None:
    """``folder/name`` when ``name`` names a tree file (``.npz``/``.plnz``) inside ``folder``
    (a ``live.json`` cannot make a viewer serve any other file), else None."""
    if not isinstance(name, str) or not name.endswith((".npz", ".plnz")):
        return None
    path = folder / name
    try:
        inside = path.resolve().is_relative_to(folder.resolve())
    except (OSError, ValueError):
        return None
    return path if inside and path.is_file() else None


def newest_tree(folder: str | os.PathLike) -> Path | None:
    """The tree a viewer of the run in ``folder`` shows: the one ``live.json`` names, else the
    last of :data:`RUN_TREES` that exists (None: no tree yet)."""
    folder = Path(folder)
    live = read_live(folder)
    if live is not None and live["tree"] is not None:
        return live["tree"]
    found = [folder / n for n in RUN_TREES if (folder / n).is_file()]
    return found[-1] if found else None
