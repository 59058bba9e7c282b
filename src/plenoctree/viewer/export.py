"""``export-web``: a self-contained static bundle (page + tree) for any static web host.

Layout of the bundle (the same URL space as :class:`~plenoctree.viewer.server.ViewerServer`)::

    DIR/index.html, main.js, renderer.js, tree.js, npz.js, camera.js, viewer.css
    DIR/config.json            {"tree": "data/<name>", "title": ..., "lod_hint": ...}
    DIR/data/<name>            the tree (.npz or .plnz)
    DIR/README.txt             how to serve it

The page fetches its files by relative URL, so the folder can live at any path of a host. It
needs HTTP (browsers do not let a ``file://`` page fetch files).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from .._util import atomic_write
from ..errors import ConfigError
from .budget import DEFAULT_MAX_MB
from .server import _tree_name, check_servable, static_files, viewer_config

__all__ = ["export_web"]

_README = """PlenOctree web viewer bundle
============================

Serve this folder with any static web server and open index.html, for example:

    python -m http.server --bind 127.0.0.1 8000 --directory {dir}
    # then open http://127.0.0.1:8000/

The tree is data/{name}; config.json names it. Opening index.html from the disk (file://)
does not work: browsers do not let such a page fetch files.
"""


def export_web(tree_path: str | os.PathLike, out_dir: str | os.PathLike,
               title: str | None = None, overwrite: bool = False,
               max_mb: float = DEFAULT_MAX_MB) -> Path:
    """Write the viewer page and ``tree_path`` into ``out_dir``; returns ``out_dir``.

    Args:
        tree_path: the tree file to ship (``.npz`` or ``.plnz``; copied as is).
        out_dir: created if missing; if it exists and is not empty, ``overwrite`` must be set
            (only the bundle's own files are replaced; other files are left alone).
        title: page title.
        max_mb: the page's texture budget in MB.
    Raises:
        ConfigError: missing tree, ``out_dir`` is a file or a non-empty folder without
        ``overwrite``. TreeFormatError: a tree the page would refuse (see
        :func:`~plenoctree.viewer.server.check_servable`).
    """
    tree = Path(tree_path)
    if not tree.is_file():
        raise ConfigError(f"{tree}: no such tree file")
    check_servable(tree)         # never ship a tree the page would refuse
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ConfigError(f"{out}: folder is not empty (pass --overwrite to replace the bundle)")
    name = _tree_name(tree)
    if (out / "data" / name).resolve() == tree.resolve():
        raise ConfigError(f"{tree}: is the bundle's own copy; export from another file")
    (out / "data").mkdir(parents=True, exist_ok=True)
    for fname, src in static_files().items():
        shutil.copyfile(src, out / fname)
    with atomic_write(out / "config.json", "w") as f:
        json.dump(viewer_config(name, title, max_mb), f, indent=1)
    with atomic_write(out / "data" / name, "wb") as f, open(tree, "rb") as src_f:
        shutil.copyfileobj(src_f, f, 1 << 20)
    with atomic_write(out / "README.txt", "w") as f:
        f.write(_README.format(dir=out, name=name))
    return out
