"""The paper's Table 3 conversion trade-offs, measured on this machine.

Variants (paper Table 3 on NeRF-synthetic: 1.9G complete / 1.4G τ_w = 0.01 / 0.4G w/o auto
bbox / 0.3G grid 256), here at CPU scale — the reference row is the CPU default (grid 256,
τ_w 0.001, auto box) and every other row changes one thing:

============  ==========================================================================
``base``      ``--grid G --weight-thresh 0.001 --bbox auto`` (the reference, same run)
``tau0.01``   ``--weight-thresh 0.01`` (paper "Ours-1.4G")
``fixed``     ``--bbox fixed`` with the dataset's box (Blender: radius 1.5; "Ours-0.4G")
``gridG/2``   half the grid resolution ("Ours-0.3G")
============  ==========================================================================

Each row reports the extraction time per stage, leaves, file size (fp32 and fp16 bytes),
raw-tree test PSNR, and the render speed of the saved tree: ``--fps-views`` test cameras
rendered at ``--fps-size`` pixels with the numba renderer (rays generated before timing, one
warm-up render, median over ``--repeats`` passes taken round-robin over the variants so that
load changes hit all alike; early stop at T < 0.01).

Usage::

    .venv/bin/python benchmarks/extract_table3.py --run runs/lego_cpu            # a trained run
    .venv/bin/python benchmarks/extract_table3.py --procedural                   # analytic scene

Writes ``benchmarks/results/extract_table3[_procedural].json`` (``--out``), prints a table.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _bench import RESULTS, interleaved, machine_info, markdown_table, write_json
from plenoctree.convert import AnalyticField, ExtractConfig, extract
from plenoctree.convert.extraction import clamp_sigma_for_fp16
from plenoctree.convert.visibility import rescale_cameras
from plenoctree.datasets import load_dataset
from plenoctree.datasets.procedural import write_procedural_dataset
from plenoctree.octree import load_tree, save_tree
from plenoctree.render import RenderOptions, render_rays


def render_fps(tree_paths: dict[str, Path], cameras, views: int, size: int, repeats: int
               ) -> dict[str, dict]:
    """Median ms per frame of each saved tree over ``views`` cameras at ``size`` pixels.

    The trees are timed round-robin (pass 1 of every tree, then pass 2, ...) so that a change
    of machine load during the run affects all of them alike.
    """
    cams = rescale_cameras(cameras, size / cameras.width)
    idx = np.linspace(0, len(cams) - 1, views).round().astype(int)
    rays = [cams.rays(int(i)) for i in idx]
    opts = RenderOptions(stop_thresh=0.01)
    trees = {k: load_tree(p) for k, p in tree_paths.items()}

    def one_pass(tree):
        for o, d in rays:
            render_rays(tree, o, d, opts, "numba")

    passes = interleaved({k: (lambda t=t: one_pass(t)) for k, t in trees.items()}, repeats)
    out = {}
    for k, t in passes.items():
        t = t.scaled(1 / len(rays))
        ms = t.median * 1e3
        out[k] = {"ms_per_frame": ms, "fps": 1e3 / ms, "spread_ms": [min(t.wall) * 1e3,
                  max(t.wall) * 1e3], "size": [cams.width, cams.height], "views": len(rays)}
    return out


def variants(grid: int) -> dict[str, dict]:
    return {"base": {}, "tau0.01": {"weight_thresh": 0.01}, "fixed": {"bbox": "fixed"},
            f"grid{grid // 2}": {"grid": grid // 2}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="runs/lego_cpu", help="trained NeRF-SH run directory")
    ap.add_argument("--procedural", action="store_true",
                    help="use the analytic procedural scene instead of a run")
    ap.add_argument("--grid", type=int, default=256)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--eval-views", type=int, default=0, help="test views for PSNR (0: all)")
    ap.add_argument("--fps-views", type=int, default=5)
    ap.add_argument("--fps-size", type=int, default=800)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", nargs="*", default=None, help="run only these variants")
    ap.add_argument("--keep", default="", help="folder to keep the trees in (default: temp)")
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)

    field = None
    tmp = tempfile.TemporaryDirectory()
    work = Path(args.keep) if args.keep else Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    base_cfg = dict(grid=args.grid, samples=args.samples, eval_views=args.eval_views,
                    show_progress=False)
    if args.procedural:
        data = work / "procedural"
        if not (data / "transforms_test.json").is_file():
            write_procedural_dataset(data, n_train=50, n_val=0, n_test=10, width=128,
                                     height=128)
        field = AnalyticField()
        base_cfg.update(data=str(data))
        name = "procedural"
    else:
        if not (Path(args.run) / "checkpoint.pt").is_file():
            print(f"{args.run}: no checkpoint.pt (train first, or use --procedural)")
            return 1
        base_cfg.update(run_dir=args.run)
        name = Path(args.run).name
    out_json = Path(args.out) if args.out else RESULTS / (
        "extract_table3" + ("_procedural" if args.procedural else "") + ".json")

    rows = {}
    test_cams = None
    for key, change in variants(args.grid).items():
        if args.only and key not in args.only:
            continue
        tree_path = work / f"{key}.npz"
        cfg = ExtractConfig(**{**base_cfg, **change, "out": str(tree_path)})
        t0 = time.perf_counter()
        res = extract(cfg, field=field)
        total = time.perf_counter() - t0
        if test_cams is None:
            root = cfg.data or res.extra["config"]["data"] or ""
            if not root and field is None:
                from plenoctree.nerf.checkpoint import read_checkpoint

                root = read_checkpoint(args.run)["config"].data
            test_cams = load_dataset(root, "test", limit=max(args.fps_views, 1)).cameras
        fp16 = work / f"{key}_fp16.npz"
        clamp_sigma_for_fp16(res.tree)                 # as `--precision fp16` does
        save_tree(res.tree, fp16, "fp16")
        rows[key] = {"change": change, "total_s": total, "stages": res.stages,
                     "box": res.box.to_json(), "grid": cfg.grid, "leaves": res.tree.n_leaves,
                     "kept": res.n_kept, "mb_fp32": res.file_bytes / 2**20,
                     "mb_fp16": fp16.stat().st_size / 2**20, "psnr": res.psnr,
                     "ssim": res.ssim, "eval_views": res.eval_views,
                     "nerf_val_psnr": res.nerf_psnr, "tree": str(tree_path),
                     "vis_size": res.extra.get("vis_size")}
        r = rows[key]
        print(f"{key:>9}: {total:7.1f} s  {r['kept']:>9} voxels  {r['mb_fp32']:8.1f} MB  "
              f"PSNR {r['psnr']:.2f}", flush=True)
        del res
    fps = render_fps({k: Path(r["tree"]) for k, r in rows.items()}, test_cams, args.fps_views,
                     args.fps_size, args.repeats)
    for k, r in rows.items():
        r["render"] = fps[k]

    print(f"\n## Table 3 trade-offs on {name} (grid {args.grid}, {args.samples} samples/voxel)\n")
    print(markdown_table(
        ["variant", "kept voxels", "MB fp32", "MB fp16", "test PSNR", "ms/frame", "FPS",
         "extract s (grid / filter / sample)"],
        [[key, r["kept"], f"{r['mb_fp32']:.1f}", f"{r['mb_fp16']:.1f}", f"{r['psnr']:.2f}",
          f"{r['render']['ms_per_frame']:.1f}", f"{r['render']['fps']:.2f}",
          f"{r['total_s']:.1f} ({r['stages']['grid']['seconds']:.1f} / "
          f"{r['stages']['filter']['seconds']:.1f} / {r['stages']['sample']['seconds']:.1f})"]
         for key, r in rows.items()]))
    write_json(out_json, {"benchmark": "extract_table3", "scene": name, "grid": args.grid,
                          "samples": args.samples, "fps_size": args.fps_size,
                          "machine": machine_info(), "rows": rows})
    print(f"\nwrote {out_json}")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
