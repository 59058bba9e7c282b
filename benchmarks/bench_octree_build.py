"""Octree build / check / query speed on sphere-shell masks (the shape of real extractions).

Usage: ``python benchmarks/bench_octree_build.py [--res 256 512] [--points 1000000]
[--out PATH.json]``

For each resolution: a mask of two thick sphere shells (about 2.3M occupied cells at 512³),
``Octree.from_grid`` with sparse values ``[M, 4]``, ``check_integrity`` and ``query`` of
``--points`` random points. Baseline measured in the same run: one ``np.flatnonzero`` pass over
the mask, the least work any builder must do. Median and half-spread of ``--repeat`` runs after
one warm-up; peak Python-heap allocation of the build from ``tracemalloc``. Prints a table,
writes JSON (``benchmarks/results/octree_build.json``).
"""

from __future__ import annotations

import argparse
import sys
import tracemalloc

import numpy as np

from _bench import add_out, machine_info, markdown_table, timed, write_json


def shell_mask(res: int) -> np.ndarray:
    """``[res, res, res]`` bool: two sphere shells (radii 0.3 and 0.6, 0.024 thick) in [-1, 1]³."""
    g = ((np.arange(res) + 0.5) / res * 2 - 1).astype(np.float32)
    x, y, z = np.meshgrid(g, g, g, indexing="ij", sparse=True)
    r = np.sqrt(x * x + y * y + z * z)
    return (np.abs(r - 0.6) < 0.012) | (np.abs(r - 0.3) < 0.012)


def measure(res: int, repeat: int, n_points: int) -> dict:
    """The row of one resolution."""
    from plenoctree import Octree

    mask = shell_mask(res)
    m = int(mask.sum())
    values = np.ones((m, 4), np.float32)
    base = timed(lambda: np.flatnonzero(mask), repeat)
    build = timed(lambda: Octree.from_grid(values, mask, 0, 1, "RGBA"), repeat)
    tree = build.result
    tracemalloc.start()
    Octree.from_grid(values, mask, 0, 1, "RGBA")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    check = timed(tree.check_integrity, repeat)
    pts = np.random.default_rng(0).uniform(-1, 1, (n_points, 3))
    query = timed(lambda: tree.query(pts), repeat)
    return dict(res=res, occupied=m, n_nodes=tree.n_nodes, n_leaves=tree.n_leaves,
                baseline_flatnonzero_s=base.median, build_s=build.median,
                build_spread_s=build.spread, build_peak_alloc_mib=peak / 2 ** 20,
                tree_mib=tree.nbytes / 2 ** 20, check_s=check.median, query_s=query.median,
                query_points=n_points)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--points", type=int, default=1_000_000, help="query points")
    add_out(ap, "octree_build.json")
    args = ap.parse_args(argv)
    rows = [measure(res, args.repeat, args.points) for res in args.res]
    print(markdown_table(
        ["res", "occupied", "nodes", "baseline s", "build s", "± s", "peak MiB", "check s",
         f"query {args.points:,} s"],
        [[r["res"], r["occupied"], r["n_nodes"], f"{r['baseline_flatnonzero_s']:.3f}",
          f"{r['build_s']:.3f}", f"{r['build_spread_s']:.3f}",
          f"{r['build_peak_alloc_mib']:.0f}", f"{r['check_s']:.3f}", f"{r['query_s']:.3f}"]
         for r in rows]))
    out = write_json(args.out, {"benchmark": "octree_build", "machine": machine_info(),
                                "rows": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
