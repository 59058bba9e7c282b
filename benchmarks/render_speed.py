"""Octree rendering speed on a real tree: today's numba kernel vs the frozen baseline kernel,
where a ray's time goes, and the torch twin for accuracy.

Method: a fixed set of orbit views (30° elevation, distance 4, the NeRF-synthetic field of view;
for the forward-facing tree, the LLFF capture's own NDC cameras at 504×378) is rendered at each
size by each path in the same run. Each path gets a warm-up render (JIT compile / cache load),
then ``--repeats`` timed passes over all views, interleaved; we report the median time per
frame, the spread (min, max) over passes and the process CPU time per frame (all threads:
robust to other jobs sharing the cores).

Paths:
- ``numba``: the public :func:`plenoctree.render_image` (camera in, image out: the kernel makes
  each pixel's ray itself) on the tree prepared by ``tree_to_device(tree, "cpu")`` (float32
  arrays and the empty-space skip tables, :mod:`plenoctree.render.empty_skip`) — what
  ``eval``/``video`` get;
- ``noskip``: the same on the plain tree (no skip tables): ``noskip / numba`` is what
  empty-space skipping buys;
- ``rays``: the public :func:`plenoctree.render_rays` on ray arrays made before timing (input
  checks + kernel: the API for arbitrary rays);
- ``kernel``: the same kernel called with prepared ray arrays (so ``rays - kernel`` is the time
  per frame spent outside the kernel by the ray API);
- ``baseline``: a frame as it was before issue 12 (``cameras.rays`` in numpy + the frozen kernel
  ``benchmarks/baseline/render_kernel.py``): the ratio ``baseline / numba`` is the speed-up;
- ``torch``: the twin (float32) on a strided subset of ``--twin-views`` views, per-ray time
  extrapolated; it gives max |Δ rgb| against ``numba`` and ``rays`` (the spec: ≤ 1e-4).

The time numpy takes to make the ray arrays of a frame (``cameras.rays``) is reported as
``raygen ms``.

Per-ray counters (the same march, :func:`plenoctree.render._render_numba.ray_stats_numba`):
leaves visited, σ > 0 leaves, σ > 0 segments of negligible weight (< 1e-4), ``child`` reads of
the descents, share of rays hitting the box and stopping early — so the distance to a frame
rate goal is explained by numbers.

Usage (each ≤ 2-3 min on 2 loaded cores)::

    .venv/bin/python benchmarks/render_speed.py                  # lego when ../shared is there
    .venv/bin/python benchmarks/render_speed.py --tree procedural
    .venv/bin/python benchmarks/render_speed.py --tree ff        # forward-facing NDC, 504x378
    .venv/bin/python benchmarks/render_speed.py --tree my.npz --sizes 400
    .venv/bin/python benchmarks/render_speed.py --tree out/ff/tree_ft.npz --data DIR  # its views

Writes ``benchmarks/results/render_speed_<tree>.json`` (``--out``) and prints markdown tables.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from _trees import ROOT, load_bench_tree, machine_info


def orbit_cameras(n_views: int, size: int) -> Any:
    """``n_views`` cameras on a 30° orbit at distance 4 (NeRF-synthetic field of view)."""
    from plenoctree.datasets import Cameras
    from plenoctree.datasets.procedural import CAMERA_ANGLE_X, CAMERA_DISTANCE, look_at

    fx = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    c2w = []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        el = math.radians(30.0)
        eye = CAMERA_DISTANCE * np.array([math.cos(el) * math.cos(a), math.cos(el) * math.sin(a),
                                          math.sin(el)])
        c2w.append(look_at(eye, np.zeros(3)))
    return Cameras(np.stack(c2w), fx, fx, size / 2.0, size / 2.0, size, size)


def data_cameras(root: str, n_views: int, split: str = "test") -> tuple[Any, list[int]]:
    """The ``split`` cameras of the dataset at ``root`` (any format; NDC ones for a
    forward-facing capture) and up to ``n_views`` indices evenly spread over them: a tree timed
    from the views it was made for."""
    from plenoctree.datasets import load_dataset

    cams = load_dataset(root, split=split).cameras
    idx = np.linspace(0, len(cams) - 1, min(n_views, len(cams))).round().astype(int)
    return cams, sorted({int(i) for i in idx})


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
    return {"ms_per_frame": 1e3 * med, "ms_min": 1e3 * min(per_frame_s),
            "ms_max": 1e3 * max(per_frame_s), "fps": 1.0 / med,
            "mrays_per_s": rays_per_frame / med / 1e6,
            "cpu_ms_per_frame": 1e3 * statistics.median(cpu_per_frame_s),
            "repeats": len(per_frame_s)}


def ray_counters(tree: Any, views: list, opts: Any, skip: Any = None) -> dict[str, float]:
    """Per-ray counters of the render march over ``views`` (``skip``: with these empty-space
    skip tables, as the renderer marches a prepared tree)."""
    from plenoctree.render._render_numba import STAT_NAMES, ray_stats_numba

    s = np.concatenate([ray_stats_numba(tree, o.reshape(-1, 3), d.reshape(-1, 3), opts,
                                        skip=skip)
                        for o, d in views])
    col = {n: s[:, k] for k, n in enumerate(STAT_NAMES)}
    hit = col["hit"] > 0
    n_hit = max(1, int(hit.sum()))
    per_hit = {f"{n}_per_hit_ray": float(col[n][hit].sum() / n_hit)
               for n in ("leaves", "sigma_leaves", "negligible", "descent")}
    return {"rays": int(len(s)), "hit_fraction": float(hit.mean()),
            "stopped_fraction_of_hit": float(col["stopped"][hit].sum() / n_hit),
            **{f"{n}_per_ray": float(col[n].mean())
               for n in ("leaves", "sigma_leaves", "negligible", "descent")}, **per_hit}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tree", default=None,
                    help="lego | procedural | ff | PATH.npz (default: lego when found)")
    ap.add_argument("--resolution", type=int, default=256, help="procedural/ff tree resolution")
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 800],
                    help="image sizes (px; orbit views)")
    ap.add_argument("--views", type=int, default=4, help="views per pass")
    ap.add_argument("--data", default=None,
                    help="dataset of the tree: time its test views (at their own size) instead "
                         "of orbit views; needed for a forward-facing (NDC) tree file")
    ap.add_argument("--repeats", type=int, default=5, help="timed passes per path and size")
    ap.add_argument("--twin-rays", type=int, default=8000,
                    help="rays per view rendered by the torch twin (strided subset)")
    ap.add_argument("--twin-views", type=int, default=1, help="views rendered by the twin")
    ap.add_argument("--no-baseline", action="store_true", help="skip the frozen kernel")
    ap.add_argument("--stop-thresh", type=float, default=0.01)
    ap.add_argument("--out", default=None,
                    help="JSON path (default benchmarks/results/render_speed_<tree>.json)")
    args = ap.parse_args(argv)

    from plenoctree.render import RenderOptions, render_image, render_rays, tree_to_device
    from plenoctree.render import _render_numba as kern
    from plenoctree.render.options import parse_data_format

    load_before = os.getloadavg()
    tree, desc = load_bench_tree(args.tree, args.resolution,
                                 log=lambda m: print(m, file=sys.stderr), data=args.data)
    info = parse_data_format(tree.data_format, tree.data_dim, tree.extra_data)
    opts = RenderOptions(stop_thresh=args.stop_thresh)
    if desc.get("data"):      # --data, or the ff tree's own capture (all its cameras)
        cams, idx = data_cameras(desc["data"], args.views,
                                 "all" if desc["kind"] == "forward_facing" else "test")
        sets = {f"{cams.width}x{cams.height}": (cams, idx)}
    else:
        sets = {f"{s}x{s}": (orbit_cameras(args.views, s), list(range(args.views)))
                for s in args.sizes}

    fast = tree_to_device(tree, "cpu")                 # as eval / video prepare the tree
    print(f"empty-space skip tables: {fast.empty_skip.seconds:.1f} s, "
          f"{fast.empty_skip.nbytes / 2**20:.1f} MiB", file=sys.stderr)
    paths = ["numba", "noskip", "rays", "kernel"] + ([] if args.no_baseline else ["baseline"])
    results: dict[str, dict[str, Any]] = {p: {} for p in paths + ["torch"]}
    counters, breakdown, max_diff = {}, {}, {}
    for key, (cams, idx) in sets.items():
        n_px = cams.width * cams.height
        t0 = time.perf_counter()
        views = [cams.rays(i) for i in idx]
        raygen_ms = 1e3 * (time.perf_counter() - t0) / len(views)
        flat = [(o.reshape(-1, 3), d.reshape(-1, 3)) for o, d in views]

        def run_public():
            for i in idx:
                render_image(fast, cams, i, opts, backend="numba")

        def run_noskip():
            for i in idx:
                render_image(tree, cams, i, opts, backend="numba")

        def run_rays():
            for o, d in views:
                render_rays(fast, o, d, opts, backend="numba")

        prepared = kern.prepare(fast, info, opts)
        outs = [kern.empty_outputs(len(o)) for o, _ in flat]
        width = cams.width

        def run_kernel():
            for (o, d), out in zip(flat, outs):
                kern.render_prepared(prepared, o, d, out, width=width)

        fns: dict[str, Callable[[], Any]] = {"numba": run_public, "noskip": run_noskip,
                                             "rays": run_rays, "kernel": run_kernel}
        if "baseline" in paths:
            from baseline import render_kernel as base

            def run_base():      # what a frame cost before issue 12: ray arrays + the kernel
                for i in idx:
                    o, d = cams.rays(i)
                    base.render_rays_numba(tree.child, tree.data, tree.offset, tree.invradius,
                                           info, tree.extra_data, o.reshape(-1, 3),
                                           d.reshape(-1, 3), opts)

            fns["baseline"] = run_base
        for name in paths:
            fns[name]()                                             # warm-up
        for _ in range(args.repeats):                               # interleaved passes
            for name in paths:
                wall, cpu = time_passes(fns[name], 1)
                results[name].setdefault(key, ([], []))
                results[name][key][0].append(wall[0] / len(views))
                results[name][key][1].append(cpu[0] / len(views))
        for name in paths:
            results[name][key] = summarise(*results[name][key], n_px)

        stride = max(1, n_px // max(1, args.twin_rays))
        subsets = [(o[::stride], d[::stride]) for o, d in flat[:max(1, args.twin_views)]]
        n_sub = sum(len(o) for o, _ in subsets)
        c0, t0 = time.process_time(), time.perf_counter()    # one pass: it is slow
        twin = [render_rays(tree, o, d, opts, backend="torch").rgb for o, d in subsets]
        wall, cpu = [time.perf_counter() - t0], [time.process_time() - c0]
        results["torch"][key] = summarise([w / n_sub * n_px for w in wall],
                                          [c / n_sub * n_px for c in cpu], n_px)
        results["torch"][key].update(extrapolated=True, rays_timed=n_sub)
        max_diff[key] = max(max(
            float((render_image(fast, cams, i, opts, backend="numba").rgb.reshape(-1, 3)
                   [::stride] - ref).abs().max()),
            float((render_image(tree, cams, i, opts, backend="numba").rgb.reshape(-1, 3)
                   [::stride] - ref).abs().max()),
            float((render_rays(fast, o, d, opts, backend="numba").rgb - ref).abs().max()))
            for i, (o, d), ref in zip(idx, subsets, twin))
        counters[key] = ray_counters(tree, views, opts)
        counters[key]["with_skip"] = ray_counters(tree, views, opts, fast.empty_skip)
        pub, ker = results["numba"][key]["ms_per_frame"], results["kernel"][key]["ms_per_frame"]
        breakdown[key] = {"raygen_ms": raygen_ms, "outside_kernel_ms": pub - ker,
                          "rays_api_outside_kernel_ms": results["rays"][key]["ms_per_frame"] - ker,
                          "kernel_ms": ker,
                          "kernel_ns_per_ray_core": ker * 1e6 / n_px * (os.cpu_count() or 1)}
        print(f"[{key}] numba {pub:.1f} ms, kernel {ker:.1f} ms"
              + (f", baseline {results['baseline'][key]['ms_per_frame']:.1f} ms"
                 if "baseline" in paths else ""), file=sys.stderr)

    ratio = ({k: results["baseline"][k]["ms_per_frame"] / results["numba"][k]["ms_per_frame"]
              for k in sets} if "baseline" in paths else {})
    skip_ratio = {k: results["noskip"][k]["ms_per_frame"] / results["numba"][k]["ms_per_frame"]
                  for k in sets}
    report = {
        "benchmark": "render_speed", "tree": desc, "views": args.views,
        "sets": list(sets), "repeats": args.repeats,
        "options": {"stop_thresh": opts.stop_thresh, "background": list(opts.background)},
        "results": results, "ray_counters": counters, "time_breakdown": breakdown,
        "speedup_numba_over_baseline": ratio, "speedup_skip_over_noskip": skip_ratio,
        "empty_skip": {"seconds": fast.empty_skip.seconds, "mib": fast.empty_skip.nbytes / 2**20,
                       "grid_bits": fast.empty_skip.grid_bits},
        "max_abs_diff_rgb_numba_vs_torch": max_diff,
        "machine": {**machine_info(), "loadavg_before": list(load_before),
                    "loadavg_after": list(os.getloadavg())},
    }
    out = Path(args.out or ROOT / "results" / f"render_speed_{desc['kind']}.json")
    from plenoctree._util import atomic_save_json

    atomic_save_json(out, report)

    print(f"\nOctree render speed — {desc['source']}: {tree.data_format}, {tree.n_leaves} "
          f"leaves, max depth {tree.max_depth}, {args.views} views, stop_thresh "
          f"{opts.stop_thresh}\n")
    print("| path | size | ms/frame (median) | spread | FPS | M rays/s | CPU ms/frame |")
    print("|---|---|---|---|---|---|---|")
    for name, per in results.items():
        for k, r in per.items():
            note = " (extrapolated)" if r.get("extrapolated") else ""
            print(f"| {name}{note} | {k} | {r['ms_per_frame']:.1f} | {r['ms_min']:.1f}–"
                  f"{r['ms_max']:.1f} | {r['fps']:.2f} | {r['mrays_per_s']:.2f} | "
                  f"{r['cpu_ms_per_frame']:.1f} |")
    print("\n| size | hit rays | leaves/hit ray (with skip) | σ>0 leaves | negligible (w<1e-4) "
          "| child reads "
          "| stopped early | numpy raygen ms | render_image − kernel ms | render_rays − kernel ms "
          "| kernel ns/ray/core |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for k in sets:
        c, b = counters[k], breakdown[k]
        print(f"| {k} | {c['hit_fraction']:.1%} | {c['leaves_per_hit_ray']:.1f} "
              f"({c['with_skip']['leaves_per_hit_ray']:.1f}) | "
              f"{c['sigma_leaves_per_hit_ray']:.1f} | {c['negligible_per_hit_ray']:.1f} | "
              f"{c['descent_per_hit_ray']:.1f} | {c['stopped_fraction_of_hit']:.1%} | "
              f"{b['raygen_ms']:.1f} | {b['outside_kernel_ms']:.1f} | "
              f"{b['rays_api_outside_kernel_ms']:.1f} | "
              f"{b['kernel_ns_per_ray_core']:.0f} |")
    print()
    for k in sets:
        sp = f"{ratio[k]:.2f}x a pre-issue-12 frame; " if ratio else ""
        sp += f"{skip_ratio[k]:.2f}x without empty-space skipping; "
        print(f"{k}: numba {results['numba'][k]['fps']:.1f} FPS, {sp}max |Δ rgb| numba/rays vs "
              f"twin = {max_diff[k]:.2e}")
    m = report["machine"]
    print(f"\nmachine: {m['cpu_model']}, {m['cpu_count']} cores, numba {m['numba']} "
          f"({m['numba_threading_layer']}, {m['numba_threads']} threads); load average before "
          f"{load_before[0]:.2f}, after {m['loadavg_after'][0]:.2f}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
