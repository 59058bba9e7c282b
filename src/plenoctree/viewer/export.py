"""``export-web``: a self-contained static bundle (page + tree) for any static web host.

Layout of the bundle (the same URL space as :class:`~plenoctree.viewer.server.ViewerServer`)::

    DIR/index.html, main.js, renderer.js, tree.js, npz.js, camera.js, viewer.css
    DIR/config.json            {"tree": "data/<name>", "title": ..., "lod_hint": ...,
                                "up": "+z", "cameras": {...}}   (the last two with cameras)
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
from typing import Any, Sequence

import numpy as np

from .._util import atomic_write
from ..errors import ConfigError
from .budget import DEFAULT_MAX_MB
from .server import _tree_name, check_servable, static_files, viewer_config

__all__ = ["export_web", "cameras_config", "add_cameras_to_server", "MAX_BUNDLE_CAMERAS"]

#: At most this many training cameras go into a bundle (evenly picked), to keep config.json small.
MAX_BUNDLE_CAMERAS = 300


def cameras_config(cameras: Any, names: list[str] | None = None,
                   max_cameras: int = MAX_BUNDLE_CAMERAS) -> dict[str, Any]:
    """The ``cameras`` / ``up`` entries of ``config.json`` for a :class:`Cameras` set.

    ``{"up": signed axis nearest the cameras' mean +y, "cameras": {"c2w": [[16 numbers,
    row-major OpenGL camera-to-world], ...], "fx", "fy" (a number or one per camera), "cx", "cy",
    "width", "height", "names"}}``. The page frames its first view like these cameras, lists
    them and jumps to them. NDC (forward-facing) cameras add ``"ndc": {"fx", "fy", "width",
    "height", "near"}`` (the NDC reference camera, :attr:`Cameras.ndc_focal`): the page then
    maps each world ray into NDC (as ``to_ndc_rays``) and starts at the reference camera.
    """
    from ..datasets.trajectories import detect_up_axis

    n = len(cameras)
    if n == 0:
        return {}
    idx = np.unique(np.round(np.linspace(0, n - 1, min(n, max_cameras))).astype(int))
    c2w = np.asarray(cameras.c2w, dtype=np.float64)[idx]
    intr = cameras.intrinsics_array()[idx]          # fx, fy, cx, cy per camera

    def one(col: np.ndarray) -> Any:
        return float(col[0]) if np.ptp(col) == 0 else [float(v) for v in col]

    out: dict[str, Any] = {
        "c2w": [[round(float(v), 7) for v in m.reshape(-1)] for m in c2w],
        "fx": one(intr[:, 0]), "fy": one(intr[:, 1]),
        "cx": one(intr[:, 2]), "cy": one(intr[:, 3]),
        "width": int(cameras.width), "height": int(cameras.height),
    }
    if names is not None:
        out["names"] = [str(names[i]) for i in idx if i < len(names)]
    cfg: dict[str, Any] = {"up": detect_up_axis(np.asarray(cameras.c2w)), "cameras": out}
    if getattr(cameras, "ndc", False):
        fx, fy = cameras.ndc_focal
        cfg["ndc"] = {"fx": float(fx), "fy": float(fy), "width": int(cameras.width),
                      "height": int(cameras.height), "near": float(cameras.ndc_near)}
    return cfg


def add_cameras_to_server(server: Any, extra: dict[str, Any]) -> None:
    """Serve ``extra`` (from :func:`cameras_config`) in a running ViewerServer's config.json."""
    if server.httpd.live is not None:               # a run folder: config.json is made per request
        server.httpd.config_extra.update(extra)
        return
    body, kind = server.httpd.routes["/config.json"]
    cfg = json.loads(body)
    cfg.update(extra)
    server.httpd.routes["/config.json"] = (json.dumps(cfg, indent=1).encode(), kind)

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
               max_mb: float = DEFAULT_MAX_MB, cameras: Any = None,
               camera_names: list[str] | None = None,
               background: Sequence[float] | None = None) -> Path:
    """Write the viewer page and ``tree_path`` into ``out_dir``; returns ``out_dir``.

    Args:
        tree_path: the tree file to ship (``.npz`` or ``.plnz``; copied as is).
        out_dir: created if missing; if it exists and is not empty, ``overwrite`` must be set
            (only the bundle's own files are replaced; other files are left alone).
        title: page title.
        max_mb: the page's texture budget in MB.
        cameras: the training :class:`Cameras` (optional): the first view is framed like them
            and the page lists them (see :func:`cameras_config`); ``camera_names`` labels them.
        background: the page's first background colour (RGB in [0, 1]; the page's own white
            when None); ``run`` gives the dataset's (black for real photos).
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
    from .._util import LOCK_NAME

    if out.is_dir() and any(p.name != LOCK_NAME for p in out.iterdir()) and not overwrite:
        raise ConfigError(f"{out}: folder is not empty (pass --overwrite to replace the bundle)")
    name = _tree_name(tree)
    if (out / "data" / name).resolve() == tree.resolve():
        raise ConfigError(f"{tree}: is the bundle's own copy; export from another file")
    (out / "data").mkdir(parents=True, exist_ok=True)
    for fname, src in static_files().items():
        shutil.copyfile(src, out / fname)
    config = viewer_config(name, title, max_mb)
    if cameras is not None:
        config.update(cameras_config(cameras, camera_names))
    if background is not None:
        config["background"] = [float(v) for v in background]
    with atomic_write(out / "config.json", "w") as f:
        json.dump(config, f, indent=1)
    with atomic_write(out / "data" / name, "wb") as f, open(tree, "rb") as src_f:
        shutil.copyfileobj(src_f, f, 1 << 20)
    with atomic_write(out / "README.txt", "w") as f:
        f.write(_README.format(dir=out, name=name))
    return out
