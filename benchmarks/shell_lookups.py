"""Where a far-field tree's leaf lookups go: by shell, empty or not, skipped or not (issue 50).

A tree with a far field (:mod:`plenoctree.convert.shells`) is its box grown ``2^L`` times with
shells of coarser cells around it; a lookup's *ring* ``k`` is the nested cube it falls in:
``2^-(k+1) <= max|p - centre| / half-side < 2^-k`` in tree space (ring 0 is the outermost shell,
the box is the innermost rings). The march is the renderer's (:func:`next_leaf` with the ancestor
stack and the empty-space skip tables of ``tree_to_device``, the same early stop); for each
ring it counts, per ray: lookups of empty leaves and how many of those could not be pushed
forward by the skip tables at all (``r = 0``: the empty cube ahead is the leaf itself), lookups
of σ > 0 leaves, ``child`` reads, and *empty runs*: the stretches of consecutive empty lookups
between σ > 0 ones (counted in the ring where they start). A run is what a skip that knew the
ray's own path would cross in one lookup, so ``σ > 0 lookups + runs`` bounds from below what
any exact empty-space skip can bring the lookups per ray to. A second table gives each
ring's share of σ > 0 leaves and of leaves with opacity ``1 - exp(-σ ℓ) > 0.1`` (ℓ: the
leaf's side in world units), and
``--prune A`` scores the tree with the leaves under opacity ``A`` emptied
(``compression.lod.prune``) on the test views: what leaving faint cells empty would buy.

Usage::

    python benchmarks/shell_lookups.py --tree W/tree_ft.npz --data W/data --downscale 2
    python benchmarks/shell_lookups.py --tree W/tree_ft.npz --data W/data --downscale 2 --prune 0.03 0.1
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
from numba import njit

from _bench import add_out, machine_info, machine_line, markdown_table, write_json
from _trees import data_cameras

from plenoctree.render._march_numba import (MARCH_MATH, MAX_LEVEL, STACK_SIZE, next_leaf,
                                            ray_octant, ray_start)
from plenoctree.render.options import QUANT_BITS

RINGS = 16
# per ring: 0 empty lookups, 1 empty with r = 0, 2 child reads, 3 σ > 0 lookups, 4 empty runs
_COLS = 5


@njit(cache=True, fastmath=MARCH_MATH)
def _count(child, skip, shift, data, offset, invr, o, d, stop, eps, out):
    """Add each ray's lookups into ``out [RINGS, 4]`` (columns: see ``_COLS``)."""
    half = 1 << (QUANT_BITS - 1)
    dim = data.shape[1]
    st = np.zeros(4, np.int64)
    stack = np.zeros(STACK_SIZE, np.int64)
    for i in range(o.shape[0]):
        dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, eps_t = ray_start(
            offset, invr, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], eps)
        if not t0 < t1:
            continue
        oc = ray_octant(vx, vy, vz)
        trans = 1.0
        t = t0
        st[0] = 0
        st[1] = -1
        stack[0] = 0
        steps = 0
        in_run = False
        while t < t1 and steps < 100000:
            steps += 1
            cell, t_end, n_desc = next_leaf(child, skip, shift, oc, px, py, pz, vx, vy, vz, ix,
                                            iy, iz, t, eps_t, t1, True, MAX_LEVEL, st, stack)
            r = max(abs(st[1] - half), abs(st[2] - half), abs(st[3] - half)) / half
            ring = 0
            while ring < RINGS - 1 and r < 0.5 ** (ring + 1):
                ring += 1
            out[ring, 2] += n_desc
            c = child[cell]
            sigma = data[cell, dim - 1] if c >= 0 else 0.0
            if sigma <= 0.0:                 # empty (marked by the skip tables or not)
                if not in_run:
                    out[ring, 4] += 1
                in_run = True
                out[ring, 0] += 1
                if c >= 0 or skip[-c - 1, oc] == 0:
                    out[ring, 1] += 1
            else:
                in_run = False
                out[ring, 3] += 1
                trans *= math.exp(-sigma * (t_end - t))
                if trans < stop:
                    break
            t = t_end


def ring_of_leaves(tree) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each leaf's ring, σ and side (world units, mean of the three axes)."""
    centres = np.asarray(tree.leaf_centers(), np.float64)
    p = np.asarray(tree.offset, np.float64) + np.asarray(tree.invradius, np.float64) * centres
    r = np.abs(p - 0.5).max(axis=1) / 0.5
    ring = np.minimum(np.floor(-np.log2(np.maximum(r, 1e-12))), RINGS - 1).astype(int)
    sigma = np.asarray(tree.leaf_data(), np.float64)[:, -1]
    return ring, sigma, np.asarray(tree.leaf_sizes(), np.float64).mean(axis=1)


def lookups_by_ring(tree, fast, views: list, opts) -> tuple[np.ndarray, int]:
    """``[RINGS, 5]`` counts (columns: ``_COLS``) summed over the rays of ``views`` and the
    number of rays; the march skips with ``fast.empty_skip`` (None: leaf by leaf)."""
    from plenoctree.render._spec import tree_spec

    p = tree_spec(tree, opts, skip=fast.empty_skip, with_values=True)
    out = np.zeros((RINGS, _COLS), np.int64)
    n = 0
    for o, d in views:
        o = np.ascontiguousarray(o.reshape(-1, 3), np.float32)
        d = np.ascontiguousarray(d.reshape(-1, 3), np.float32)
        _count(*p.tree_args(p.data), o, d, p.stop, p.eps, out)
        n += len(o)
    return out, n


def prune_rows(tree, data_root: str, downscale: int, alphas: list[float]) -> list[dict]:
    """PSNR, leaves and lookups per ray of the tree pruned at each opacity in ``alphas``."""
    from plenoctree.compression.lod import prune
    from plenoctree.datasets import load_dataset
    from plenoctree.evaluation import evaluate_tree
    from plenoctree.render import RenderOptions, tree_to_device

    data = load_dataset(data_root, split="test", downscale=downscale)
    rows = []
    for a in [0.0] + alphas:
        t = prune(tree, a) if a > 0 else tree
        res = evaluate_tree(t, data, show_progress=False)
        fast = tree_to_device(t, "cpu")
        counts, n = lookups_by_ring(t, fast, [data.cameras.rays(0)], RenderOptions())
        rows.append({"alpha": a, "leaves": int((np.asarray(t.child) == 0).sum()),
                     "psnr": float(np.mean(res.psnr)), "ms_per_view": float(np.median(res.ms)),
                     "lookups_per_ray": float((counts[:, 0] + counts[:, 3]).sum() / n)})
    return rows


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", required=True, help="a tree file with a far field (.npz/.plnz)")
    ap.add_argument("--data", required=True, help="its dataset (the test views are marched)")
    ap.add_argument("--downscale", type=int, default=2, help="the views at 1/N of their size")
    ap.add_argument("--views", type=int, default=2, help="test views marched")
    ap.add_argument("--stride", type=int, default=7, help="every N-th pixel's ray")
    ap.add_argument("--prune", type=float, nargs="*", default=[],
                    help="also score the tree pruned at these opacities (slow: every test view)")
    add_out(ap, "shell_lookups")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from plenoctree.octree.io import load_tree
    from plenoctree.render import RenderOptions, tree_to_device

    load_before = os.getloadavg()
    tree = load_tree(args.tree)
    cams, idx = data_cameras(args.data, args.views, "test")
    cams = cams.scaled(args.downscale)
    fast = tree_to_device(tree, "cpu")
    views = []
    for i in idx:
        o, d = cams.rays(i)
        views.append((o.reshape(-1, 3)[::args.stride], d.reshape(-1, 3)[::args.stride]))
    t0 = time.perf_counter()
    counts, n = lookups_by_ring(tree, fast, views, RenderOptions())
    ring, sigma, side = ring_of_leaves(tree)
    alpha = 1.0 - np.exp(-np.maximum(sigma, 0.0) * side)
    rows = []
    for k in range(RINGS):
        in_ring = ring == k
        if not in_ring.any() and not counts[k].any():
            continue
        empty = counts[k, 0]
        rows.append({"ring": k, "empty_per_ray": empty / n,
                     "no_skip_share": counts[k, 1] / max(1, empty),
                     "sigma_per_ray": counts[k, 3] / n, "reads_per_ray": counts[k, 2] / n,
                     "runs_per_ray": counts[k, 4] / n,
                     "leaves": int(in_ring.sum()),
                     "sigma_share": float((sigma[in_ring] > 0).mean()) if in_ring.any() else 0.0,
                     "alpha01_share": float((alpha[in_ring] > 0.1).mean()) if in_ring.any()
                     else 0.0})
    total = {"lookups_per_ray": float((counts[:, 0] + counts[:, 3]).sum() / n),
             "empty_per_ray": float(counts[:, 0].sum() / n),
             "sigma_per_ray": float(counts[:, 3].sum() / n),
             "no_skip_share": float(counts[:, 1].sum() / max(1, counts[:, 0].sum())),
             "runs_per_ray": float(counts[:, 4].sum() / n),
             "rays": n, "seconds": time.perf_counter() - t0}
    print(f"{args.tree}: {len(sigma):,} leaves, {n:,} rays ({len(views)} test views at "
          f"{cams.width}x{cams.height}, every {args.stride}th pixel)\n")
    print(markdown_table(
        ["ring", "leaves", "σ>0 share", "α>0.1 share", "empty lookups/ray", "of them r=0",
         "σ>0 lookups/ray", "child reads/ray", "empty runs/ray"],
        [[r["ring"], f"{r['leaves']:,}", f"{r['sigma_share']:.2f}", f"{r['alpha01_share']:.2f}",
          f"{r['empty_per_ray']:.2f}", f"{r['no_skip_share']:.2f}", f"{r['sigma_per_ray']:.2f}",
          f"{r['reads_per_ray']:.2f}", f"{r['runs_per_ray']:.2f}"] for r in rows]))
    print(f"\nper ray: {total['lookups_per_ray']:.1f} lookups, {total['empty_per_ray']:.1f} "
          f"empty ({100 * total['no_skip_share']:.0f} % of them not skippable), "
          f"{total['sigma_per_ray']:.1f} with σ > 0; the empty lookups form "
          f"{total['runs_per_ray']:.1f} runs, so an exact skip could bring a ray to "
          f"{total['sigma_per_ray'] + total['runs_per_ray']:.1f} lookups at best")
    pruned = prune_rows(tree, args.data, args.downscale, args.prune) if args.prune else []
    if pruned:
        print("\n" + markdown_table(
            ["prune opacity <", "leaves", "PSNR (test views)", "lookups/ray (view 0)",
             "ms/view"],
            [[r["alpha"], f"{r['leaves']:,}", f"{r['psnr']:.3f}", f"{r['lookups_per_ray']:.1f}",
              f"{r['ms_per_view']:.0f}"] for r in pruned]))
    m = machine_info(load_before)
    print("\n" + machine_line(m))
    path = write_json(args.out, {"benchmark": "shell_lookups", "tree": args.tree,
                                 "data": args.data, "downscale": args.downscale,
                                 "rings": rows, "total": total, "prune": pruned, "machine": m})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
