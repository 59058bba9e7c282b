"""The chain on ``process``'s lego poses vs the same chain on the true poses (same settings).

Input: a dataset written by ``plenoctree process`` from the lego training photos (e.g. by
``benchmarks/colmap_poses.py``, under ``benchmarks/results/cache/colmap_poses/process_defaults``);
the true poses are those of ``nerf_synthetic/lego`` of the data root (``--data-root``). A twin
dataset is
made beside it with the same images (linked), the same frames and split, but the true poses,
the true focal length (of the source photos' size; the principal point of the undistorted
images) and the Blender scene box [-1.5, 1.5]³. Both go through
``run_pipeline`` with one small budget (``--steps`` of NeRF-SH training, ``--grid``,
``--epochs`` of fine-tuning, at ``--downscale``); the table gives the test PSNR of every stage
(the photos `process` held out: every 8th; the lego rows of docs/capture.md were measured
with the earlier 90 % rule, 10 photos) and the difference.

    python benchmarks/colmap_chain.py \\
        --data benchmarks/results/cache/colmap_poses/process_defaults \\
        --work benchmarks/results/cache/colmap_chain --steps 800 --downscale 2 --grid 128 \\
        --epochs 2

The chains run in ``--work`` (kept: a later call resumes them); the table goes to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from _bench import CACHE, add_data_root, add_out, data_path, machine_info, write_json


def make_twin(data: Path, twin: Path, lego: Path) -> Path:
    """``twin``: ``data``'s frames with the true poses, focal and box of ``lego``."""
    tj = json.loads((data / "transforms.json").read_text())
    meta = json.loads((lego / "transforms_train.json").read_text())
    gt = {Path(f["file_path"]).name + ".png": f["transform_matrix"] for f in meta["frames"]}
    twin.mkdir(parents=True, exist_ok=True)
    for d in data.iterdir():
        if d.is_dir() and d.name.startswith("images") and not (twin / d.name).exists():
            os.symlink(d.resolve(), twin / d.name)
    # The undistorted images are the source photos resampled by COLMAP's camera (focal kept,
    # principal point moved to the new centre, a ~0 radial term: a half-pixel shift on lego)
    # and cropped at the top left to a multiple of 8: the true camera of these pixels is the
    # true focal of the source size, with the principal point where `process` put it.
    from PIL import Image

    src = Path(json.loads((data / "process.json").read_text())["source"])
    with Image.open(next(p for p in sorted(src.iterdir()) if p.suffix == ".png")) as im:
        w_src = im.size[0]
    focal = 0.5 * w_src / math.tan(0.5 * meta["camera_angle_x"])
    out = {"camera_model": "PINHOLE", "w": tj["w"], "h": tj["h"], "fl_x": focal, "fl_y": focal,
           "cx": tj["cx"], "cy": tj["cy"], "aabb_scale": 1, "scale": 1 / 3,
           "offset": [0.5, 0.5, 0.5],
           "frames": [{"file_path": f["file_path"], "transform_matrix": gt[f["colmap_name"]]}
                      for f in tj["frames"]]}
    text = json.dumps(out, indent=1)
    tfile = twin / "transforms.json"
    if not tfile.is_file() or tfile.read_text() != text:    # (a resumed run keeps its stamps)
        tfile.write_text(text)
    return twin


def main(argv: list[str] | None = None) -> int:
    from plenoctree._log import configure_cli
    from plenoctree.pipeline import PipelineConfig, layer_settings, run_pipeline

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="a lego dataset written by `process`")
    ap.add_argument("--work", default=str(CACHE / "colmap_chain"),
                    help="folder of the two chains (kept: a later call resumes them)")
    ap.add_argument("--steps", type=int, default=800, help="NeRF-SH training steps (a step "
                    "count, not minutes: the machine may be shared)")
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--only", choices=["colmap", "true"], default=None,
                    help="run one of the two chains (two processes in parallel); a later run "
                         "without it skips the finished stages and prints the table")
    add_data_root(ap)
    add_out(ap, "colmap_chain.json")
    args = ap.parse_args(argv)
    data, work = Path(args.data), Path(args.work)
    twin = make_twin(data, work / "gt_data", data_path(args.data_root, "nerf_synthetic", "lego"))
    load_before = os.getloadavg()
    res = {}
    for name, d in (("colmap poses", data), ("true poses", twin)):
        if args.only and not name.startswith(args.only):
            continue
        cfg = PipelineConfig(data=str(d), out=str(work / name.replace(" ", "_")),
                             downscale=args.downscale, nerf_eval_views=-1, video_frames=0,
                             web=False, format="nerfstudio")
        layer_settings(cfg, {"train": {"minutes": 0, "max_steps": args.steps, "val_views": 0},
                             "extract": {"grid": args.grid},
                             "finetune": {"epochs": args.epochs}}, "colmap_chain")
        configure_cli()                          # the pipeline's progress lines on stdout
        s = run_pipeline(cfg)
        res[name] = {row["stage"]: row["psnr"] for row in s["rows"] if row["psnr"] is not None}
    if args.only:
        return 0
    machine = machine_info(load_before)
    stages = list(res["true poses"])
    print(f"{'stage':<24} {'colmap poses':>13} {'true poses':>11} {'diff (dB)':>10}")
    for st in stages:
        a, b = res["colmap poses"].get(st), res["true poses"][st]
        print(f"{st:<24} {a:13.2f} {b:11.2f} {a - b:10.2f}")
    print(f"budget: {args.steps} NeRF-SH training steps, grid {args.grid}, {args.epochs} "
          f"fine-tune epochs, downscale {args.downscale}; load {load_before[0]:.1f} -> "
          f"{machine['loadavg'][0]:.1f} on {machine['cpu_count']} cores")
    out = write_json(args.out, {"benchmark": "colmap_chain", "psnr": res,
                                "settings": vars(args), "machine": machine})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
