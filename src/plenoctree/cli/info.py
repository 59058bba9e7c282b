"""``plenoctree info [TREE]``: version, compute backends, threads and GPU; or what a tree file
holds (format, size, depth, box, NDC space, the dataset it was made from)."""

from __future__ import annotations

import argparse
import os
import platform


def collect_info() -> dict:
    """Return a dict describing the installation: versions, backends, threads, GPU."""
    import numpy
    import torch

    from .. import __version__
    from ..render import available_backends

    import numba

    numba_version, numba_threads = numba.__version__, numba.config.NUMBA_NUM_THREADS
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "plenoctree": __version__,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "torch": torch.__version__,
        "numba": numba_version,
        "backends": available_backends(),
        "cpu_cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "numba_threads": numba_threads,
        "gpu": gpu,
    }


def tree_info(path: str) -> dict:
    """What the tree file ``path`` holds (any format :func:`load_any_tree` reads)."""
    from pathlib import Path

    from ..compress import is_compressed_file, load_any_tree
    from ._provenance import dataset_of

    tree = load_any_tree(path)
    found = dataset_of(path)
    bbox = tree.bbox.tolist()
    return {
        "file": str(path),
        "file_mb": round(Path(path).stat().st_size / 2**20, 3),
        "compressed": bool(is_compressed_file(path)),
        "data_format": tree.data_format,
        "sh_degree": tree.sh_degree,
        "basis_dim": int(tree.basis_dim),
        "n_nodes": int(tree.n_nodes),
        "n_leaves": int(tree.n_leaves),
        "max_depth": int(tree.max_depth),
        "bbox_min": [round(v, 6) for v in bbox[0]],
        "bbox_max": [round(v, 6) for v in bbox[1]],
        "memory_mb": round(tree.nbytes / 2**20, 3),
        "ndc": tree.ndc.to_json() if tree.ndc is not None else None,
        "dataset": found[0] if found else None,
    }


def _run(args: argparse.Namespace) -> int:
    from ._output import check_json

    check_json(args)
    info = tree_info(args.tree) if args.tree else collect_info()
    if args.json:
        from ._output import write_json

        write_json(args.json, info)
    else:
        width = max(len(k) for k in info)
        for key, value in info.items():
            if isinstance(value, list):
                value = ", ".join(str(v) for v in value)
            elif isinstance(value, dict):
                value = ", ".join(f"{k} {v:g}" for k, v in value.items())
            if key == "ndc":
                value = ("forward-facing, NDC of the reference camera: " + value
                         if value else "no (world-space tree)")
            print(f"{key:<{width}}  {value if value is not None else 'none'}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``info`` command."""
    from ._output import add_json, add_overwrite

    p = sub.add_parser("info", help="print version, backends, threads and GPU; or a tree's "
                                    "format, size, depth and box")
    p.add_argument("tree", nargs="?", default=None,
                   help="a tree file (.npz native/svox, .plnz): describe it instead")
    add_json(p, "the information")
    add_overwrite(p)
    p.set_defaults(func=_run)
