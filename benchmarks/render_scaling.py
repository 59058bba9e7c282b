"""How the numba renderer scales with threads: per-thread balance counted from the real march,
and measured frames per second for 1, 2, 4, ... threads where the machine has the cores.

Balance (no timing, any machine): the per-ray segment counts of the render march
(:func:`plenoctree.render._render_numba.ray_stats_numba`, with the prepared tree's empty-space
skip tables, as ``render_image`` marches it) are summed per image tile
(:data:`~plenoctree.render._render_numba.TILE_2D`) and the tiles given to ``T`` threads as each
schedule does (``_balance.py``: numba's static ``prange`` with the kernel's former
``set_parallel_chunksize(4)``, an interleaved static order, and the shared-counter dynamic
schedule the kernel uses now). ``balance = mean / max`` per-thread work, averaged over the views
(the worst view in the JSON); ``T × balance`` bounds the speed-up over one thread. The same for
a fine-tuning batch (random ``4×4`` pixel tiles of these views, shuffled, in the fine-tuning
kernel's tiles of 64 rays, ``set_parallel_chunksize(2)``).

FPS: ``render_image`` of the orbit views, one fresh process per thread count
(``NUMBA_NUM_THREADS`` is read when numba loads): a warm-up render, then ``--repeats`` passes
over the views; the median time per frame. Counts above the machine's cores are not measured.

Old code against new (the FPS; the counts are the same on both sides)::

    python benchmarks/ab.py --rev main --same-script -- render_scaling.py --threads 1 2

Usage::

    .venv/bin/python benchmarks/render_scaling.py                 # lego, 400² and 800²
    .venv/bin/python benchmarks/render_scaling.py --threads 1 2 4 8 16   # on a 16-core machine

Writes ``benchmarks/results/render_scaling_<tree>.json`` (``--out``) and prints markdown tables.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

import numpy as np

from _balance import balance, per_thread_work, tile_costs
from _bench import (RESULTS, child_json, machine_info, machine_line, markdown_table, timed,
                    write_json)
from _trees import add_tree_args, orbit_cameras, tree_from_args

#: ``(label, schedule, chunksize)`` of the render kernel's balance table; "static" is the
#: kernel before this benchmark (``set_parallel_chunksize(4)``: still static under omp).
RENDER_SCHEDULES = (("static (before)", "static", 4), ("interleaved", "cyclic", 0),
                    ("dynamic (now)", "dynamic", 0))
#: The fine-tuning kernel's schedule: its ``set_parallel_chunksize(2)``, static under omp.
FINETUNE = {"tile_rays": 64, "pixel_tile": 4, "batch_rays": 1 << 16, "chunksize": 2}


def view_counts(tree: Any, fast: Any, size: int, n_views: int, opts: Any) -> list[np.ndarray]:
    """Segments marched per ray, ``[size, size]`` int64 per orbit view."""
    from plenoctree.render._render_numba import STAT_NAMES, ray_stats_numba

    cams = orbit_cameras(n_views, size)
    col = STAT_NAMES.index("leaves")
    out = []
    for i in range(n_views):
        o, d = cams.rays(i)
        s = ray_stats_numba(tree, o.reshape(-1, 3), d.reshape(-1, 3), opts,
                            skip=fast.empty_skip)
        out.append(s[:, col].reshape(size, size))
    return out


def balance_rows(costs: list[np.ndarray], threads: list[int],
                 schedules: tuple) -> dict[str, dict[str, dict[str, float]]]:
    """``{label: {T: {"mean": .., "worst": ..}}}``: balance over the views' tile costs."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for label, schedule, chunk in schedules:
        out[label] = {}
        for t in threads:
            b = [balance(per_thread_work(c, t, schedule, chunk)) for c in costs]
            out[label][str(t)] = {"mean": float(np.mean(b)), "worst": float(np.min(b))}
    return out


def finetune_batches(maps: list[np.ndarray], n_batches: int, seed: int = 0) -> list[np.ndarray]:
    """Cost per fine-tuning kernel tile of ``n_batches`` batches: random ``4×4`` pixel tiles of
    the count maps, shuffled as the fine-tuning loop draws them, grouped in 64-ray tiles."""
    rng = np.random.default_rng(seed)
    k = FINETUNE["pixel_tile"]
    per_tile = np.concatenate([m[:m.shape[0] // k * k, :m.shape[1] // k * k]
                               .reshape(m.shape[0] // k, k, m.shape[1] // k, k)
                               .sum(axis=(1, 3)).reshape(-1) for m in maps])
    n_tiles = FINETUNE["batch_rays"] // (k * k)
    per_kernel_tile = FINETUNE["tile_rays"] // (k * k)
    return [rng.choice(per_tile, n_tiles).reshape(-1, per_kernel_tile).sum(axis=1).astype(float)
            for _ in range(n_batches)]


def count_balance(tree: Any, fast: Any, args: argparse.Namespace) -> dict[str, Any]:
    """The balance tables of every size (render) and of fine-tuning batches of all sizes."""
    from plenoctree.render import RenderOptions
    from plenoctree.render._render_numba import TILE_2D

    opts = RenderOptions(stop_thresh=args.stop_thresh)
    render, maps, summary = {}, [], {}
    for size in args.sizes:
        counts = view_counts(tree, fast, size, args.views, opts)
        maps += counts
        costs = [tile_costs(c, TILE_2D) for c in counts]
        render[f"{size}x{size}"] = balance_rows(costs, args.count_threads, RENDER_SCHEDULES)
        summary[f"{size}x{size}"] = {
            "tiles": int(costs[0].size), "segments_per_frame": float(np.mean([c.sum()
                                                                              for c in counts])),
            "empty_tile_fraction": float(np.mean([(c == 0).mean() for c in costs]))}
    fine = balance_rows(finetune_batches(maps, args.views), args.count_threads,
                        (("static (now)", "static", FINETUNE["chunksize"]),
                         ("dynamic", "dynamic", 0)))
    return {"render": render, "finetune_batch": fine, "frames": summary,
            "finetune_settings": FINETUNE}


def child_fps(args: argparse.Namespace) -> dict[str, Any]:
    """(In the child process.) ``render_image`` FPS per size at this process's thread count."""
    import numba

    from plenoctree.render import RenderOptions, render_image, tree_to_device

    tree, _ = tree_from_args(args)
    fast = tree_to_device(tree, "cpu")
    opts = RenderOptions(stop_thresh=args.stop_thresh)
    out: dict[str, Any] = {"threads": numba.get_num_threads()}
    for size in args.sizes:
        cams = orbit_cameras(args.views, size)

        def one_pass(cams=cams):
            for i in range(args.views):
                render_image(fast, cams, i, opts, backend="numba")

        t = timed(one_pass, args.repeats).scaled(1 / args.views)
        out[f"{size}x{size}"] = {"fps": 1.0 / t.median, **t.summary()}
    out["threading_layer"] = numba.threading_layer()
    return out


def measure_fps(args: argparse.Namespace, argv: list[str]) -> dict[str, Any]:
    """FPS per thread count, one fresh process each (skipped above the usable cores)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    fps: dict[str, Any] = {}
    for t in args.threads:
        if t > (cores or 1):
            fps[str(t)] = None
            continue
        print(f"measuring {t} thread(s) ...", file=sys.stderr)
        fps[str(t)] = child_json([__file__, *argv, "--child-fps"], {"NUMBA_NUM_THREADS": str(t)})
    return fps


def print_report(report: dict) -> None:
    """The markdown tables of a report."""
    bal, threads = report["balance"], report["count_threads"]
    print(f"\nPer-thread balance (mean / max work, mean over {report['views']} orbit views; "
          f"T × balance bounds the speed-up) — {report['tree']['source']}\n")
    rows = [[size, label, *(f"{per[str(t)]['mean']:.2f}" for t in threads)]
            for size, table in bal["render"].items() for label, per in table.items()]
    rows += [["fine-tuning batch", label, *(f"{per[str(t)]['mean']:.2f}" for t in threads)]
             for label, per in bal["finetune_batch"].items()]
    print(markdown_table(["image", "schedule", *(f"T={t}" for t in threads)], rows))
    fps = report["fps"]
    rows = []
    for t, r in fps.items():
        for size in report["sets"]:
            if r is None:
                rows.append([t, size, "not measured (fewer cores)", "–", "–"])
                continue
            one = fps.get("1")
            speedup = r[size]["fps"] / one[size]["fps"] if one else None
            rows.append([t, size, f"{r[size]['fps']:.2f}",
                         f"{r[size]['ms_min']:.1f}–{r[size]['ms_max']:.1f}",
                         "–" if speedup is None else f"{speedup:.2f}x"])
    print()
    print(markdown_table(["threads", "size", "FPS (median)", "ms/frame min–max", "vs 1 thread"],
                         rows))
    print("\n" + machine_line(report["machine"]))


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_tree_args(ap, "unused (orbit views only)", "render_scaling")
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 800], help="image sizes (px)")
    ap.add_argument("--views", type=int, default=4, help="orbit views")
    ap.add_argument("--repeats", type=int, default=5, help="timed passes per thread count")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2, 4, 8, 16],
                    help="thread counts to time (those above the machine's cores are skipped)")
    ap.add_argument("--count-threads", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32],
                    help="thread counts of the balance tables")
    ap.add_argument("--child-fps", action="store_true", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    if args.child_fps:
        print(json.dumps(child_fps(args)))
        return 0
    from plenoctree.render import tree_to_device

    load_before = os.getloadavg()
    tree, desc = tree_from_args(args)
    counts = count_balance(tree, tree_to_device(tree, "cpu"), args)
    report = {"benchmark": "render_scaling", "tree": desc, "views": args.views,
              "sets": [f"{s}x{s}" for s in args.sizes], "repeats": args.repeats,
              "count_threads": args.count_threads, "balance": counts,
              "fps": measure_fps(args, argv), "machine": machine_info(load_before)}
    out = write_json(args.out or RESULTS / f"render_scaling_{desc['kind']}.json", report)
    print_report(report)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
