"""Dataset loading time and peak memory per format (Blender, LLFF, NSVF, nerfstudio).

Usage: ``python benchmarks/dataset_load.py [--n 100] [--width 1008 --height 756]
[--repeat 3] [--tmp DIR] [--out PATH.json]``

For each format a synthetic ``--n``-image scene at ``--width x --height`` is written under
``--tmp`` (default: a new temporary folder, removed afterwards unless ``--keep``) in that
format's layout (images: a few procedural-scene renders upsampled, cycled
over the frames and hard-linked; Blender RGBA PNG, NSVF RGB PNG, LLFF and nerfstudio JPEG as
those captures usually are). Each load runs in a fresh subprocess (``load_dataset(dir,
split)`` with format auto-detection; all ``--n`` images, split "all" / Blender "train"; a
process each, so that its peak memory is its own) and reports wall time and the process's peak RSS above its level after ``import plenoctree``.
Baseline measured in the same run: decoding the same files with PIL alone into uint8 arrays
(no conversion, compositing or float copies), single- and multi-threaded as the loader.
Median (and half-range) of ``--repeat`` runs; files are in the page cache (just written).
Prints a table, writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _bench import Timing, add_out, child_json, machine_info, markdown_table, write_json

_WORKER = r"""
import json, os, resource, sys, time
mode, fmt, root, split = sys.argv[1:5]
def rss_kb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
if mode == "load":
    import PIL.Image, PIL.PngImagePlugin, PIL.JpegImagePlugin
    import plenoctree
    from plenoctree.datasets import load_dataset
    base = rss_kb()
    t0 = time.perf_counter()
    ds = load_dataset(root, split)
    dt = time.perf_counter() - t0
    nbytes = ds.images.nbytes + (0 if ds.alphas is None else ds.alphas.nbytes)
    n = len(ds)
else:
    from concurrent.futures import ThreadPoolExecutor
    import numpy as np
    from PIL import Image
    import PIL.PngImagePlugin, PIL.JpegImagePlugin
    files = sorted(p for p in open(root).read().split("\n") if p)
    base = rss_kb()
    def dec(p):
        with Image.open(p) as im:
            return np.asarray(im)
    t0 = time.perf_counter()
    threads = min(8, os.cpu_count() or 1)
    with ThreadPoolExecutor(threads) as pool:
        arrs = list(pool.map(dec, files))
    dt = time.perf_counter() - t0
    nbytes = sum(a.nbytes for a in arrs)
    n = len(arrs)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"seconds": dt, "peak_mb": (peak - base) / 1024.0, "array_mb": nbytes / 2**20,
                  "n": n}))
"""


def _views(width: int, height: int, k: int = 6) -> list[np.ndarray]:
    """``k`` RGBA uint8 renders of the procedural scene, upsampled to ``width x height``."""
    from PIL import Image

    from plenoctree.datasets import generate_rays
    from plenoctree.datasets.procedural import CAMERA_ANGLE_X, procedural_cameras, render_field

    w, h = max(8, width // 6), max(6, height // 6)
    f = 0.5 * w / np.tan(0.5 * CAMERA_ANGLE_X)
    out = []
    for c2w in procedural_cameras(k, "random", seed=5):
        o, d = generate_rays(c2w, f, f, w / 2, h / 2, w, h)
        rgb, a = render_field(o, d, n_samples=48)
        with np.errstate(divide="ignore", invalid="ignore"):
            straight = np.where(a[..., None] > 0, (rgb - (1 - a[..., None])) / a[..., None], 0)
        rgba = np.concatenate([np.clip(straight, 0, 1), a[..., None]], -1)
        im = Image.fromarray((rgba * 255).round().astype(np.uint8), "RGBA")
        out.append(np.asarray(im.resize((width, height), Image.Resampling.BICUBIC)))
    return out


def _save(views: list[np.ndarray], paths: list[Path], mode: str) -> None:
    """Write view ``i % len(views)`` to ``paths[i]``, hard-linking repeats."""
    from PIL import Image

    first: dict[int, Path] = {}
    for i, p in enumerate(paths):
        p.parent.mkdir(parents=True, exist_ok=True)
        k = i % len(views)
        if k in first:
            os.link(first[k], p)
            continue
        v = views[k]
        if mode == "RGBA":
            Image.fromarray(v, "RGBA").save(p)
        else:
            a = v[..., 3:4].astype(np.float32) / 255
            rgb = (v[..., :3] * a + 255 * (1 - a)).round().astype(np.uint8)
            Image.fromarray(rgb, "RGB").save(p, quality=95)
        first[k] = p


def write_scenes(tmp: Path, n: int, width: int, height: int) -> dict[str, tuple[Path, list[Path]]]:
    """Write the four scenes; returns ``{format: (root, image files)}``."""
    from plenoctree.datasets.forward_facing import forward_facing_cameras
    from plenoctree.datasets.procedural import procedural_cameras

    views = _views(width, height)
    sphere = procedural_cameras(n, "random", seed=0)
    f = 0.5 * width / np.tan(0.5 * 0.6911112070083618)
    out = {}
    # Blender
    root = tmp / "blender"
    files = [root / "train" / f"r_{i}.png" for i in range(n)]
    _save(views, files, "RGBA")
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": m.tolist()}
              for i, m in enumerate(sphere)]
    (root / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.6911112070083618, "frames": frames}))
    out["blender"] = (root, files)
    # LLFF
    root = tmp / "llff"
    files = [root / "images" / f"IMG_{i:04d}.JPG" for i in range(n)]
    _save(views, files, "RGB")
    ff = forward_facing_cameras(n)
    m = np.stack([-ff[:, :3, 1], ff[:, :3, 0], ff[:, :3, 2], ff[:, :3, 3],
                  np.tile([height, width, f], (n, 1))], 2)
    np.save(root / "poses_bounds.npy",
            np.concatenate([m.reshape(n, 15), np.tile([3.0, 5.0], (n, 1))], 1))
    out["llff"] = (root, files)
    # NSVF
    root = tmp / "nsvf"
    files = [root / "rgb" / f"0_{i:04d}.png" for i in range(n)]
    _save(views, files, "RGB")
    (root / "pose").mkdir(parents=True, exist_ok=True)
    for i, c in enumerate(sphere):
        cv = c @ np.diag([1.0, -1.0, -1.0, 1.0])
        (root / "pose" / f"0_{i:04d}.txt").write_text(
            "\n".join(" ".join(f"{v:.9g}" for v in row) for row in cv))
    (root / "intrinsics.txt").write_text(f"{f} 0 {width / 2} 0\n0 {f} {height / 2} 0\n"
                                         "0 0 1 0\n0 0 0 1\n")
    (root / "bbox.txt").write_text("-1 -1 -1 1 1 1 0.1\n")
    out["nsvf"] = (root, files)
    # nerfstudio
    root = tmp / "nerfstudio"
    files = [root / "images" / f"frame_{i + 1:05d}.jpg" for i in range(n)]
    _save(views, files, "RGB")
    frames = [{"file_path": f"images/{p.name}", "transform_matrix": c.tolist()}
              for p, c in zip(files, sphere)]
    (root / "transforms.json").write_text(json.dumps(
        {"camera_model": "OPENCV", "fl_x": f, "fl_y": f, "cx": width / 2, "cy": height / 2,
         "w": width, "h": height, "k1": 0, "k2": 0, "p1": 0, "p2": 0, "aabb_scale": 1,
         "frames": frames}))
    out["nerfstudio"] = (root, files)
    return out


def _stat(runs: list[dict], key: str) -> Timing:
    """``key`` of the runs as a timing (median, spread, min)."""
    return Timing([r[key] for r in runs])


def measure(fmt: str, root: Path, files: list[Path], tmp: Path, args: argparse.Namespace
            ) -> dict:
    """The row of one format: ``--repeat`` loads and PIL decodes, a fresh process each."""
    split = "train" if fmt == "blender" else "all"
    listing = tmp / f"{fmt}-files.txt"
    listing.write_text("\n".join(str(p) for p in files))
    loads = [child_json(["-c", _WORKER, "load", fmt, root, split]) for _ in range(args.repeat)]
    bases = [child_json(["-c", _WORKER, "decode", fmt, listing, split])
             for _ in range(args.repeat)]
    assert all(r["n"] == args.n for r in loads + bases)
    t, mem = _stat(loads, "seconds"), _stat(loads, "peak_mb")
    bt, bmem = _stat(bases, "seconds"), _stat(bases, "peak_mb")
    return {"format": fmt, "n_images": args.n, "width": args.width, "height": args.height,
            "file_type": files[0].suffix, "load_s": t.median, "load_s_halfrange": t.spread,
            "load_s_min": min(t.wall), "peak_mb": mem.median, "peak_mb_halfrange": mem.spread,
            "arrays_mb": loads[0]["array_mb"], "baseline_decode_s": bt.median,
            "baseline_decode_s_halfrange": bt.spread, "baseline_decode_s_min": min(bt.wall),
            "baseline_decode_peak_mb": bmem.median}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--width", type=int, default=1008)
    ap.add_argument("--height", type=int, default=756)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--tmp", default=None,
                    help="folder for the scenes (emptied first; default: a new temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the written scenes")
    add_out(ap, "dataset_load.json")
    args = ap.parse_args(argv)
    tmp = Path(args.tmp) if args.tmp else Path(tempfile.mkdtemp(prefix="plenoctree-dsbench-"))
    if args.tmp and tmp.exists():
        shutil.rmtree(tmp)
    t0 = time.perf_counter()
    try:
        scenes = write_scenes(tmp, args.n, args.width, args.height)
        print(f"wrote 4 scenes of {args.n} images {args.width}x{args.height} in "
              f"{time.perf_counter() - t0:.1f} s under {tmp}")
        rows = [measure(fmt, root, files, tmp, args) for fmt, (root, files) in scenes.items()]
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    print()
    print(markdown_table(
        ["format", "files", "load s median ± half-range (min)", "peak MB", "arrays MB",
         "PIL decode s (baseline, min)", "load / decode (min)"],
        [[r["format"], r["file_type"], f"{r['load_s']:.2f} ± {r['load_s_halfrange']:.2f} "
          f"({r['load_s_min']:.2f})", f"{r['peak_mb']:.0f}", f"{r['arrays_mb']:.0f}",
          f"{r['baseline_decode_s']:.2f} ({r['baseline_decode_s_min']:.2f})",
          f"{r['load_s_min'] / r['baseline_decode_s_min']:.2f}x"] for r in rows]))
    meta = {"threads": min(8, os.cpu_count() or 1), "repeat": args.repeat,
            "note": "wall time of load_dataset (auto-detect) in a fresh process; peak RSS above "
                    "the post-import level; page cache warm"}
    out = write_json(args.out, {"benchmark": "dataset_load", "machine": machine_info(),
                                "meta": meta, "results": rows})
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
