"""Octree rendering speed on a real tree: the numba renderer's paths against the torch twin,
where a ray's time goes, and the twin's accuracy check.

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
- ``fast``: ``numba`` with svox's fast rule (``RenderOptions.renormalize``, rays stopped at
  transmittance ``--fast-stop``, 0.1): ``numba / fast`` is what it buys, and the report gives
  its frames' PSNR against the exact ones;
- ``rays``: the public :func:`plenoctree.render_rays` on ray arrays made before timing (input
  checks + kernel: the API for arbitrary rays);
- ``kernel``: the same kernel called with prepared ray arrays (so ``rays - kernel`` is the time
  per frame spent outside the kernel by the ray API);
- ``torch``: the baseline measured in the same run, the renderer's torch twin (float32, the
  specification) on a strided subset of ``--twin-views`` views, per-ray time extrapolated to the
  frame: ``torch / numba`` is the speed-up; it also gives max |Δ rgb| against ``numba`` and
  ``rays`` (the spec: ≤ 1e-4).

Old code against new: ``python benchmarks/ab.py --rev REV -- render_speed.py --tree T ...``
runs this script under both revisions, alternating, and tabulates each figure's ratio.

The time numpy takes to make the ray arrays of a frame (``cameras.rays``) is reported as
``raygen ms``.

Per-ray counters (the same march, :func:`plenoctree.render._render_numba.ray_stats_numba`):
leaves visited, σ > 0 leaves, σ > 0 segments of negligible weight (< 1e-4), ``child`` reads of
the descents, share of rays hitting the box and stopping early — so the distance to a frame
rate goal is explained by numbers.

Usage (each ≤ 2-3 min on 2 loaded cores)::

    .venv/bin/python benchmarks/render_speed.py                  # lego when the data root has it
    .venv/bin/python benchmarks/render_speed.py --tree procedural
    .venv/bin/python benchmarks/render_speed.py --tree ff        # forward-facing NDC, 504x378
    .venv/bin/python benchmarks/render_speed.py --tree my.npz --sizes 400
    .venv/bin/python benchmarks/render_speed.py --tree out/ff/tree_ft.npz --data DIR  # its views
    .venv/bin/python benchmarks/render_speed.py --tree T --data DIR --downscale 2  # at 1/2 size

Writes ``benchmarks/results/render_speed_<tree>.json`` (``--out``) and prints markdown tables.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from typing import Any, Callable

import numpy as np

from _bench import (RESULTS, Timing, interleaved, machine_info, machine_line, markdown_table,
                    write_json)
from _trees import add_tree_args, data_cameras, orbit_cameras, tree_from_args

PATHS = ("numba", "noskip", "fast", "rays", "kernel")


def summarise(t: Timing, rays_per_frame: int) -> dict[str, Any]:
    """The JSON row of a path's per-frame timing ``t``."""
    med = t.median
    return {"ms_per_frame": 1e3 * med, "ms_min": 1e3 * min(t.wall),
            "ms_max": 1e3 * max(t.wall), "fps": 1.0 / med,
            "mrays_per_s": rays_per_frame / med / 1e6,
            "cpu_ms_per_frame": 1e3 * t.cpu_median, "repeats": len(t.wall)}


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


def path_functions(tree: Any, fast: Any, cams: Any, idx: list[int], views: list,
                   opts: Any, fast_opts: Any) -> dict[str, Callable[[], Any]]:
    """One pass over the views for each of :data:`PATHS`."""
    from plenoctree.render import render_image, render_rays
    from plenoctree.render import _render_numba as kern
    from plenoctree.render.options import parse_data_format

    info = parse_data_format(tree.data_format, tree.data_dim, tree.extra_data)
    flat = [(o.reshape(-1, 3), d.reshape(-1, 3)) for o, d in views]
    prepared = kern.prepare(fast, info, opts)
    outs = [kern.empty_outputs(len(o)) for o, _ in flat]

    def run_public():
        for i in idx:
            render_image(fast, cams, i, opts, backend="numba")

    def run_noskip():
        for i in idx:
            render_image(tree, cams, i, opts, backend="numba")

    def run_fast():
        for i in idx:
            render_image(fast, cams, i, fast_opts, backend="numba")

    def run_rays():
        for o, d in views:
            render_rays(fast, o, d, opts, backend="numba")

    def run_kernel():
        for (o, d), out in zip(flat, outs):
            kern.render_prepared(prepared, o, d, out, width=cams.width)

    return {"numba": run_public, "noskip": run_noskip, "fast": run_fast, "rays": run_rays,
            "kernel": run_kernel}


def twin_pass(tree: Any, fast: Any, cams: Any, idx: list[int], views: list, opts: Any,
              args: argparse.Namespace) -> tuple[dict, float]:
    """The torch twin on a strided subset of rays of the first ``--twin-views`` views (one
    pass: it is slow), its time extrapolated to a frame, and the largest |Δ rgb| of the numba
    paths against it."""
    from plenoctree.render import render_image, render_rays

    n_px = cams.width * cams.height
    stride = max(1, n_px // max(1, args.twin_rays))
    subsets = [(o.reshape(-1, 3)[::stride], d.reshape(-1, 3)[::stride])
               for o, d in views[:max(1, args.twin_views)]]
    n_sub = sum(len(o) for o, _ in subsets)
    t = Timing()
    t.call(lambda: [render_rays(tree, o, d, opts, backend="torch").rgb for o, d in subsets])
    row = {**summarise(t.scaled(n_px / n_sub), n_px), "extrapolated": True, "rays_timed": n_sub}

    def sub(img):
        return img.rgb.reshape(-1, 3)[::stride]

    diff = max(max(float((sub(render_image(fast, cams, i, opts, backend="numba")) - ref)
                         .abs().max()),
                   float((sub(render_image(tree, cams, i, opts, backend="numba")) - ref)
                         .abs().max()),
                   float((render_rays(fast, o, d, opts, backend="numba").rgb - ref).abs().max()))
               for i, (o, d), ref in zip(idx, subsets, t.result))
    return row, diff


def skip_deviation(tree: Any, fast: Any, cams: Any, idx: list[int], opts: Any) -> dict:
    """Whole frames with and without the skip tables: their largest |Δ rgb| and the pixels
    off by more than the twin's tolerance (1e-4; the lookups' ε push lands elsewhere after a
    skip, :mod:`plenoctree.render.empty_skip`)."""
    from plenoctree.render import render_image

    worst, off, n = 0.0, 0, 0
    for i in idx:
        d = (render_image(fast, cams, i, opts, backend="numba").rgb
             - render_image(tree, cams, i, opts, backend="numba").rgb).abs().amax(-1)
        worst, off, n = max(worst, float(d.max())), off + int((d > 1e-4).sum()), n + d.numel()
    return {"max_abs_diff_rgb": worst, "pixels_over_1e-4": off, "pixels": n}


def fast_psnr(fast: Any, cams: Any, idx: list[int], opts: Any, fast_opts: Any) -> float:
    """Mean PSNR (dB, :func:`plenoctree.metrics.psnr`; identical frames 200 instead of
    infinite, for the JSON) of the ``fast`` path's frames against the exact frames."""
    from plenoctree.metrics import psnr
    from plenoctree.render import render_image

    return float(np.mean([min(psnr(render_image(fast, cams, i, fast_opts, backend="numba").rgb,
                                   render_image(fast, cams, i, opts, backend="numba").rgb), 200.0)
                          for i in idx]))


def measure_set(tree: Any, fast: Any, cams: Any, idx: list[int], opts: Any,
                args: argparse.Namespace) -> dict[str, Any]:
    """Every path, the twin, the counters and the time breakdown on one view set."""
    n_px = cams.width * cams.height
    t0 = time.perf_counter()
    views = [cams.rays(i) for i in idx]
    raygen_ms = 1e3 * (time.perf_counter() - t0) / len(views)
    fast_opts = replace(opts, stop_thresh=args.fast_stop, renormalize=True)
    timings = interleaved(path_functions(tree, fast, cams, idx, views, opts, fast_opts),
                          args.repeats)
    rows = {p: summarise(t.scaled(1 / len(views)), n_px) for p, t in timings.items()}
    rows["torch"], max_diff = twin_pass(tree, fast, cams, idx, views, opts, args)
    counters = ray_counters(tree, views, opts)
    counters["with_skip"] = ray_counters(tree, views, opts, fast.empty_skip)
    pub, ker = rows["numba"]["ms_per_frame"], rows["kernel"]["ms_per_frame"]
    breakdown = {"raygen_ms": raygen_ms, "outside_kernel_ms": pub - ker,
                 "rays_api_outside_kernel_ms": rows["rays"]["ms_per_frame"] - ker,
                 "kernel_ms": ker,
                 "kernel_ns_per_ray_core": ker * 1e6 / n_px * (os.cpu_count() or 1)}
    return {"rows": rows, "counters": counters, "breakdown": breakdown, "max_diff": max_diff,
            "skip_vs_noskip": skip_deviation(tree, fast, cams, idx, opts),
            "fast_psnr_vs_exact": fast_psnr(fast, cams, idx, opts, fast_opts)}


def print_report(report: dict, tree: Any) -> None:
    """The markdown tables of a report."""
    sets, results = report["sets"], report["results"]
    print(f"\nOctree render speed — {report['tree']['source']}: {tree.data_format}, "
          f"{tree.n_leaves} leaves, max depth {tree.max_depth}, {report['views']} views, "
          f"stop_thresh {report['options']['stop_thresh']}\n")
    print(markdown_table(
        ["path", "size", "ms/frame (median)", "spread", "FPS", "M rays/s", "CPU ms/frame"],
        [[name + (" (extrapolated)" if r.get("extrapolated") else ""), k,
          f"{r['ms_per_frame']:.1f}", f"{r['ms_min']:.1f}–{r['ms_max']:.1f}", f"{r['fps']:.2f}",
          f"{r['mrays_per_s']:.2f}", f"{r['cpu_ms_per_frame']:.1f}"]
         for name, per in results.items() for k, r in per.items()]))
    rows = []
    for k in sets:
        c, b = report["ray_counters"][k], report["time_breakdown"][k]
        rows.append([k, f"{c['hit_fraction']:.1%}", f"{c['leaves_per_hit_ray']:.1f} "
                     f"({c['with_skip']['leaves_per_hit_ray']:.1f})",
                     f"{c['sigma_leaves_per_hit_ray']:.1f}", f"{c['negligible_per_hit_ray']:.1f}",
                     f"{c['descent_per_hit_ray']:.1f}", f"{c['stopped_fraction_of_hit']:.1%}",
                     f"{b['raygen_ms']:.1f}", f"{b['outside_kernel_ms']:.1f}",
                     f"{b['rays_api_outside_kernel_ms']:.1f}",
                     f"{b['kernel_ns_per_ray_core']:.0f}"])
    print()
    print(markdown_table(
        ["size", "hit rays", "leaves/hit ray (with skip)", "σ>0 leaves", "negligible (w<1e-4)",
         "child reads", "stopped early", "numpy raygen ms", "render_image − kernel ms",
         "render_rays − kernel ms", "kernel ns/ray/core"], rows))
    print()
    sk = report["skip_vs_noskip"]
    for k in sets:
        print(f"{k}: numba {results['numba'][k]['fps']:.1f} FPS, "
              f"{report['speedup_numba_over_twin'][k]:.0f}x the torch twin; "
              f"{report['speedup_skip_over_noskip'][k]:.2f}x without empty-space skipping; "
              f"fast rule (stop {report['options']['fast_stop']}, renormalised) "
              f"{report['speedup_fast_over_numba'][k]:.2f}x at "
              f"{report['fast_psnr_vs_exact'][k]:.1f} dB against the exact frames; "
              f"max |Δ rgb| numba/rays vs twin = {report['max_abs_diff_rgb_numba_vs_torch'][k]:.2e}; "
              f"skip vs no skip, whole frames: {sk[k]['max_abs_diff_rgb']:.2e}, "
              f"{sk[k]['pixels_over_1e-4']} of {sk[k]['pixels']} pixels over 1e-4")
    print("\n" + machine_line(report["machine"]))


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_tree_args(ap, "dataset of the tree: time its test views (at their own size) instead "
                      "of orbit views; needed for a forward-facing (NDC) tree file",
                  "render_speed")
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 800],
                    help="image sizes (px; orbit views)")
    ap.add_argument("--views", type=int, default=4, help="views per pass")
    ap.add_argument("--downscale", type=int, default=1,
                    help="with --data: the views at 1/N of their size (a capture's working "
                         "resolution: lounge's 960x540 frames are trained at 480x270, 2)")
    ap.add_argument("--repeats", type=int, default=5, help="timed passes per path and size")
    ap.add_argument("--twin-rays", type=int, default=8000,
                    help="rays per view rendered by the torch twin (strided subset)")
    ap.add_argument("--twin-views", type=int, default=1, help="views rendered by the twin")
    ap.add_argument("--fast-stop", type=float, default=0.1,
                    help="transmittance at which the fast path stops a ray (renormalised)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from plenoctree.render import RenderOptions, tree_to_device

    load_before = os.getloadavg()
    tree, desc = tree_from_args(args)
    opts = RenderOptions(stop_thresh=args.stop_thresh)
    if desc.get("data"):      # --data, or the ff tree's own capture (all its cameras)
        cams, idx = data_cameras(desc["data"], args.views,
                                 "all" if desc["kind"] == "forward_facing" else "test")
        cams = cams.scaled(args.downscale)
        sets = {f"{cams.width}x{cams.height}": (cams, idx)}
    else:
        sets = {f"{s}x{s}": (orbit_cameras(args.views, s), list(range(args.views)))
                for s in args.sizes}
    fast = tree_to_device(tree, "cpu")                 # as eval / video prepare the tree
    print(f"empty-space skip tables: {fast.empty_skip.seconds:.1f} s, "
          f"{fast.empty_skip.nbytes / 2**20:.1f} MiB", file=sys.stderr)
    per_set = {}
    for key, (cams, idx) in sets.items():
        per_set[key] = measure_set(tree, fast, cams, idx, opts, args)
        r = per_set[key]["rows"]
        print(f"[{key}] numba {r['numba']['ms_per_frame']:.1f} ms, kernel "
              f"{r['kernel']['ms_per_frame']:.1f} ms, twin {r['torch']['ms_per_frame']:.0f} ms "
              "(extrapolated)", file=sys.stderr)
    results = {p: {k: s["rows"][p] for k, s in per_set.items()} for p in PATHS + ("torch",)}

    def ratio(slow: str, fast_path: str) -> dict[str, float]:
        return {k: results[slow][k]["ms_per_frame"] / results[fast_path][k]["ms_per_frame"]
                for k in sets}

    report = {
        "benchmark": "render_speed", "tree": desc, "views": args.views,
        "sets": list(sets), "repeats": args.repeats,
        "options": {"stop_thresh": opts.stop_thresh, "background": list(opts.background),
                    "fast_stop": args.fast_stop},
        "results": results, "ray_counters": {k: s["counters"] for k, s in per_set.items()},
        "time_breakdown": {k: s["breakdown"] for k, s in per_set.items()},
        "speedup_numba_over_twin": ratio("torch", "numba"),
        "speedup_skip_over_noskip": ratio("noskip", "numba"),
        "speedup_fast_over_numba": ratio("numba", "fast"),
        "fast_psnr_vs_exact": {k: s["fast_psnr_vs_exact"] for k, s in per_set.items()},
        "empty_skip": {"seconds": fast.empty_skip.seconds, "mib": fast.empty_skip.nbytes / 2**20,
                       "grid_bits": fast.empty_skip.grid_bits},
        "max_abs_diff_rgb_numba_vs_torch": {k: s["max_diff"] for k, s in per_set.items()},
        "skip_vs_noskip": {k: s["skip_vs_noskip"] for k, s in per_set.items()},
        "machine": machine_info(load_before),
    }
    out = write_json(args.out or RESULTS / f"render_speed_{desc['kind']}.json", report)
    print_report(report, tree)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
