"""Moving frames of the viewer's CPU mode: a coarser level of the same tree against the tree
itself at a lower resolution (issue 48: "use a coarser level of the same tree while moving").

For a tree, levels ``k = 0..--levels`` (the tree with its ``k`` deepest levels merged,
``compression.lod.merge_to_depth``: each 2x2x2 block one leaf keeping its mean transmittance
and opacity-weighted colour) are made, and from the tree's reference view (NDC trees: the NDC
reference camera, shifted a little; others: 2.5 radii from the box centre) the script reports
per level and frame side: leaves, segments per ray (``ray_stats_numba``), the numba render time
(median of ``--repeats``, both cores) and the PSNR against the sharp ``--size``² frame of the
tree after bilinear upscaling (as the page stretches a moving frame over its canvas). The tree
itself (level 0) is the baseline, measured in the same run.

    python benchmarks/moving_levels.py --tree TREE [--size 800] [--sides 248,320,400]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from _bench import RESULTS, fmt, machine_info, markdown_table, write_json


def _camera(tree, px: int):
    from plenoctree.datasets import Cameras
    from plenoctree.datasets.trajectories import look_at

    if tree.ndc is not None:
        c2w, fov_x = np.eye(4), 2 * np.arctan(0.5 * tree.ndc.width / tree.ndc.fx)
        c2w[:3, 3] = [0.05, -0.03, 0.0]
    else:
        centre = (0.5 - np.asarray(tree.offset)) / np.asarray(tree.invradius)
        radius = float(np.max(0.5 / np.asarray(tree.invradius)))
        c2w, fov_x = look_at(centre + 2.5 * radius * np.array([0.6, 0.5, 0.62]), centre), 0.69
    f = 0.5 * px / np.tan(0.5 * fov_x)
    cams = Cameras(np.asarray(c2w, np.float32)[None], f, f, px / 2, px / 2, px, px)
    return cams if tree.ndc is None else tree.ndc.apply(cams)


def _upscaled(rgb: np.ndarray, size: int) -> np.ndarray:
    from PIL import Image

    img = Image.fromarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8))
    return np.asarray(img.resize((size, size), Image.BILINEAR), np.float64) / 255


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", required=True, help="a tree file (.npz or .plnz)")
    ap.add_argument("--size", type=int, default=800, help="side of the sharp frame, pixels")
    ap.add_argument("--sides", default="248,320,400", help="sides of the moving frames")
    ap.add_argument("--levels", type=int, default=3, help="coarser levels to make")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None, help="JSON (default results/moving_levels.json)")
    args = ap.parse_args()
    from plenoctree.compression import load_any_tree
    from plenoctree.compression.lod import merge_to_depth
    from plenoctree.render import RenderOptions, render_image, tree_to_device
    from plenoctree.render._render_numba import STAT_NAMES, ray_stats_numba

    load_before = __import__("os").getloadavg()
    tree = load_any_tree(args.tree)
    sharp = render_image(tree_to_device(tree, "cpu"), _camera(tree, args.size), 0).rgb.numpy()
    rows, level = [], tree
    for k in range(args.levels + 1):
        if k:
            if level.max_depth < 2:
                break
            t0 = time.perf_counter()
            level = merge_to_depth(level, level.max_depth - 1)
            build_s = time.perf_counter() - t0
        else:
            build_s = 0.0
        dev = tree_to_device(level, "cpu")
        for side in (int(s) for s in args.sides.split(",")):
            cams = _camera(tree, side)
            o, d = cams.rays(0)
            stats = ray_stats_numba(level, o.reshape(-1, 3), d.reshape(-1, 3), RenderOptions())
            out = render_image(dev, cams, 0)
            ms = []
            for _ in range(args.repeats):
                a = time.perf_counter()
                render_image(dev, cams, 0)
                ms.append(1e3 * (time.perf_counter() - a))
            err = np.mean((_upscaled(out.rgb.numpy(), args.size) - sharp) ** 2)
            rows.append({"level": k, "leaves": int(level.n_leaves), "build_s": build_s,
                         "side": side, "segments_per_ray":
                         float(stats[:, STAT_NAMES.index("leaves")].mean()),
                         "render_ms": statistics.median(ms),
                         "psnr_vs_sharp": float(-10 * np.log10(max(err, 1e-12)))})
            print(f"level {k} at {side}²: {rows[-1]['render_ms']:.0f} ms", file=sys.stderr)
    print(f"\n{Path(args.tree).name}: moving frames against the sharp {args.size}² frame")
    print(markdown_table(["level", "leaves", "side", "segments / ray", "render ms",
                          "PSNR vs sharp (dB)"],
                         [[r["level"], f"{r['leaves']:,}", f"{r['side']}²",
                           fmt(r["segments_per_ray"], ".1f"), fmt(r["render_ms"], ".0f"),
                           fmt(r["psnr_vs_sharp"], ".2f")] for r in rows]))
    out = args.out or str(RESULTS / "moving_levels.json")
    write_json(out, {"tree": str(args.tree), "args": vars(args), "rows": rows,
                     "machine": machine_info(load_before)})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
