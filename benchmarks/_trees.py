"""Trees and machine facts shared by the speed benchmarks (``render_speed``, ``finetune_speed``).

``--tree`` accepts ``lego`` (the real tree: the default extraction of the trained NeRF-SH
``shared/data/runs/lego_cpu_400``, made once into the ignored cache folder
``benchmarks/results/cache/``), ``procedural`` (the analytic scene's tree), ``ff`` (the
forward-facing NDC scene's RGBA tree) or a path to a saved tree. The default is ``lego`` when
the run directory is found beside the repository, else ``procedural``.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent
CACHE = ROOT / "results" / "cache"


def find_lego_run() -> Path | None:
    """``shared/data/runs/lego_cpu_400`` in a folder above the repository, or None."""
    for up in ROOT.parents:
        run = up / "shared" / "data" / "runs" / "lego_cpu_400"
        if (run / "checkpoint.pt").is_file():
            return run
    return None


def default_tree_name() -> str:
    return "lego" if find_lego_run() is not None else "procedural"


def _lego_tree(log: Any) -> tuple[Any, dict]:
    from plenoctree.octree import load_tree

    run = find_lego_run()
    if run is None:
        raise SystemExit("--tree lego: shared/data/runs/lego_cpu_400 not found above "
                         f"{ROOT.parent}")
    path = CACHE / "lego_cpu_400_256.npz"
    if not path.exists():
        from plenoctree.convert import ExtractConfig, extract

        log(f"extracting the lego tree once into {path} (default options, ~1-3 min)")
        CACHE.mkdir(parents=True, exist_ok=True)
        extract(ExtractConfig(run_dir=str(run), out=str(path), eval=False))
    return load_tree(path), {"kind": "lego", "source": str(path), "run": str(run)}


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
                    log: Any = print, data: str | None = None) -> tuple[Any, dict]:
    """``(tree, description)`` for ``--tree`` (see the module docstring).

    ``data``: the tree's dataset (``--data``): ``description["data"]`` then names it, and the
    benchmarks take their views from its cameras instead of orbit views (the ``ff`` tree names
    its own). A forward-facing (NDC) tree file without ``data`` is refused: orbit views mean
    nothing in NDC space."""
    name = name or default_tree_name()
    t0 = time.perf_counter()
    if name == "lego":
        tree, desc = _lego_tree(log)
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


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    import numba
    import torch

    import plenoctree

    try:
        layer = numba.threading_layer()
    except ValueError:
        layer = "not initialised"
    return {
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": layer,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "numba": numba.__version__,
        "plenoctree": plenoctree.__version__,
        "platform": platform.platform(),
        "loadavg": list(os.getloadavg()),
    }
