"""The chain on ``process``'s lego poses vs the same chain on the true poses (same settings).

Input: a dataset written by ``plenoctree process`` from the lego training photos (e.g. by
``benchmarks/colmap_poses.py``, under ``/tmp/colmap_poses/process_defaults``). A twin dataset is
made beside it with the same images (linked), the same frames and split, but the true poses,
the true focal length (of the source photos' size; the principal point of the undistorted
images) and the Blender scene box [-1.5, 1.5]³. Both go through
``run_pipeline`` with one small budget (``--steps`` of NeRF-SH training, ``--grid``,
``--epochs`` of fine-tuning, at ``--downscale``); the table gives the test PSNR of every stage
(the 10 held-out photos of nerfstudio's 90 % rule) and the difference.

    python benchmarks/colmap_chain.py --data /tmp/colmap_poses/process_defaults \\
        --out /tmp/colmap_chain --steps 800 --downscale 2 --grid 128 --epochs 2
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from plenoctree._util import atomic_save_json

_HERE = Path(__file__).resolve().parents[1]          # the checkout (a worktree: one deeper)
LEGO = next((d / "shared/data/nerf_synthetic/lego" for d in (_HERE.parent, _HERE.parent.parent)
             if (d / "shared/data/nerf_synthetic/lego").is_dir()),
            _HERE.parent / "shared/data/nerf_synthetic/lego")


def make_twin(data: Path, twin: Path) -> Path:
    """``twin``: ``data``'s frames with the true lego poses, focal and box."""
    tj = json.loads((data / "transforms.json").read_text())
    meta = json.loads((LEGO / "transforms_train.json").read_text())
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
    ap.add_argument("--out", default="/tmp/colmap_chain")
    ap.add_argument("--steps", type=int, default=800, help="NeRF-SH training steps (a step "
                    "count, not minutes: the machine may be shared)")
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--json", default=None)
    ap.add_argument("--only", choices=["colmap", "true"], default=None,
                    help="run one of the two chains (two processes in parallel); a later run "
                         "without it skips the finished stages and prints the table")
    args = ap.parse_args(argv)
    data, out = Path(args.data), Path(args.out)
    twin = make_twin(data, out / "gt_data")
    load_before = os.getloadavg()
    res = {}
    for name, d in (("colmap poses", data), ("true poses", twin)):
        if args.only and not name.startswith(args.only):
            continue
        cfg = PipelineConfig(data=str(d), out=str(out / name.replace(" ", "_")),
                             downscale=args.downscale, nerf_eval_views=-1, video_frames=0,
                             web=False, format="nerfstudio")
        layer_settings(cfg, {"train": {"minutes": 0, "max_steps": args.steps, "val_views": 0},
                             "extract": {"grid": args.grid},
                             "finetune": {"epochs": args.epochs}}, "colmap_chain")
        configure_cli()                          # the pipeline's progress lines on stdout
        s = run_pipeline(cfg)
        res[name] = {row["stage"]: row["psnr"] for row in s["rows"] if row["psnr"] is not None}
    load_after = os.getloadavg()
    if args.only:
        return 0
    stages = list(res["true poses"])
    print(f"{'stage':<24} {'colmap poses':>13} {'true poses':>11} {'diff (dB)':>10}")
    for st in stages:
        a, b = res["colmap poses"].get(st), res["true poses"][st]
        print(f"{st:<24} {a:13.2f} {b:11.2f} {a - b:10.2f}")
    print(f"budget: {args.steps} NeRF-SH training steps, grid {args.grid}, {args.epochs} "
          f"fine-tune epochs, downscale {args.downscale}; load {load_before[0]:.1f} -> "
          f"{load_after[0]:.1f} on {os.cpu_count()} cores")
    atomic_save_json(args.json or out / "chain.json", {
        "psnr": res, "settings": vars(args), "load_avg_before": load_before,
        "load_avg_after": load_after, "cpu_count": os.cpu_count()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
