"""Octree build / check / query speed on sphere-shell masks (the shape of real extractions).

Usage: ``python benchmarks/bench_octree_build.py [--res 256 512] [--out PATH.json]``

For each resolution: a mask of two thick sphere shells (about 2.3M occupied cells at 512³),
``Octree.from_grid`` with sparse values ``[M, 4]``, ``check_integrity`` and ``query`` of 1M
random points. Baseline measured in the same run: one ``np.flatnonzero`` pass over the mask,
the least work any builder must do. Median of ``--repeat`` runs after one warm-up; peak
Python-heap allocation of the build from ``tracemalloc``. Prints a table, writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
import tracemalloc
from pathlib import Path

import numpy as np

from plenoctree import Octree


def shell_mask(res: int) -> np.ndarray:
    g = ((np.arange(res) + 0.5) / res * 2 - 1).astype(np.float32)
    x, y, z = np.meshgrid(g, g, g, indexing="ij", sparse=True)
    r = np.sqrt(x * x + y * y + z * z)
    return (np.abs(r - 0.6) < 0.012) | (np.abs(r - 0.3) < 0.012)


def timed(fn, repeat: int) -> tuple[float, float, object]:
    out = fn()                                      # warm-up
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), (max(times) - min(times)) / 2, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results/octree_build.json")
    args = ap.parse_args()
    rows = []
    for res in args.res:
        mask = shell_mask(res)
        m = int(mask.sum())
        values = np.ones((m, 4), np.float32)
        base, base_sp, _ = timed(lambda: np.flatnonzero(mask), args.repeat)
        build, build_sp, tree = timed(lambda: Octree.from_grid(values, mask, 0, 1, "RGBA"),
                                      args.repeat)
        tracemalloc.start()
        Octree.from_grid(values, mask, 0, 1, "RGBA")
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        check, _, _ = timed(tree.check_integrity, args.repeat)
        pts = np.random.default_rng(0).uniform(-1, 1, (1_000_000, 3))
        query, _, _ = timed(lambda: tree.query(pts), args.repeat)
        rows.append(dict(res=res, occupied=m, n_nodes=tree.n_nodes, n_leaves=tree.n_leaves,
                         baseline_flatnonzero_s=base, build_s=build, build_spread_s=build_sp,
                         build_peak_alloc_mib=peak / 2 ** 20, tree_mib=tree.nbytes / 2 ** 20,
                         check_s=check, query_1m_s=query))
    print(f"{'res':>5} {'occupied':>9} {'nodes':>8} {'baseline s':>10} {'build s':>8} "
          f"{'peak MiB':>8} {'check s':>7} {'query 1M s':>10}")
    for r in rows:
        print(f"{r['res']:>5} {r['occupied']:>9} {r['n_nodes']:>8} "
              f"{r['baseline_flatnonzero_s']:>10.3f} {r['build_s']:>8.3f} "
              f"{r['build_peak_alloc_mib']:>8.0f} {r['check_s']:>7.3f} {r['query_1m_s']:>10.3f}")
    machine = dict(cpus=os.cpu_count(), platform=platform.platform(), numpy=np.__version__,
                   python=platform.python_version())
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(machine=machine, rows=rows), indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
