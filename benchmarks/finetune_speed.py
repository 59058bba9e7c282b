"""Fine-tuning speed: rays per second for forward + backward + optimiser step.

Usage: ``python benchmarks/finetune_speed.py [--tree T.npz] [--batch 65536] [--ray-tile 4]
[--repeat 5] [--twin-batch 16384] [--out benchmarks/results/finetune_speed_<tree>.json]``

Default tree: the real lego tree when ``runs/lego_cpu_400`` is found in the data root
(``--data-root``; extracted once into ``benchmarks/results/cache``), else the procedural
scene's 256³ SH-degree-3 tree; ``--tree lego | procedural | ff | PATH`` (see
``benchmarks/_trees.py``). Rays: random pixels of 32 cameras (800×800, the NeRF-synthetic
field of view) on a sphere around the tree's box looking at its centre, drawn as the
fine-tuning loop draws them (random ``--ray-tile``² pixel tiles); targets random colours (every
ray then has a gradient, so the backward does its full work). A tree with its own scene
(``ff``: the forward-facing NDC tree) takes its rays from that scene's training cameras instead
(NDC rays at 504×378, as ``finetune`` draws them).

Measured in the same run, each after a warm-up step (JIT compilation), median and half-spread
of ``--repeat`` steps:

- ``fast``: the fine-tuning path (one fused numba kernel: forward + analytic backward into
  per-thread slabs, merge, sparse SGD step) with all numba threads and, as ``finetune`` runs
  it, empty-space skipping (:mod:`plenoctree.render.empty_skip`);
- ``fast_noskip``: the same without empty-space skipping, timed interleaved with ``fast``;
- ``adam``: the fine-tuning default (lazy Adam, σ with its own learning rate) as one fused
  kernel + one optimiser kernel, with the split of its step (``kernel_ms``, ``optimizer_ms``,
  ``touched_cells``);
- ``fast_1thread``: the same with one thread and one slab (what the race-free scatter costs /
  buys);
- ``fast_tile1``: ``fast`` on independent random pixels (``--ray-tile 1``);
- ``autograd_fn``: ``render_rays_differentiable`` (the ``torch.autograd.Function``, numba forward
  and analytic backward, dense gradient tensor) + dense ``torch.optim.SGD`` step;
- ``twin``: the baseline, the renderer's torch twin with torch autograd + dense SGD (the
  oracle); the JSON gives the speed-up ``speedup_fast_over_twin``;
- ``forward_only``: the fine-tuning kernel's forward pass alone (same traversal, no gradient);
- ``render_only``: the renderer's ``render_rays(backend="numba")``, for scale.

Old code against new: ``python benchmarks/ab.py --rev REV -- finetune_speed.py --tree T ...``.

Ray generation for the batch is timed separately (``raygen``). Besides wall time the table gives
the process CPU time per step (all threads): on a shared machine ``rays_per_cpu_s`` times the
core count estimates the idle-machine throughput. Prints a table, writes JSON with
``rays_per_s`` per path and the speed-up of ``fast`` over ``twin``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from typing import Any

import numpy as np

from _bench import RESULTS, Timing, interleaved, machine_info, markdown_table, timed, write_json
from _trees import add_tree_args, tree_from_args

LR = 1e-3
"""SGD rate of the timed steps: tiny, so the values (and the work per ray) stay put."""


def split_step(st: Any, o, d, tgt, scale: float, repeat: int) -> tuple[float, float]:
    """Median ms of the two halves of ``st.step``: ``accumulate`` (the fused forward +
    backward kernel) and ``apply`` (the optimiser kernel), timed apart."""
    tk, ts = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        st.accumulate(o, d, tgt, scale)
        t1 = time.perf_counter()
        st.apply()
        ts.append(time.perf_counter() - t1)
        tk.append(t1 - t0)
    return statistics.median(tk) * 1e3, statistics.median(ts) * 1e3


def orbit_views(tree: Any, n_cams: int, size: int, rng: np.random.Generator) -> Any:
    """``n_cams`` cameras (``size``², the NeRF-synthetic field of view) at random points of a
    sphere around the tree's box, looking at its centre, as a view set (images unused)."""
    from plenoctree.datasets.procedural import CAMERA_ANGLE_X, look_at
    from plenoctree.optim._loop import ViewSet

    center, radius = tree.center, float(np.max(tree.radius))
    v = rng.normal(size=(n_cams, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    c2w = np.stack([look_at(center + 2.7 * radius * vi, center) for vi in v]).astype(np.float32)
    fx = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    imgs = np.zeros((n_cams, 1, 1, 3), np.float32)
    return ViewSet(c2w, fx, fx, size / 2, size / 2, size, size,
                   np.broadcast_to(imgs, (n_cams, size, size, 3)), [])


def bench_views(tree: Any, desc: dict, size: int, rng: np.random.Generator) -> Any:
    """The views a batch is drawn from: a tree with its own scene (``ff``: the forward-facing
    NDC tree) uses that scene's training cameras (NDC rays at 504×378, as ``finetune`` does),
    any other tree 32 orbit cameras (:func:`orbit_views`)."""
    if desc.get("data"):
        from plenoctree.datasets import load_dataset
        from plenoctree.optim._loop import ViewSet

        return ViewSet.from_dataset(load_dataset(desc["data"], "train"))
    return orbit_views(tree, 32, size, rng)


def draw_rays(views: Any, batch: int, tile: int, rng: np.random.Generator):
    """Random ``tile × tile`` pixel tiles of ``views`` (about ``batch`` rays), as the fine-tuning
    loop draws them; returns pixel indices, origins and dirs ``[M, 3]``."""
    n_tiles = views.n_tiles(tile)
    tiles = rng.choice(n_tiles, size=min(n_tiles, max(1, batch // (tile * tile))),
                       replace=False)
    idx = views.tile_pixels(tiles, tile)
    o, d, _ = views.rays(idx)
    return idx, o, d


class Batch:
    """The rays of one step: ``o``, ``d`` ``[n, 3]`` float32, random targets ``tgt`` and the
    loss scale of an image's mean squared error."""

    def __init__(self, views: Any, args: argparse.Namespace, rng: np.random.Generator):
        self.views = views
        self.idx, self.o, self.d = draw_rays(views, args.batch, args.ray_tile, rng)
        self.n = self.o.shape[0]
        self.tgt = rng.uniform(0, 1, size=(self.n, 3)).astype(np.float32)
        self.scale = 1.0 / (3 * views.width * views.height)


def row(t: Timing, n: int) -> dict[str, float]:
    """The JSON row of a path's timing ``t`` per step of ``n`` rays."""
    sec, cpu = t.median, t.cpu_median
    return {"rays_per_s": n / sec, "ms_per_step": sec * 1e3, "ms_spread": t.spread * 1e3,
            "batch": n, "cpu_ms_per_step": cpu * 1e3, "rays_per_cpu_s": n / max(cpu, 1e-9)}


def numba_rows(tree: Any, b: Batch, args: argparse.Namespace) -> dict[str, dict]:
    """The rows of the numba paths: ``raygen`` ... ``fast_tile1``."""
    import numba

    from plenoctree.optim._render_grad import forward_numba, kernel_args
    from plenoctree.optim._steppers import NumbaStepper
    from plenoctree.render import RenderOptions, render_rays

    opts = RenderOptions(stop_thresh=args.stop_thresh)
    o, d, tgt, scale, n, rep = b.o, b.d, b.tgt, b.scale, b.n, args.repeat
    rows = {"raygen": row(timed(lambda: b.views.rays(b.idx), rep), n),
            "render_only": row(timed(lambda: render_rays(tree, o, d, opts, backend="numba"),
                                     rep), n)}
    data2 = np.ascontiguousarray(tree.data, np.float32).reshape(-1, tree.data_dim).copy()
    kargs = kernel_args(tree, opts, skip_from=data2)   # as `finetune`: empty-space skipping
    rows["forward_only"] = row(timed(lambda: forward_numba(kargs, data2, o, d), rep), n)
    st = NumbaStepper(data2, kargs, "sgd", LR)
    sn = NumbaStepper(data2.copy(), kernel_args(tree, opts), "sgd", LR)
    for name, t in interleaved({"fast": lambda: st.step(o, d, tgt, scale),
                                "fast_noskip": lambda: sn.step(o, d, tgt, scale)}, rep).items():
        rows[name] = row(t, n)
    rows["fast"].update(touched_cells=st.last_touched, slab_mb=st.buf.nbytes / 2**20,
                        dense_slab_mb=st.buf.n_chunks * data2.nbytes / 2**20)
    # the fine-tuning default: Adam with σ's own learning rate (in opacity units / h; tiny
    # rates here, so the values stay put)
    h = float(tree.leaf_sizes().min())
    sa = NumbaStepper(data2.copy(), kargs, "adam", 1e-6, sigma_lr=1e-6 / h)
    rows["adam"] = row(timed(lambda: sa.step(o, d, tgt, scale), rep), n)
    k_ms, s_ms = split_step(sa, o, d, tgt, scale, rep)
    rows["adam"].update(kernel_ms=k_ms, optimizer_ms=s_ms, touched_cells=sa.last_touched)
    n_threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        st1 = NumbaStepper(data2, kargs, "sgd", LR, n_chunks=1)
        rows["fast_1thread"] = row(timed(lambda: st1.step(o, d, tgt, scale), rep), n)
    finally:
        numba.set_num_threads(n_threads)
    if args.ray_tile != 1:
        _, o1, d1 = draw_rays(b.views, n, 1, np.random.default_rng(1))
        rows["fast_tile1"] = row(timed(lambda: st.step(o1, d1, tgt[:o1.shape[0]], scale), rep),
                                 o1.shape[0])
    return rows


def torch_rows(tree: Any, b: Batch, args: argparse.Namespace) -> dict[str, dict]:
    """The rows of the torch paths: ``autograd_fn`` and (unless ``--skip-twin``) ``twin``."""
    import torch

    from plenoctree.optim import render_rays_differentiable
    from plenoctree.optim._steppers import TorchStepper
    from plenoctree.render import RenderOptions

    opts = RenderOptions(stop_thresh=args.stop_thresh)
    data_t = torch.tensor(tree.data, dtype=torch.float32, requires_grad=True)
    sgd = torch.optim.SGD([data_t], lr=LR)
    o_t, d_t, tgt_t = torch.from_numpy(b.o), torch.from_numpy(b.d), torch.from_numpy(b.tgt)

    def fn_step():
        sgd.zero_grad(set_to_none=True)
        rgb = render_rays_differentiable(data_t, tree, o_t, d_t, opts, backend="numba")
        (((rgb - tgt_t) ** 2).sum() * b.scale).backward()
        sgd.step()

    rows = {"autograd_fn": row(timed(fn_step, max(2, args.repeat // 2)), b.n)}
    if not args.skip_twin:
        nb = min(args.twin_batch, b.n)
        data2 = np.ascontiguousarray(tree.data, np.float32).reshape(-1, tree.data_dim).copy()
        tw = TorchStepper(data2, tree, opts, "sgd", LR, device="cpu")
        rows["twin"] = row(timed(lambda: tw.step(b.o[:nb], b.d[:nb], b.tgt[:nb], b.scale),
                                 args.twin_repeat, warmup=False), nb)
    return rows


def print_report(report: dict, tree: Any) -> None:
    """The table and the ratios of a report."""
    rows = report["results"]
    print(f"tree: {report['tree']['source']}: {tree.n_leaves} leaves, {tree.data_format}, "
          f"{tree.data.nbytes / 2**20:.0f} MiB; {report['machine']['numba_threads']} numba "
          f"threads; stop_thresh {report['stop_thresh']}; rays in {report['ray_tile']}x"
          f"{report['ray_tile']} tiles")
    print(markdown_table(["path", "batch", "ms/step", "± ms", "M rays/s", "cpu ms",
                          "M rays/cpu-s"],
                         [[name, r["batch"], f"{r['ms_per_step']:.1f}", f"{r['ms_spread']:.1f}",
                           f"{r['rays_per_s'] / 1e6:.3f}", f"{r['cpu_ms_per_step']:.1f}",
                           f"{r['rays_per_cpu_s'] / 1e6:.3f}"] for name, r in rows.items()]))
    if report["speedup_fast_over_twin"]:
        print(f"fast / twin speed-up (same run): {report['speedup_fast_over_twin']:.1f}x")
    a, f = rows["adam"], rows["fast"]
    print(f"adam (the finetune default): step = fused kernel {a['kernel_ms']:.1f} ms + "
          f"optimiser {a['optimizer_ms']:.1f} ms over {a['touched_cells']} touched cells; "
          f"gradient slabs {f['slab_mb']:.0f} MiB (dense ones: {f['dense_slab_mb']:.0f} MiB)")
    m = report["machine"]
    print(f"fast / fast_noskip (empty-space skipping, same run): "
          f"{f['rays_per_s'] / rows['fast_noskip']['rays_per_s']:.2f}x; load average "
          f"before {m['loadavg_before'][0]:.2f}, after {m['loadavg'][0]:.2f}")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_tree_args(ap, "dataset of the tree: draw the batch from its training cameras (as "
                      "finetune does) instead of orbit views; needed for an NDC tree file",
                  "finetune_speed")
    ap.add_argument("--batch", type=int, default=1 << 16, help="rays per step (fast paths)")
    ap.add_argument("--ray-tile", type=int, default=4, help="rays drawn as k x k pixel tiles")
    ap.add_argument("--twin-batch", type=int, default=1 << 14, help="rays per step (twin)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--twin-repeat", type=int, default=1, help="timed twin steps (slow)")
    ap.add_argument("--size", type=int, default=800, help="camera image size (pixels)")
    ap.add_argument("--skip-twin", action="store_true")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    load_before = os.getloadavg()
    tree, desc = tree_from_args(args)
    rng = np.random.default_rng(0)
    b = Batch(bench_views(tree, desc, args.size, rng), args, rng)
    rows = {**numba_rows(tree, b, args), **torch_rows(tree, b, args)}
    twin = rows.get("twin")
    report = {"benchmark": "finetune_speed", "tree": desc, "n_leaves": tree.n_leaves,
              "data_format": tree.data_format, "stop_thresh": args.stop_thresh,
              "ray_tile": args.ray_tile, "results": rows,
              "speedup_fast_over_twin": (rows["fast"]["rays_per_s"] / twin["rays_per_s"]
                                         if twin else None),
              "machine": machine_info(load_before)}
    out = write_json(args.out or RESULTS / f"finetune_speed_{desc['kind']}.json", report)
    print_report(report, tree)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
