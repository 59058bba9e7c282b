"""``plenoctree view / export-web``: the in-browser viewer, served locally or as a bundle."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import TreeFormatError


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


def _cameras_extra(args: argparse.Namespace) -> dict:
    """config.json entries for --data: the split's cameras (first view, list, jumps).

    The images are loaded at downscale 4 only to read the poses cheaply: the page uses the
    poses and the field of view (fx, fy relative to width, height), which downscaling keeps.
    """
    if not getattr(args, "data", None):
        return {}
    from ..datasets import load_dataset
    from ..viewer.export import cameras_config

    data = load_dataset(args.data, split=args.split, downscale=4)
    return cameras_config(data.cameras, data.names)


def _run_view(args: argparse.Namespace) -> int:
    from ..viewer import ViewerServer
    from ..viewer.budget import check_budget

    path = Path(args.tree)
    _check_tree(path)
    need = check_budget(path, args.max_mb)
    extra = _cameras_extra(args)
    server = ViewerServer(path, port=args.port, max_mb=args.max_mb, verbose=args.verbose)
    if extra:
        from ..viewer.export import add_cameras_to_server

        add_cameras_to_server(server, extra)
    print(f"Serving {path} ({need / 1e6:.0f} MB of textures) at {server.url}  (Ctrl-C to stop)",
          flush=True)
    if args.open:
        import webbrowser

        webbrowser.open(server.url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
    return 0


def _run_export(args: argparse.Namespace) -> int:
    from ..viewer import export_web

    from ..viewer.budget import check_budget

    path = Path(args.tree)
    _check_tree(path)
    check_budget(path, args.max_mb)
    extra = _cameras_extra(args)
    out = export_web(path, args.out, title=args.title, overwrite=args.overwrite,
                     max_mb=args.max_mb)
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
    """Add the ``view`` and ``export-web`` commands."""
    p = sub.add_parser("view", help="view a tree in the browser (local server on 127.0.0.1)",
                       description="Start a local HTTP server bound to 127.0.0.1 that serves the "
                       "WebGL2 viewer page and TREE (raw .npz or compressed .plnz), and print "
                       "its URL. It serves nothing else.")
    p.add_argument("tree", help="tree file (.npz or .plnz)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default 8000; 0 = any free)")
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    p.add_argument("--max-mb", type=float, default=2048,
                   help="GPU texture budget in MB; larger trees are refused with a hint to "
                   "'plenoctree lod' (default 2048)")
    p.add_argument("--verbose", action="store_true", help="log every request")
    p.add_argument("--data", default=None,
                   help="dataset folder: frame the first view like its cameras and list them "
                   "in the page (jump to any)")
    p.add_argument("--split", default="train", help="dataset split whose cameras (default train)")
    p.set_defaults(func=_run_view)

    p = sub.add_parser("export-web", help="write a static viewer bundle (page + tree)",
                       description="Write the viewer page and TREE into a folder that any static "
                       "web host can serve.")
    p.add_argument("tree", help="tree file (.npz or .plnz)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--title", default=None, help="page title")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bundle")
    p.add_argument("--max-mb", type=float, default=2048,
                   help="GPU texture budget in MB written into the bundle (default 2048)")
    p.add_argument("--data", default=None,
                   help="dataset folder: frame the first view like its cameras and list them "
                   "in the page (jump to any)")
    p.add_argument("--split", default="train", help="dataset split whose cameras (default train)")
    p.set_defaults(func=_run_export)
