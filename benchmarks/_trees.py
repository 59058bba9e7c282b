"""Trees and views shared by the speed benchmarks (``render_speed``, ``finetune_speed``, ...).

``--tree`` accepts ``lego`` (the real tree: the default extraction of the trained NeRF-SH
``runs/lego_cpu_400`` of the data root (:func:`_bench.data_root`), made once into the ignored
cache folder ``benchmarks/results/cache/``), ``procedural`` (the analytic scene's tree),
``ff`` (the forward-facing NDC scene's RGBA tree) or a path to a saved tree. The default is
``lego`` when that run is found, else ``procedural``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from _bench import CACHE, add_data_root, data_root

LEGO_RUN = ("runs", "lego_cpu_400")
LEGO_TREE = CACHE / "lego_cpu_400_256.npz"
"""The lego tree ``--tree lego`` extracts once (default options, grid 256)."""


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr)


def find_lego_run(root: str | None = None) -> Path | None:
    """``runs/lego_cpu_400`` of the data root (``root``: ``--data-root``), or None."""
    base = data_root(root)
    run = None if base is None else base.joinpath(*LEGO_RUN)
    return run if run is not None and (run / "checkpoint.pt").is_file() else None


def default_tree_name(root: str | None = None) -> str:
    """``lego`` when its run is found, else ``procedural``."""
    return "lego" if find_lego_run(root) is not None else "procedural"


def _lego_tree(log: Callable[[str], None], root: str | None) -> tuple[Any, dict]:
    from plenoctree.octree import load_tree

    run = find_lego_run(root)
    if run is None:
        raise SystemExit(f"--tree lego: {'/'.join(LEGO_RUN)} not found in the data root "
                         "(--data-root / $PLENOCTREE_DATA)")
    if not LEGO_TREE.exists():
        from plenoctree.convert import ExtractConfig, extract

        log(f"extracting the lego tree once into {LEGO_TREE} (default options, ~1-3 min)")
        CACHE.mkdir(parents=True, exist_ok=True)
        extract(ExtractConfig(run_dir=str(run), out=str(LEGO_TREE), eval=False))
    return load_tree(LEGO_TREE), {"kind": "lego", "source": str(LEGO_TREE), "run": str(run)}


def _ff_tree(resolution: int) -> tuple[Any, dict]:
    from plenoctree.datasets.forward_facing import (forward_facing_tree,
                                                    write_forward_facing_dataset)

    root = CACHE / "forward_facing_504x378"
    if not (root / "poses_bounds.npy").exists():   # images only serve as a dataset: few samples
        write_forward_facing_dataset(root, n_images=8, width=504, height=378, n_samples=32)
    return forward_facing_tree(root, resolution), {
        "kind": "forward_facing", "source": f"forward_facing_tree({resolution})",
        "data": str(root)}


def load_bench_tree(name: str | None, resolution: int = 256,
                    log: Callable[[str], None] = _stderr, data: str | None = None,
                    root: str | None = None) -> tuple[Any, dict]:
    """``(tree, description)`` for ``--tree`` (see the module docstring).

    ``data``: the tree's dataset (``--data``): ``description["data"]`` then names it, and the
    benchmarks take their views from its cameras instead of orbit views (the ``ff`` tree names
    its own). A forward-facing (NDC) tree file without ``data`` is refused: orbit views mean
    nothing in NDC space. ``root``: the data root (``--data-root``) where ``lego`` is found."""
    name = name or default_tree_name(root)
    t0 = time.perf_counter()
    if name == "lego":
        tree, desc = _lego_tree(log, root)
    elif name == "procedural":
        from plenoctree.datasets.procedural import procedural_tree

        tree, desc = procedural_tree(resolution), {
            "kind": "procedural", "source": f"procedural_tree({resolution})"}
    elif name == "ff":
        tree, desc = _ff_tree(resolution)
    else:
        from plenoctree.octree import load_tree

        tree, desc = load_tree(name), {"kind": "file", "source": str(name)}
    if data:
        desc["data"] = str(data)
    elif getattr(tree, "ndc", None) is not None and not desc.get("data"):
        raise SystemExit(f"{desc['source']}: a forward-facing (NDC) tree; pass --data DIR (its "
                         "capture) to time it from its own cameras, not from orbit views")
    desc.update(data_format=tree.data_format, n_nodes=int(tree.n_nodes),
                n_leaves=int(tree.n_leaves), max_depth=int(tree.max_depth),
                data_mb=tree.data.nbytes / 2**20, load_s=time.perf_counter() - t0)
    return tree, desc


def add_tree_args(ap: argparse.ArgumentParser, data_help: str, name: str) -> None:
    """The options of a speed benchmark on a tree (``name``): ``--tree``, ``--resolution``,
    ``--data`` (``data_help``: what the benchmark does with it) and ``--data-root``, which
    :func:`tree_from_args` reads, the renderer's ``--stop-thresh`` and ``--out`` (default
    ``benchmarks/results/<name>_<tree kind>.json``)."""
    ap.add_argument("--tree", default=None,
                    help="lego | procedural | ff | PATH.npz (default: lego when found)")
    ap.add_argument("--resolution", type=int, default=256, help="procedural/ff tree resolution")
    ap.add_argument("--data", default=None, help=data_help)
    add_data_root(ap)
    ap.add_argument("--stop-thresh", type=float, default=0.01,
                    help="the renderer's early stop (transmittance)")
    ap.add_argument("--out", default=None,
                    help=f"JSON (default benchmarks/results/{name}_<tree kind>.json)")


def tree_from_args(args: argparse.Namespace) -> tuple[Any, dict]:
    """:func:`load_bench_tree` of the options of :func:`add_tree_args`."""
    return load_bench_tree(args.tree, args.resolution, data=args.data, root=args.data_root)


def orbit_cameras(n_views: int, size: int) -> Any:
    """``n_views`` cameras (``size``² pixels) on a 30° orbit at distance 4 (NeRF-synthetic
    field of view), as ``plenoctree.datasets.Cameras``."""
    from plenoctree.datasets import Cameras
    from plenoctree.datasets.procedural import CAMERA_ANGLE_X, CAMERA_DISTANCE, look_at

    fx = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    el = math.radians(30.0)
    c2w = []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        eye = CAMERA_DISTANCE * np.array([math.cos(el) * math.cos(a), math.cos(el) * math.sin(a),
                                          math.sin(el)])
        c2w.append(look_at(eye, np.zeros(3)))
    return Cameras(np.stack(c2w), fx, fx, size / 2.0, size / 2.0, size, size)


def data_cameras(root: str, n_views: int, split: str = "test") -> tuple[Any, list[int]]:
    """The ``split`` cameras of the dataset at ``root`` (any format; NDC ones for a
    forward-facing capture) and up to ``n_views`` indices evenly spread over them: a tree timed
    from the views it was made for, at the images' full size, or at the size of the first
    pre-downscaled folder when there is no full-size one (LLFF's flower: images_8/, 504x378)."""
    from plenoctree.datasets import load_dataset
    from plenoctree.errors import DatasetError

    try:
        cams = load_dataset(root, split=split).cameras
    except DatasetError:
        from plenoctree.datasets import load_cameras

        cams = load_cameras(root, split=split).cameras
    idx = np.linspace(0, len(cams) - 1, min(n_views, len(cams))).round().astype(int)
    return cams, sorted({int(i) for i in idx})
