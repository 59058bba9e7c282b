"""Fine-tuning speed: rays per second for forward + backward + optimiser step.

Usage: ``python benchmarks/finetune_speed.py [--tree T.npz] [--batch 65536] [--ray-tile 4]
[--repeat 5] [--twin-batch 16384] [--out benchmarks/results/finetune_speed.json]``

Default tree: the procedural scene's 256³ SH-degree-3 tree (built once, cached under
``benchmarks/results/cache``). Rays: random pixels of 32 cameras (800×800, the NeRF-synthetic
field of view) on a sphere around the tree's box looking at its centre, drawn as the
fine-tuning loop draws them (random ``--ray-tile``² pixel tiles); targets random colours (every
ray then has a gradient, so the backward does its full work).

Measured in the same run, each after a warm-up step (JIT compilation), median and half-spread
of ``--repeat`` steps:

- ``fast``: the fine-tuning path (one fused numba kernel: forward + analytic backward into
  per-thread slabs, merge, sparse SGD step) with all numba threads;
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
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

_CACHE = Path("benchmarks/results/cache")


def default_tree():
    from plenoctree.datasets.procedural import procedural_tree
    from plenoctree.octree import load_tree, save_tree

    path = _CACHE / "procedural_256_sh16.npz"
    if path.exists():
        return load_tree(path), str(path)
    tree = procedural_tree(256)
    save_tree(tree, path)
    return tree, f"procedural_tree(256) (cached at {path})"


def camera_rays(tree, n_cams: int, size: int, batch: int, tile: int, rng):
    """Random ``tile × tile`` pixel tiles of ``n_cams`` cameras around the tree (about ``batch``
    rays); returns the view set, pixel indices, origins and dirs ``[M, 3]``."""
    from plenoctree.datasets.procedural import CAMERA_ANGLE_X, look_at
    from plenoctree.optim._loop import ViewSet

    center, radius = tree.center, float(np.max(tree.radius))
    v = rng.normal(size=(n_cams, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    c2w = np.stack([look_at(center + 2.7 * radius * vi, center) for vi in v]).astype(np.float32)
    fx = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    imgs = np.zeros((n_cams, 1, 1, 3), np.float32)
    views = ViewSet(c2w, fx, fx, size / 2, size / 2, size, size,
                    np.broadcast_to(imgs, (n_cams, size, size, 3)), [])
    tiles = rng.choice(views.n_tiles(tile), size=max(1, batch // (tile * tile)), replace=False)
    idx = views.tile_pixels(tiles, tile)
    o, d, _ = views.rays(idx)
    return views, idx, o, d


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

    from plenoctree.octree import load_tree
    from plenoctree.optim import render_rays_differentiable
    from plenoctree.optim._render_grad import forward_numba, kernel_args
    from plenoctree.optim._steppers import NumbaStepper, TorchStepper
    from plenoctree.render import RenderOptions, render_rays

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree", default=None, help="tree .npz (default: procedural 256³ SH16)")
    ap.add_argument("--batch", type=int, default=1 << 16, help="rays per step (fast paths)")
    ap.add_argument("--ray-tile", type=int, default=4, help="rays drawn as k x k pixel tiles")
    ap.add_argument("--twin-batch", type=int, default=1 << 14, help="rays per step (twin)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--twin-repeat", type=int, default=1, help="timed twin steps (slow)")
    ap.add_argument("--size", type=int, default=800, help="camera image size (pixels)")
    ap.add_argument("--stop-thresh", type=float, default=0.01)
    ap.add_argument("--skip-twin", action="store_true")
    ap.add_argument("--out", default="benchmarks/results/finetune_speed.json")
    args = ap.parse_args()

    tree, tree_name = (load_tree(args.tree), args.tree) if args.tree else default_tree()
    opts = RenderOptions(stop_thresh=args.stop_thresh)
    rng = np.random.default_rng(0)
    views, idx, o, d = camera_rays(tree, 32, args.size, args.batch, args.ray_tile, rng)
    n = o.shape[0]
    tgt = rng.uniform(0, 1, size=(n, 3)).astype(np.float32)
    scale = 1.0 / (3 * args.size * args.size)
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
    kargs = kernel_args(tree, opts)
    sec, sp = timed(lambda: forward_numba(kargs, data2, o, d), args.repeat)
    add("forward_only", sec, sp, n)
    st = NumbaStepper(data2, kargs, "sgd", lr)
    sec, sp = timed(lambda: st.step(o, d, tgt, scale), args.repeat)
    add("fast", sec, sp, n)
    rows["fast"]["touched_cells"] = st.last_touched
    numba.set_num_threads(1)
    try:
        st1 = NumbaStepper(data2, kargs, "sgd", lr, n_chunks=1)
        sec, sp = timed(lambda: st1.step(o, d, tgt, scale), args.repeat)
        add("fast_1thread", sec, sp, n)
    finally:
        numba.set_num_threads(n_threads)
    del st1
    if args.ray_tile != 1:
        _, _, o1, d1 = camera_rays(tree, 32, args.size, n, 1, np.random.default_rng(1))
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
    machine = dict(cpus=os.cpu_count(), numba_threads=n_threads, platform=platform.platform(),
                   python=platform.python_version(), numpy=np.__version__,
                   torch=torch.__version__, numba=numba.__version__,
                   torch_threads=torch.get_num_threads())
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(machine=machine, tree=tree_name, n_leaves=tree.n_leaves,
                                   data_format=tree.data_format, stop_thresh=args.stop_thresh,
                                   ray_tile=args.ray_tile,
                                   results=rows, speedup_fast_over_twin=speedup), indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
