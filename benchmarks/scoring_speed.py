"""What scoring a stage costs outside the renderer: loading the tree and SSIM per view, each
against the previous implementation in the same run.

- ``load``: :func:`plenoctree.octree.load_tree` (uncompressed members read straight into the
  array, CRC-32 checked, plus the tree's integrity check) against reading the same members
  through ``zipfile``'s ``readinto`` (what the reader did before; no checks), on ``--tree`` (``lego``: the default extraction of
  ``shared/data/runs/lego_cpu_400``, cached once; or a path, e.g. a refined tree);
- ``ssim``: :func:`plenoctree.metrics.ssim` (numpy separable blur) against the previous
  torch ``conv2d`` blur (``benchmarks/baseline/scoring.py``), on pairs of consecutive lego test views
  at 400² (real content), with the largest difference of the two values.

Usage::

    .venv/bin/python benchmarks/scoring_speed.py [--tree lego|PATH.npz] [--pairs 10]

Prints a table and writes ``benchmarks/results/scoring_speed.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from _trees import CACHE, ROOT, find_lego_run, load_bench_tree, machine_info  # noqa: E402
from baseline.scoring import read_members_zipfile, ssim_torch  # noqa: E402


def best_of(fn, repeats: int) -> float:
    """Fastest of ``repeats`` calls, seconds."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return min(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", default="lego", help="lego | PATH.npz")
    ap.add_argument("--pairs", type=int, default=10, help="test-view pairs scored by SSIM")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "results" / "scoring_speed.json"))
    args = ap.parse_args()

    from plenoctree.datasets import load_dataset
    from plenoctree.metrics import ssim
    from plenoctree.octree import load_tree

    if args.tree == "lego":
        load_bench_tree("lego")                      # extracts it once into the cache
        path = CACHE / "lego_cpu_400_256.npz"
    else:
        path = Path(args.tree)
    load_tree(path)                                  # page cache warm for both paths

    t_new = best_of(lambda: load_tree(path), args.repeats)
    t_old = best_of(lambda: read_members_zipfile(path), args.repeats)
    mb = path.stat().st_size / 1e6

    run = find_lego_run()
    if run is None:
        raise SystemExit("needs shared/data/nerf_synthetic/lego beside the repository")
    test = load_dataset(str(run.parents[1] / "nerf_synthetic" / "lego"), split="test",
                        downscale=2)
    pairs = [(test.images[k], test.images[k + 1]) for k in range(min(args.pairs,
                                                                     len(test) - 1))]
    diff = max(abs(ssim(a, b) - ssim_torch(a, b)) for a, b in pairs)
    s_new = best_of(lambda: [ssim(a, b) for a, b in pairs], args.repeats) / len(pairs)
    s_old = best_of(lambda: [ssim_torch(a, b) for a, b in pairs], args.repeats) / len(pairs)

    h, w = pairs[0][0].shape[:2]
    rows = {"load": {"what": f"{path} ({mb:.0f} MB)", "new_s": t_new, "before_s": t_old,
                     "speedup": t_old / t_new},
            "ssim": {"what": f"{len(pairs)} lego test-view pairs at {w}x{h}",
                     "new_s": s_new, "before_s": s_old, "speedup": s_old / s_new,
                     "max_abs_diff": diff}}
    print("| what | on | now | before (same run) | speed-up |\n|---|---|---|---|---|")
    print(f"| load_tree | {rows['load']['what']} | {t_new:.2f} s | {t_old:.2f} s (zipfile readinto) | "
          f"{t_old / t_new:.1f}x |")
    print(f"| ssim per view | {rows['ssim']['what']} | {s_new * 1e3:.0f} ms | "
          f"{s_old * 1e3:.0f} ms (torch conv2d) | {s_old / s_new:.1f}x |")
    print(f"ssim values: max |numpy - torch| = {diff:.2e}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine_info(), "rows": rows}, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
