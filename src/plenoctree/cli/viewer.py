"""``plenoctree view / export-web``: the in-browser viewer, served locally or as a bundle."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from ..errors import TreeFormatError


@dataclass
class PageConfig:
    """What the viewer page shows (``view`` and ``export-web``)."""

    tree: str = ""
    """tree file (.npz or .plnz); for view also a run folder (run --out, train --out): its
    newest tree, reloaded as newer ones land while the run goes on"""
    max_mb: float = 2048.0
    """GPU texture budget in MB (written into a bundle); larger trees are refused with a hint
    to 'plenoctree lod'"""
    data: str | None = None
    """dataset folder: frame the first view like its cameras and list them in the page (jump
    to any)"""
    split: str = "train"
    """dataset split whose cameras"""


@dataclass
class ViewConfig(PageConfig):
    """Options of ``plenoctree view``."""

    port: int = 8000
    """TCP port (0 = any free)"""
    host: str = "127.0.0.1"
    """address to listen on; anything but loopback serves the tree to every machine that can
    reach it (prefer an ssh tunnel: docs/viewer.md)"""
    render: str = "auto"
    """who draws: webgl (the browser's GPU), cpu (this machine's numba renderer streams JPEG
    frames to the page) or auto (cpu when the browser has only software WebGL or none)"""
    open: bool = False
    """open the page in the default browser"""
    verbose: bool = False
    """log every request"""


@dataclass
class ExportWebConfig(PageConfig):
    """Options of ``plenoctree export-web``."""

    out: str = ""
    """output folder"""
    title: str | None = None
    """page title"""
    overwrite: bool = False
    """replace an existing bundle"""


def _check_tree(path: Path) -> None:
    """Fail early, in the terminal, on a file the page could not read."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
    except (OSError, zipfile.BadZipFile) as e:
        raise TreeFormatError(f"{path}: not a tree file (not a zip/.npz archive: {e})") from None
    if "child.npy" not in names or not ({"data.npy", "quant_colors.npy"} & names):
        raise TreeFormatError(f"{path}: not a tree file (no 'child' and 'data'/'quant_colors' "
                              "arrays)")


def _cameras_extra(cfg: PageConfig) -> dict:
    """config.json entries for --data: the split's cameras (first view, list, jumps) and the
    dataset's background (black for real photos: :func:`~plenoctree.datasets.default_background`).

    The images are loaded small (:func:`~plenoctree.datasets.load_cameras`) only to read the
    poses cheaply: the page uses the poses and the field of view (fx, fy relative to width,
    height), which downscaling keeps.
    """
    if not cfg.data:
        return {}
    from ..datasets import load_cameras
    from ..viewer.export import cameras_config

    data = load_cameras(cfg.data, split=cfg.split)       # (its background: the default's)
    return {**cameras_config(data.cameras, data.names),
            "background": [float(v) for v in data.background]}


def _warn_if_exposed(host: str, port: int) -> None:
    """Say on stderr that a non-loopback ``host`` serves the tree to the network."""
    from ..viewer.server import is_loopback

    if is_loopback(host):
        return
    print(f"warning: listening on {host}:{port}, not loopback: anyone who can reach this "
          "address can download the tree (the viewer has no login). To view from another "
          f"machine privately, keep the default host and tunnel instead:\n"
          f"  ssh -L {port}:127.0.0.1:{port} THIS_HOST   then open http://127.0.0.1:{port}/",
          file=sys.stderr, flush=True)


def _run_view(cfg: ViewConfig, args: argparse.Namespace) -> int:
    from ..viewer import ViewerServer
    from ..viewer.budget import check_texture_budget

    path = Path(cfg.tree)
    live = path.is_dir()             # a run folder: its newest tree, reloaded as newer land
    if not live:
        _check_tree(path)
    # CPU mode: the page never holds the tree, so no texture budget applies
    need = check_texture_budget(path, cfg.max_mb) if cfg.render != "cpu" and not live else None
    extra = _cameras_extra(cfg)
    server = ViewerServer(path, port=cfg.port, max_mb=cfg.max_mb, verbose=cfg.verbose,
                          render=cfg.render, host=cfg.host)
    if extra:
        from ..viewer.export import add_cameras_to_server

        add_cameras_to_server(server, extra)
    _warn_if_exposed(cfg.host, server.port)
    how = {"webgl": "WebGL in the browser", "cpu": "the CPU renderer here",
           "auto": "WebGL, or the CPU renderer here when the browser's GL is software"}
    size = "" if need is None else f" ({need / 1e6:.0f} MB of textures)"
    what = f"the newest tree of the run in {path} (live)" if live else f"{path}{size}"
    print(f"Serving {what} at {server.url}, drawn by "
          f"{how[cfg.render]}  (Ctrl-C to stop)", flush=True)
    if cfg.open:
        import webbrowser

        webbrowser.open(server.url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
    return 0


def _run_export(cfg: ExportWebConfig, args: argparse.Namespace) -> int:
    from ..viewer import export_web
    from ._output import output_dir

    from ..viewer.budget import check_texture_budget

    path = Path(cfg.tree)
    _check_tree(path)
    check_texture_budget(path, cfg.max_mb)
    extra = _cameras_extra(cfg)
    with output_dir(cfg.out, "export-web"):
        out = export_web(path, cfg.out, title=cfg.title, overwrite=cfg.overwrite,
                         max_mb=cfg.max_mb)
        if extra:
            import json

            from .._util import atomic_save_json

            cfg = json.loads((out / "config.json").read_text())
            cfg.update(extra)
            atomic_save_json(out / "config.json", cfg)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"wrote {out} ({size / 1e6:.2f} MB); serve it with any static web server, e.g.\n"
          f"  python -m http.server --bind 127.0.0.1 8000 --directory {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``view`` and ``export-web`` commands (flags: :class:`ViewConfig`,
    :class:`ExportWebConfig`)."""
    from ._options import add_command

    from ..viewer.frames import RENDER_MODES

    add_command(sub, "view", ViewConfig, _run_view,
                help="view a tree in the browser (local server on 127.0.0.1)",
                description="Start a local HTTP server bound to 127.0.0.1 (or --host) that "
                "serves the WebGL2 viewer page and TREE (raw .npz or compressed .plnz), and "
                "print its URL. It serves nothing else. Without a GPU (--render cpu, or auto "
                "when the browser's WebGL is software) the server draws the frames with the "
                "numba CPU renderer and streams them to the page.", positional=("tree",),
                fields={"render": {"choices": RENDER_MODES}})
    add_command(sub, "export-web", ExportWebConfig, _run_export,
                help="write a static viewer bundle (page + tree)",
                description="Write the viewer page and TREE into a folder that any static web "
                "host can serve.", positional=("tree",), fields={"out": {"required": True}})
