"""Fine-tuning speed: rays per second for forward + backward + optimiser step.

Usage: ``python benchmarks/finetune_speed.py [--tree T.npz] [--batch 65536] [--ray-tile 4]
[--repeat 5] [--twin-batch 16384] [--out benchmarks/results/finetune_speed.json]``

Default tree: the real lego tree when ``shared/data/runs/lego_cpu_400`` is found above the
repository (extracted once into ``benchmarks/results/cache``), else the procedural scene's 256³
SH-degree-3 tree; ``--tree lego | procedural | ff | PATH`` (see ``benchmarks/_trees.py``). Rays: random pixels of 32 cameras (800×800, the NeRF-synthetic
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
- ``baseline``: the same step with the kernels as they were before issue 12 (frozen in
  ``benchmarks/baseline/grad_kernel.py``), timed interleaved with ``fast``; the JSON gives the
  ratio ``speedup_fast_over_baseline``;
- ``adam``: the fine-tuning default (lazy Adam, σ with its own learning rate) as one fused
  kernel + one optimiser kernel, with the split of its step (``kernel_ms``, ``optimizer_ms``,
  ``touched_cells``);
- ``fast_1thread``: the same with one thread and one slab (what the race-free scatter costs /
  buys);
- ``fast_tile1``: ``fast`` on independent random pixels (``--ray-tile 1``);
- ``autograd_fn``: ``render_rays_differentiable`` (the ``torch.autograd.Function``, numba forward
  and analytic backward, dense gradient tensor) + dense ``torch.optim.SGD`` step;
- ``twin``: the renderer's torch twin with torch autograd + dense SGD (the oracle; baseline);
- ``forward_only``: the fine-tuning kernel's forward pass alone (same traversal, no gradient);
- ``render_only``: the renderer's ``render_rays(backend="numba")``, for scale.

Ray generation for the batch is timed separately (``raygen``). Besides wall time the table gives
the process CPU time per step (all threads): on a shared machine ``rays_per_cpu_s`` times the
core count estimates the idle-machine throughput. Prints a table, writes JSON with
``rays_per_s`` per backend and the speed-up of ``fast`` over ``twin``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from _trees import load_bench_tree, machine_info


def baseline_step(st, o, d, tgt, scale):
    """``NumbaStepper.step`` (SGD) with the frozen pre-issue-12 kernels and their dense slabs."""
    import numba

    from baseline import grad_kernel as bk

    a = st.args
    if not hasattr(st, "dense"):
        st.dense = bk.DenseSlabs(*st.data2.shape, st.buf.n_chunks)
    b = st.dense
    o = np.ascontiguousarray(o, np.float32)
    d = np.ascontiguousarray(d, np.float32)
    t = np.ascontiguousarray(tgt, np.float64)
    rgb = np.empty((o.shape[0], 3), np.float64)
    b.sse[:] = 0.0
    old = numba.get_parallel_chunksize()
    numba.set_parallel_chunksize(2)
    try:
        bk.grad_kernel(a.child, st.sig, st.data2, a.offset, a.invr, o, d, t, 1, float(scale),
                       a.info.kind, a.info.basis_dim, a.sg, a.b_lo, a.b_hi, a.bg, a.stop, a.eps,
                       a.cap0, rgb, b.grad3, b.flags, b.touched, b.n_touched, b.sse)
    finally:
        numba.set_parallel_chunksize(old)
    st.step_count += 1
    bk.step_touched(st.data2, st.sig, b.grad3, b.flags, b.touched, b.n_touched, bk.OPT_SGD,
                    st.lr, st._dummy, st._dummy, 0.0, 0.0, 0.0, float(st.step_count))


def split_step(st, o, d, tgt, scale, repeat):
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


def interleaved(paths, repeat, add, n):
    """Time the ``(name, fn)`` pairs of ``paths`` in turn, ``repeat`` passes (so a noisy
    machine slows them alike), and ``add`` each one's median wall time as a row."""
    both = {name: ([], []) for name, _ in paths}
    for _ in range(repeat):
        for name, fn in paths:
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            both[name][0].append(time.perf_counter() - t0)
            both[name][1].append(time.process_time() - c0)
    for name, (ts, cs) in both.items():
        _CPU.append(statistics.median(cs))
        add(name, statistics.median(ts), (max(ts) - min(ts)) / 2, n)


def orbit_views(tree, n_cams: int, size: int, rng):
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


def bench_views(tree, desc: dict, size: int, rng):
    """The views a batch is drawn from: a tree with its own scene (``ff``: the forward-facing
    NDC tree) uses that scene's training cameras (NDC rays at 504×378, as ``finetune`` does),
    any other tree 32 orbit cameras (:func:`orbit_views`)."""
    if desc.get("data"):
        from plenoctree.datasets import load_dataset
        from plenoctree.optim._loop import ViewSet

        return ViewSet.from_dataset(load_dataset(desc["data"], "train"))
    return orbit_views(tree, 32, size, rng)


def draw_rays(views, batch: int, tile: int, rng):
    """Random ``tile × tile`` pixel tiles of ``views`` (about ``batch`` rays), as the fine-tuning
    loop draws them; returns pixel indices, origins and dirs ``[M, 3]``."""
    n_tiles = views.n_tiles(tile)
    tiles = rng.choice(n_tiles, size=min(n_tiles, max(1, batch // (tile * tile))),
                       replace=False)
    idx = views.tile_pixels(tiles, tile)
    o, d, _ = views.rays(idx)
    return idx, o, d


_CPU: list[float] = []


def timed(fn, repeat: int, warmup: bool = True) -> tuple[float, float]:
    """Median and half-spread of the wall time of ``fn``; the median process CPU time (all
    threads) goes to ``_CPU[-1]``."""
    if warmup:
        fn()                                      # warm-up (compilation)
    ts, cs = [], []
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    _CPU.append(statistics.median(cs))
    return statistics.median(ts), (max(ts) - min(ts)) / 2


def main() -> None:
    import numba

    from plenoctree.optim import render_rays_differentiable
    from plenoctree.optim._render_grad import forward_numba, kernel_args
    from plenoctree.optim._steppers import NumbaStepper, TorchStepper
    from plenoctree.render import RenderOptions, render_rays

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", default=None,
                    help="lego | procedural | ff | PATH.npz (default: lego when found)")
    ap.add_argument("--batch", type=int, default=1 << 16, help="rays per step (fast paths)")
    ap.add_argument("--ray-tile", type=int, default=4, help="rays drawn as k x k pixel tiles")
    ap.add_argument("--twin-batch", type=int, default=1 << 14, help="rays per step (twin)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--twin-repeat", type=int, default=1, help="timed twin steps (slow)")
    ap.add_argument("--size", type=int, default=800, help="camera image size (pixels)")
    ap.add_argument("--stop-thresh", type=float, default=0.01)
    ap.add_argument("--skip-twin", action="store_true")
    ap.add_argument("--data", default=None,
                    help="dataset of the tree: draw the batch from its training cameras (as "
                         "finetune does) instead of orbit views; needed for an NDC tree file")
    ap.add_argument("--out", default=None,
                    help="JSON (default benchmarks/results/finetune_speed_<tree>.json)")
    args = ap.parse_args()

    load_before = os.getloadavg()
    tree, desc = load_bench_tree(args.tree, 256, data=args.data)
    tree_name = desc["source"]
    opts = RenderOptions(stop_thresh=args.stop_thresh)
    rng = np.random.default_rng(0)
    views = bench_views(tree, desc, args.size, rng)
    idx, o, d = draw_rays(views, args.batch, args.ray_tile, rng)
    n = o.shape[0]
    tgt = rng.uniform(0, 1, size=(n, 3)).astype(np.float32)
    scale = 1.0 / (3 * views.width * views.height)
    lr = 1e-3   # tiny: keeps the values (and so the work per ray) stable across repeats
    n_threads = numba.get_num_threads()
    rows = {}

    def add(name, sec, spread, n):
        rows[name] = {"rays_per_s": n / sec, "ms_per_step": sec * 1e3,
                      "ms_spread": spread * 1e3, "batch": n, "cpu_ms_per_step": _CPU[-1] * 1e3,
                      "rays_per_cpu_s": n / max(_CPU[-1], 1e-9)}

    sec, sp = timed(lambda: views.rays(idx), args.repeat)
    add("raygen", sec, sp, n)
    sec, sp = timed(lambda: render_rays(tree, o, d, opts, backend="numba"), args.repeat)
    add("render_only", sec, sp, n)

    data2 = np.ascontiguousarray(tree.data, np.float32).reshape(-1, tree.data_dim).copy()
    kplain = kernel_args(tree, opts)
    kargs = kernel_args(tree, opts, skip_from=data2)   # as `finetune`: empty-space skipping
    sec, sp = timed(lambda: forward_numba(kargs, data2, o, d), args.repeat)
    add("forward_only", sec, sp, n)
    st = NumbaStepper(data2, kargs, "sgd", lr)
    sn = NumbaStepper(data2.copy(), kplain, "sgd", lr)
    sb = NumbaStepper(data2.copy(), kplain, "sgd", lr)
    st.step(o, d, tgt, scale)                                    # warm-up (compilation)
    sn.step(o, d, tgt, scale)
    baseline_step(sb, o, d, tgt, scale)
    interleaved((("fast", lambda: st.step(o, d, tgt, scale)),
                 ("fast_noskip", lambda: sn.step(o, d, tgt, scale)),
                 ("baseline", lambda: baseline_step(sb, o, d, tgt, scale))), args.repeat, add, n)
    del sb, sn
    rows["fast"]["touched_cells"] = st.last_touched
    rows["fast"]["slab_mb"] = st.buf.nbytes / 2**20
    # the fine-tuning default: Adam with σ's own learning rate (in opacity units / h; tiny
    # rates here, so the values stay put)
    h = float(tree.leaf_sizes().min())
    sa = NumbaStepper(data2.copy(), kargs, "adam", 1e-6, sigma_lr=1e-6 / h)
    sec, sp = timed(lambda: sa.step(o, d, tgt, scale), args.repeat)
    add("adam", sec, sp, n)
    k_ms, s_ms = split_step(sa, o, d, tgt, scale, args.repeat)
    rows["adam"].update(kernel_ms=k_ms, optimizer_ms=s_ms, touched_cells=sa.last_touched)
    del sa
    numba.set_num_threads(1)
    try:
        st1 = NumbaStepper(data2, kargs, "sgd", lr, n_chunks=1)
        sec, sp = timed(lambda: st1.step(o, d, tgt, scale), args.repeat)
        add("fast_1thread", sec, sp, n)
    finally:
        numba.set_num_threads(n_threads)
    del st1
    if args.ray_tile != 1:
        _, o1, d1 = draw_rays(views, n, 1, np.random.default_rng(1))
        sec, sp = timed(lambda: st.step(o1, d1, tgt[:o1.shape[0]], scale), args.repeat)
        add("fast_tile1", sec, sp, o1.shape[0])

    data_t = torch.tensor(tree.data, dtype=torch.float32, requires_grad=True)
    sgd = torch.optim.SGD([data_t], lr=lr)
    o_t, d_t, tgt_t = torch.from_numpy(o), torch.from_numpy(d), torch.from_numpy(tgt)

    def fn_step():
        sgd.zero_grad(set_to_none=True)
        rgb = render_rays_differentiable(data_t, tree, o_t, d_t, opts, backend="numba")
        (((rgb - tgt_t) ** 2).sum() * scale).backward()
        sgd.step()

    sec, sp = timed(fn_step, max(2, args.repeat // 2))
    add("autograd_fn", sec, sp, n)
    del data_t, sgd

    if not args.skip_twin:
        nb = min(args.twin_batch, n)
        tw = TorchStepper(data2, tree, opts, "sgd", lr, device="cpu")
        sec, sp = timed(lambda: tw.step(o[:nb], d[:nb], tgt[:nb], scale), args.twin_repeat,
                        warmup=False)
        add("twin", sec, sp, nb)
        del tw

    speedup = rows["fast"]["rays_per_s"] / rows["twin"]["rays_per_s"] if "twin" in rows else None
    vs_base = rows["fast"]["rays_per_s"] / rows["baseline"]["rays_per_s"]
    print(f"tree: {tree_name}: {tree.n_leaves} leaves, {tree.data_format}, "
          f"{tree.data.nbytes / 2**20:.0f} MiB; {n_threads} numba threads; stop_thresh "
          f"{args.stop_thresh}; rays in {args.ray_tile}x{args.ray_tile} tiles")
    print(f"{'path':<14} {'batch':>7} {'ms/step':>9} {'± ms':>7} {'M rays/s':>9} "
          f"{'cpu ms':>8} {'M rays/cpu-s':>12}")
    for name, r in rows.items():
        print(f"{name:<14} {r['batch']:>7} {r['ms_per_step']:>9.1f} {r['ms_spread']:>7.1f} "
              f"{r['rays_per_s'] / 1e6:>9.3f} {r['cpu_ms_per_step']:>8.1f} "
              f"{r['rays_per_cpu_s'] / 1e6:>12.3f}")
    if speedup:
        print(f"fast / twin speed-up: {speedup:.1f}x")
    a = rows["adam"]
    print(f"adam (the finetune default): step = fused kernel {a['kernel_ms']:.1f} ms + "
          f"optimiser {a['optimizer_ms']:.1f} ms over {a['touched_cells']} touched cells; "
          f"gradient slabs {rows['fast']['slab_mb']:.0f} MiB (dense ones: "
          f"{st.buf.n_chunks * data2.nbytes / 2**20:.0f} MiB)")
    print(f"fast / fast_noskip (empty-space skipping, same run): "
          f"{rows['fast']['rays_per_s'] / rows['fast_noskip']['rays_per_s']:.2f}x")
    print(f"fast / baseline (pre-issue-12 kernels, same run): {vs_base:.2f}x; load average "
          f"before {load_before[0]:.2f}, after {os.getloadavg()[0]:.2f}")
    machine = {**machine_info(), "loadavg_before": list(load_before),
               "loadavg_after": list(os.getloadavg())}
    out = Path(args.out or f"benchmarks/results/finetune_speed_{desc['kind']}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(machine=machine, tree=desc, n_leaves=tree.n_leaves,
                                   data_format=tree.data_format, stop_thresh=args.stop_thresh,
                                   ray_tile=args.ray_tile,
                                   results=rows, speedup_fast_over_twin=speedup,
                                   speedup_fast_over_baseline=vs_base), indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
