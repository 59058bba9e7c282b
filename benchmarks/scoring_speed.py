"""What scoring a stage costs outside the renderer: loading the tree and SSIM per view, each
against a reference implementation measured in the same run.

- ``load``: :func:`plenoctree.octree.load_tree` (uncompressed members read straight into the
  array, CRC-32 checked, plus the tree's integrity check) against numpy's own ``.npz`` reader
  (``np.load`` reading every member; no checks), on ``--tree`` (``lego``: the default
  extraction of the data root's ``runs/lego_cpu_400``, cached once; or a path, e.g. a refined
  tree);
- ``ssim``: :func:`plenoctree.metrics.ssim` (numpy separable blur) against scikit-image's
  ``structural_similarity`` (Gaussian weights, σ 1.5, population covariance: the common
  reference implementation; its values differ slightly, the NeRF variant clamps σxy and
  averages the valid region only), on pairs of consecutive test views of ``--data`` (default
  the data root's lego at 400², real content), with the largest difference of the two values.
  Skipped with a note without scikit-image.
- ``ssim_blur``: the same SSIM with its blur by scipy's ``correlate1d`` (used when scipy is
  installed) against the numpy blur it falls back to without scipy, on the same pairs.

Each figure is the median of ``--repeats`` timed calls after a warm-up (page cache warm for
both readers). Old code against new: ``python benchmarks/ab.py --rev REV -- scoring_speed.py``.

Usage::

    .venv/bin/python benchmarks/scoring_speed.py [--tree lego|PATH.npz] [--data DIR] [--pairs 10]

Prints a table and writes ``benchmarks/results/scoring_speed.json`` (``--out``).
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path
from typing import Any

import numpy as np

from _bench import add_data_root, add_out, data_path, machine_info, markdown_table, timed, \
    write_json
from _trees import LEGO_TREE, load_bench_tree


def read_npz(path: Path) -> None:
    """Every member of the ``.npz`` through numpy's reader."""
    with np.load(path, allow_pickle=False) as z:
        for k in z.files:
            z[k]


def ssim_skimage(a: np.ndarray, b: np.ndarray) -> float:
    """scikit-image's SSIM with the evaluation's window (Gaussian, σ 1.5, data range 1)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                       use_sample_covariance=False, data_range=1.0,
                                       channel_axis=-1))


def row(what: str, new: Any, ref: Any, ref_name: str, per: int = 1) -> dict[str, Any]:
    """A table row of two timings (seconds per item: ``per`` items a call)."""
    return {"what": what, "reference": ref_name, "new_s": new.median / per,
            "new_spread_s": new.spread / per, "reference_s": ref.median / per,
            "reference_spread_s": ref.spread / per, "speedup": ref.median / new.median}


def test_pairs(data: Path, n_pairs: int) -> tuple[list[tuple[Any, Any]], str]:
    """Consecutive test-view pairs of ``data`` at 400² (downscale 2), loaded once for both
    SSIM rows, and their description."""
    from plenoctree.datasets import load_dataset

    test = load_dataset(str(data), split="test", downscale=2, limit=n_pairs + 1)
    pairs = [(test.images[k], test.images[k + 1]) for k in range(min(n_pairs, len(test) - 1))]
    h, w = pairs[0][0].shape[:2]
    return pairs, f"{len(pairs)} test-view pairs of {data.name} at {w}x{h}"


def ssim_row(pairs: list, what: str, repeats: int) -> dict[str, Any]:
    """The ``ssim`` row: :func:`plenoctree.metrics.ssim` against scikit-image's."""
    from plenoctree.metrics import ssim

    if importlib.util.find_spec("skimage") is None:
        return {"skipped": "scikit-image is not installed (pip install scikit-image)"}
    diff = max(abs(ssim(a, b) - ssim_skimage(a, b)) for a, b in pairs)
    new = timed(lambda: [ssim(a, b) for a, b in pairs], repeats)
    ref = timed(lambda: [ssim_skimage(a, b) for a, b in pairs], repeats)
    return {**row(what, new, ref, "skimage structural_similarity", len(pairs)),
            "max_abs_diff": diff}


def ssim_blur_row(pairs: list, what: str, repeats: int) -> dict[str, Any]:
    """SSIM with its blur by scipy (what it uses when scipy is installed) against the plain
    numpy blur it falls back to (scipy hidden from the import), on the same pairs."""
    import sys

    from plenoctree.metrics import ssim

    if importlib.util.find_spec("scipy") is None:
        return {"skipped": "scipy is not installed: SSIM uses the numpy blur"}
    new = timed(lambda: [ssim(a, b) for a, b in pairs], repeats)
    hidden = sys.modules.pop("scipy", None)
    sys.modules["scipy"] = None                  # type: ignore[assignment]  # import fails
    try:
        ref = timed(lambda: [ssim(a, b) for a, b in pairs], repeats)
    finally:
        del sys.modules["scipy"]
        if hidden is not None:
            sys.modules["scipy"] = hidden
    return row(what, new, ref, "the numpy blur", len(pairs))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", default="lego", help="lego | PATH.npz")
    ap.add_argument("--data", default=None,
                    help="dataset of the SSIM pairs (default: nerf_synthetic/lego of the data "
                         "root)")
    ap.add_argument("--pairs", type=int, default=10, help="test-view pairs scored by SSIM")
    ap.add_argument("--repeats", type=int, default=3)
    add_data_root(ap)
    add_out(ap, "scoring_speed.json")
    args = ap.parse_args(argv)

    from plenoctree.octree import load_tree

    if args.tree == "lego":
        load_bench_tree("lego", root=args.data_root)      # extracts it once into the cache
        path = LEGO_TREE
    else:
        path = Path(args.tree)
    new = timed(lambda: load_tree(path), args.repeats)   # the warm-up fills the page cache
    ref = timed(lambda: read_npz(path), args.repeats)
    rows = {"load": row(f"{path} ({path.stat().st_size / 1e6:.0f} MB)", new, ref, "np.load")}
    data = Path(args.data) if args.data else data_path(args.data_root, "nerf_synthetic", "lego")
    pairs, what = test_pairs(data, args.pairs)
    rows["ssim"] = ssim_row(pairs, what, args.repeats)
    rows["ssim_blur"] = ssim_blur_row(pairs, what, args.repeats)
    table = [[name, r["what"], f"{r['new_s'] * 1e3:.1f} ± {r['new_spread_s'] * 1e3:.1f} ms",
              f"{r['reference_s'] * 1e3:.1f} ms ({r['reference']})", f"{r['speedup']:.2f}x"]
             for name, r in rows.items() if "skipped" not in r]
    print(markdown_table(["what", "on", "now", "reference (same run)", "reference / now"],
                         table))
    if "skipped" in rows["ssim"]:
        print(f"ssim: skipped ({rows['ssim']['skipped']})")
    else:
        print(f"ssim values: max |plenoctree - skimage| = {rows['ssim']['max_abs_diff']:.2e}")
    out = write_json(args.out, {"benchmark": "scoring_speed", "rows": rows,
                                "machine": machine_info()})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
