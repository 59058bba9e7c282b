"""Optimising the octree's leaves directly from a coarse start (issue 49's Plenoxels-like
candidate) against the NeRF-SH chain's tree, on the same test views.

Method: a dense tree over the box of ``--box`` (a chain's ``tree.extract.json``: the box the
NeRF-SH found, which a from-scratch method would have to find itself) at the first of
``--levels`` cells per axis, every cell of opacity ~0.01 and grey (SH9, colour 0), is
fine-tuned on the photos (:func:`plenoctree.finetune`, the chain's optimiser and defaults) for
the level's ``--epochs``; then each next level is the tree resampled on a grid twice as fine
(children copy their parent's values; cells of opacity below ``--keep-alpha`` left empty) and
fine-tuned again. No total-variation or sparsity prior (Plenoxels has both): what the
chain's own machinery gives. The baseline, measured in the same run: ``--baseline`` (the
chain's fine-tuned tree), scored on the same ``--test-views`` evenly spaced test views as
``finetune``'s test pass.

    python benchmarks/direct_leaves.py --data LEGO --downscale 2 --box W/5/tree.extract.json \\
        --baseline W/5/tree_ft.npz [--levels 64,128,256] [--epochs 4,4,6] [--test-views 20]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from _bench import RESULTS, fmt, machine_info, markdown_table, write_json


def dense_start(center: np.ndarray, radius: np.ndarray, res: int) -> "object":
    """A ``res³`` tree over the box, opacity ~0.01 a cell, colour 0 (grey after the sigmoid)."""
    from plenoctree.octree.build import dense_tree

    vals = np.zeros((res, res, res, 28), np.float32)          # SH9: 27 colour values + σ
    vals[..., -1] = 0.01 / (2 * float(radius.max()) / res)
    return dense_tree(res.bit_length() - 2, "SH9", center, radius, values=vals)


def upsample(tree: "object", res: int, keep_alpha: float) -> "object":
    """``tree`` resampled on a ``res³`` grid over its box (each cell the value at its centre);
    cells of opacity below ``keep_alpha`` empty."""
    from plenoctree.octree.build import tree_from_grid

    c, r = np.asarray(tree.center, float), np.asarray(tree.radius, float)
    g = (np.arange(res) + 0.5) / res * 2 - 1
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * r + c
    v = tree.query(pts).reshape(res, res, res, -1).astype(np.float32)
    alpha = 1 - np.exp(-np.maximum(v[..., -1], 0) * (2 * float(r.max()) / res))
    keep = alpha >= keep_alpha
    v[~keep] = 0
    return tree_from_grid(v, keep, c, r, tree.data_format)


def finetune(tree_path: Path, out: Path, args: argparse.Namespace, epochs: int) -> dict:
    """``plenoctree.finetune`` of ``tree_path``: test PSNR before / after, seconds."""
    from plenoctree.optim.finetuning import FinetuneConfig, finetune as run

    t0 = time.perf_counter()
    res = run(FinetuneConfig(tree=str(tree_path), data=args.data, out=str(out), epochs=epochs,
                             downscale=args.downscale, test_views=args.test_views,
                             val_views=10, continue_on_decrease=True, show_progress=False))
    return {"before": res.test_psnr_before, "after": res.test_psnr_after,
            "seconds": time.perf_counter() - t0}


def score(tree_path: str, args: argparse.Namespace) -> float:
    """Mean PSNR of a tree on the ``--test-views`` evenly spaced test views ``finetune``
    scores (the same split load as its test pass)."""
    from plenoctree.compression import load_any_tree
    from plenoctree.datasets import load_dataset
    from plenoctree.evaluation import evaluate_tree

    test = load_dataset(args.data, "test", downscale=args.downscale, limit=args.test_views,
                        spread=True)
    return float(evaluate_tree(load_any_tree(tree_path), test).mean_psnr)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="dataset folder (lego)")
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--box", required=True, help="a chain's tree.extract.json (its box)")
    ap.add_argument("--baseline", required=True, help="the chain's fine-tuned tree")
    ap.add_argument("--levels", default="64,128,256", help="cells per axis of each level")
    ap.add_argument("--epochs", default="4,4,6", help="fine-tuning epochs per level")
    ap.add_argument("--keep-alpha", type=float, default=0.001)
    ap.add_argument("--test-views", type=int, default=20)
    ap.add_argument("--work", default=str(RESULTS / "direct_leaves"), help="scratch folder")
    ap.add_argument("--out", default=None, help="JSON (default results/direct_leaves.json)")
    args = ap.parse_args()
    from plenoctree.compression import load_any_tree
    from plenoctree.octree.io import save_tree

    load_before = os.getloadavg()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    box = json.loads(Path(args.box).read_text())["box"]
    center, radius = np.asarray(box["center"], float), np.asarray(box["radius"], float)
    levels = [int(v) for v in args.levels.split(",")]
    epochs = [int(v) for v in args.epochs.split(",")]
    if len(levels) != len(epochs):
        raise SystemExit("--levels and --epochs need as many entries")
    if any(v < 2 or v & (v - 1) for v in levels):
        raise SystemExit(f"--levels: powers of two >= 2, got {args.levels}")
    base = score(args.baseline, args)
    rows, total, prev = [], 0.0, None
    for res, ep in zip(levels, epochs):
        t0 = time.perf_counter()
        tree = dense_start(center, radius, res) if prev is None else upsample(
            load_any_tree(prev), res, args.keep_alpha)
        start = work / f"start_{res}.npz"
        save_tree(tree, start)
        build_s = time.perf_counter() - t0
        prev = work / f"ft_{res}.npz"
        r = finetune(start, prev, args, ep)
        total += build_s + r["seconds"]
        rows.append({"level": res, "leaves": int(tree.n_leaves), "epochs": ep,
                     "build_s": build_s, **r, "cumulative_s": total})
    print(f"\ndirect leaf optimisation on {Path(args.data).name}, {args.test_views} test views; "
          f"baseline {Path(args.baseline).name}: {fmt(base, '.2f')} dB")
    print(markdown_table(["level", "leaves", "epochs", "test dB before", "test dB after",
                          "seconds (build + fine-tuning)", "cumulative s"],
                         [[f"{r['level']}³", f"{r['leaves']:,}", r["epochs"],
                           fmt(r["before"], ".2f"), fmt(r["after"], ".2f"),
                           fmt(r["build_s"] + r["seconds"], ".0f"), fmt(r["cumulative_s"], ".0f")]
                          for r in rows]))
    out = args.out or str(RESULTS / "direct_leaves.json")
    write_json(out, {"args": vars(args), "baseline_psnr": base, "rows": rows,
                     "machine": machine_info(load_before)})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
