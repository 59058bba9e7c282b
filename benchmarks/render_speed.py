"""Octree rendering speed: numba kernel vs its root-descent baseline vs the torch twin.

Method: a fixed set of orbit views (30° elevation, distance 4, the procedural scene's field of
view) is rendered at each resolution with each backend in the same run. Rays are generated
before timing (ray generation is not part of the renderer). Each backend gets a warm-up render
(JIT compile / cache load), then ``--repeats`` timed passes over all views; we report the median
time per frame and the spread (min, max) over passes.

Backends:
- ``numba``: the public :func:`plenoctree.render_rays` with the default kernel (ancestor-stack
  traversal), input checks included.
- ``numba-root``: the same kernel re-descending from the root at every step (the "plain kernel"
  baseline of docs/reference measurements), called directly.
- ``torch``: the torch twin (float32) on a strided subset of the pixels of ``--twin-views`` views
  (it is far slower); its time per frame is extrapolated per ray and marked ``extrapolated``
  (the twin pays a fixed Python overhead per marching step; with few rays that overhead is
  spread thin and the per-ray cost is overstated, so keep ``--twin-rays`` large).

Besides wall-clock time, each entry records the process CPU time per frame (all threads): when
other jobs share the cores, wall time inflates while CPU time stays close to the quiet figure.

Accuracy: max |Δ colour| between numba and the twin on the twin's rays (all views).

Usage::

    .venv/bin/python benchmarks/render_speed.py                 # procedural scene, 256^3 tree
    .venv/bin/python benchmarks/render_speed.py --tree my.npz --sizes 400 --repeats 3

Writes ``benchmarks/results/render_speed.json`` (``--out``) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

import plenoctree
from plenoctree._util import atomic_save_json
from plenoctree.datasets import generate_rays
from plenoctree.datasets.procedural import CAMERA_ANGLE_X, CAMERA_DISTANCE, procedural_cameras
from plenoctree.render import RenderOptions, render_rays
from plenoctree.render.options import parse_data_format

ROOT = Path(__file__).resolve().parent


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

    try:
        layer = numba.threading_layer()
    except ValueError:
        layer = "not initialised"
    return {
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "numba_threads": numba.config.NUMBA_NUM_THREADS,
        "numba_threading_layer": layer,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "numba": numba.__version__,
        "plenoctree": plenoctree.__version__,
        "platform": platform.platform(),
    }


def load_or_build_tree(path: str | None, resolution: int):
    if path:
        from plenoctree.octree.io import load_tree

        return load_tree(path), str(path)
    from plenoctree.datasets.procedural import procedural_tree

    return procedural_tree(resolution), f"procedural_tree({resolution})"


def orbit_views(n_views: int, size: int) -> list[tuple[np.ndarray, np.ndarray]]:
    fx = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    c2ws = procedural_cameras(n_views, "orbit", distance=CAMERA_DISTANCE)
    return [generate_rays(c, fx, fx, size / 2.0, size / 2.0, size, size) for c in c2ws]


def time_passes(fn: Callable[[], Any], repeats: int) -> tuple[list[float], list[float]]:
    """Wall-clock and process CPU seconds (all threads) of ``repeats`` calls of ``fn``."""
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def summarise(per_frame_s: list[float], cpu_per_frame_s: list[float],
              rays_per_frame: int) -> dict[str, Any]:
    med = statistics.median(per_frame_s)
    return {
        "ms_per_frame": 1e3 * med,
        "ms_min": 1e3 * min(per_frame_s),
        "ms_max": 1e3 * max(per_frame_s),
        "fps": 1.0 / med,
        "mrays_per_s": rays_per_frame / med / 1e6,
        # CPU time summed over threads: robust to other processes sharing the cores.
        "cpu_ms_per_frame": 1e3 * statistics.median(cpu_per_frame_s),
        "repeats": len(per_frame_s),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tree", help="a saved tree (.npz); default: the procedural scene")
    ap.add_argument("--resolution", type=int, default=256, help="procedural tree resolution")
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 800], help="image sizes (px)")
    ap.add_argument("--views", type=int, default=4, help="orbit views per pass")
    ap.add_argument("--repeats", type=int, default=5, help="timed passes per backend and size")
    ap.add_argument("--twin-rays", type=int, default=40000,
                    help="rays per view rendered by the torch twin (strided subset)")
    ap.add_argument("--twin-views", type=int, default=2, help="views rendered by the twin")
    ap.add_argument("--stop-thresh", type=float, default=0.01)
    ap.add_argument("--out", default=str(ROOT / "results" / "render_speed.json"))
    args = ap.parse_args(argv)

    load_before = os.getloadavg()
    t0 = time.perf_counter()
    tree, tree_name = load_or_build_tree(args.tree, args.resolution)
    build_s = time.perf_counter() - t0
    info = parse_data_format(tree.data_format, tree.data_dim, tree.extra_data)
    opts = RenderOptions(stop_thresh=args.stop_thresh)
    from plenoctree.render import _numba_impl

    results: dict[str, dict[str, Any]] = {"numba": {}, "numba-root": {}, "torch": {}}
    max_diff: dict[str, float] = {}
    for size in args.sizes:
        views = orbit_views(args.views, size)
        n_px = size * size
        key = str(size)

        def run_numba():
            for o, d in views:
                render_rays(tree, o, d, opts, backend="numba")

        def run_root():
            for o, d in views:
                _numba_impl.render_rays_numba(tree.child, tree.data, tree.offset,
                                              tree.invradius, info, tree.extra_data,
                                              o.reshape(-1, 3), d.reshape(-1, 3), opts,
                                              use_stack=False)

        stride = max(1, n_px // max(1, args.twin_rays))
        subsets = [(o.reshape(-1, 3)[::stride], d.reshape(-1, 3)[::stride])
                   for o, d in views[:max(1, args.twin_views)]]
        n_sub = sum(len(o) for o, _ in subsets)

        def run_twin():
            return [render_rays(tree, o, d, opts, backend="torch").rgb for o, d in subsets]

        for name, fn in (("numba", run_numba), ("numba-root", run_root)):
            fn()                                                    # warm-up
            wall, cpu = time_passes(fn, args.repeats)
            results[name][key] = summarise([p / len(views) for p in wall],
                                           [p / len(views) for p in cpu], n_px)
        twin_rgb = run_twin()                                       # warm-up
        wall, cpu = time_passes(run_twin, max(1, min(args.repeats, 3)))
        results["torch"][key] = summarise([p / n_sub * n_px for p in wall],
                                          [p / n_sub * n_px for p in cpu], n_px)
        results["torch"][key].update(extrapolated=True, rays_timed=n_sub)
        diffs = [float((render_rays(tree, o, d, opts, backend="numba").rgb - ref).abs().max())
                 for (o, d), ref in zip(subsets, twin_rgb)]
        max_diff[key] = max(diffs)
        print(f"[{size}x{size}] numba {results['numba'][key]['ms_per_frame']:.1f} ms, "
              f"root {results['numba-root'][key]['ms_per_frame']:.1f} ms, "
              f"twin {results['torch'][key]['ms_per_frame']:.0f} ms (extrapolated)",
              file=sys.stderr)

    speedup = {k: results["torch"][k]["ms_per_frame"] / results["numba"][k]["ms_per_frame"]
               for k in results["numba"]}
    speedup_root = {k: results["numba-root"][k]["ms_per_frame"]
                    / results["numba"][k]["ms_per_frame"] for k in results["numba"]}
    report = {
        "benchmark": "render_speed",
        "tree": {"source": tree_name, "data_format": tree.data_format,
                 "n_nodes": tree.n_nodes, "n_leaves": tree.n_leaves,
                 "depth_limit": tree.depth_limit, "data_mb": tree.data.nbytes / 2**20,
                 "build_s": build_s},
        "views": args.views, "sizes": args.sizes, "repeats": args.repeats,
        "options": {"stop_thresh": opts.stop_thresh, "background": list(opts.background)},
        "results": results,
        "speedup_numba_over_torch": speedup,
        "speedup_stack_over_root_descent": speedup_root,
        "max_abs_diff_rgb_numba_vs_torch": max_diff,
        "machine": {**machine_info(), "loadavg_before": load_before,
                    "loadavg_after": os.getloadavg()},
    }
    atomic_save_json(args.out, report)

    print(f"\nOctree render speed — {tree_name}, {tree.data_format}, {tree.n_leaves} leaves, "
          f"{args.views} orbit views, stop_thresh {opts.stop_thresh}\n")
    print("| backend | size | ms/frame (median) | spread (min–max) | FPS | M rays/s "
          "| CPU ms/frame |")
    print("|---|---|---|---|---|---|---|")
    for name, per_size in results.items():
        for k, r in per_size.items():
            note = " (extrapolated)" if r.get("extrapolated") else ""
            print(f"| {name}{note} | {k}² | {r['ms_per_frame']:.1f} | {r['ms_min']:.1f}–"
                  f"{r['ms_max']:.1f} | {r['fps']:.2f} | {r['mrays_per_s']:.2f} | "
                  f"{r['cpu_ms_per_frame']:.1f} |")
    print()
    for k in speedup:
        print(f"{k}²: numba is {speedup[k]:.0f}x the torch twin, {speedup_root[k]:.2f}x the "
              f"root-descent kernel; max |Δ rgb| numba vs twin = {max_diff[k]:.2e}")
    m = report["machine"]
    print(f"\nmachine: {m['cpu_model']}, {m['cpu_count']} cores, numba {m['numba']} "
          f"({m['numba_threading_layer']}, {m['numba_threads']} threads), torch {m['torch']}; "
          f"load average before {load_before[0]:.2f}, after {m['loadavg_after'][0]:.2f}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
