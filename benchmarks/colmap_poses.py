"""Camera poses recovered by ``plenoctree process`` (COLMAP) against the lego ground truth.

Method: the 100 lego training photos are area-downscaled to ``--size`` (400²), composited on
white and written as PNGs under ``--work`` (never the repository); ``plenoctree.process``
(the command's own code path, default options unless ``--camera-model`` etc. are given)
recovers the poses; the recovered camera centres are aligned to the true ones by the
least-squares similarity (Umeyama); then per registered image the rotation error (angle of
``R_true^T R_aligned``, degrees) and the centre error (percent of that camera's true
distance to the scene centre) are reported: median, max, the number of outliers (rotation
error > 5°), the registered count and the wall time, with the machine and its load average
(the machine may be shared: wall-clock minutes and the process's CPU minutes are both given). ``--baseline`` also runs pycolmap's
defaults (SIMPLE_RADIAL camera per image, exhaustive matching, no guided matching, default
mapper) on the same photos in the same run.

    python benchmarks/colmap_poses.py --size 400 --out benchmarks/results/colmap_poses.json

``--video N``: the video path instead: the 200 views of the lego test orbit (two turns,
3.6° apart, elevation 7°-47°) at ``--size``² on white as an MP4 (10 fps), ``process`` keeping
N frames (default options: the sharper of each two candidates), the same figures against
the true poses of the frames kept.

    python benchmarks/colmap_poses.py --video 100 --size 320 --out benchmarks/results/video.json

``--real flower|fox|lounge``: a real capture of the data root's ``real/`` (its README)
instead: flower's 34 photos (``images_8``, 504x378) against LLFF's published
``poses_bounds.npy``, fox's 67 video frames (1080x1920) against instant-ngp's
``transforms.json``, lounge's 64 walk-around frames (``images_2``, 960x540) against its
``poses_bounds.npy`` (mip-NeRF 360's layout). Besides the pose errors
it reports what ``process`` wrote against the published file: the focal length (pixels of the
input photos), the principal point's offset from the image centre, and the per-image near /
far depth bounds (flower: in LLFF's units through the similarity's scale, and their ratio).

    python benchmarks/colmap_poses.py --real flower --out benchmarks/results/colmap_flower.json

``--matcher``, ``--max-image-size``, ``--guided``, ``--overlap``, ``--retry``, ``--mapping``
set ``process``'s options (``--mapping incremental global``: one run each, in turn)
(default: its own). The lego scene is ``nerf_synthetic/lego`` of the data root
(``--data-root``); the photos and ``process``'s outputs go under ``--work`` (default
``benchmarks/results/cache/colmap_poses``, kept: a second run reuses the photos).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from _bench import CACHE, add_data_root, add_out, data_path, machine_info, write_json

from plenoctree.datasets.camera_sets import umeyama

OUTLIER_DEG = 5.0


def prepare(lego: Path, size: int, out: Path) -> dict[str, np.ndarray]:
    """Write the training photos of ``lego`` at ``size``² on white; return name -> true
    OpenGL c2w."""
    from PIL import Image

    meta = json.loads((lego / "transforms_train.json").read_text())
    out.mkdir(parents=True, exist_ok=True)
    gt = {}
    for fr in meta["frames"]:
        name = Path(fr["file_path"]).name + ".png"
        gt[name] = np.array(fr["transform_matrix"], dtype=np.float64)
        if (out / name).is_file():
            continue
        im = Image.open(lego / (fr["file_path"] + ".png")).convert("RGBA")
        im = im.resize((size, size), Image.BOX)
        a = np.asarray(im).astype(np.float32) / 255.0
        rgb = a[..., :3] * a[..., 3:] + (1.0 - a[..., 3:])
        Image.fromarray(np.round(rgb * 255).astype(np.uint8)).save(out / name)
    return gt


def prepare_video(lego: Path, size: int, out: Path) -> tuple[Path, list[np.ndarray]]:
    """The test orbit of ``lego`` at ``size``² on white as ``out/lego_orbit_{size}.mp4``;
    returns it and the true OpenGL c2w of each of its frames."""
    from PIL import Image

    meta = json.loads((lego / "transforms_test.json").read_text())
    gt = [np.array(fr["transform_matrix"], dtype=np.float64) for fr in meta["frames"]]
    video = out / f"lego_orbit_{size}.mp4"
    if not video.is_file():
        import imageio.v2 as iio

        frames = []
        for fr in meta["frames"]:
            im = Image.open(lego / (fr["file_path"] + ".png")).convert("RGBA")
            a = np.asarray(im.resize((size, size), Image.BOX)).astype(np.float32) / 255.0
            rgb = a[..., :3] * a[..., 3:] + (1.0 - a[..., 3:])
            frames.append(np.round(rgb * 255).astype(np.uint8))
        out.mkdir(parents=True, exist_ok=True)
        iio.mimwrite(out / f".{video.name}", frames, format="FFMPEG", fps=10, quality=9,
                     macro_block_size=16)
        (out / f".{video.name}").rename(video)
    return video, gt


def pose_errors(est: np.ndarray, ref: np.ndarray) -> dict:
    """Errors of OpenGL c2w ``est [N, 4, 4]`` against ``ref`` after a similarity alignment
    (fitted on all cameras, then refitted without the outliers so that one flipped camera
    does not tilt the others; the outliers stay in the max figures and are counted)."""
    keep = np.ones(len(est), bool)
    for _ in range(2):
        s, r, t = umeyama(est[keep, :3, 3], ref[keep, :3, 3])
        centres = (s * (r @ est[:, :3, 3].T)).T + t
        cerr = (np.linalg.norm(centres - ref[:, :3, 3], axis=1)
                / np.linalg.norm(ref[:, :3, 3], axis=1))
        cos = (np.einsum("nij,nij->n", r @ est[:, :3, :3], ref[:, :3, :3]) - 1) / 2
        rerr = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        keep = rerr <= OUTLIER_DEG
        if keep.sum() < 3:
            break
    return {"rot_median_deg": float(np.median(rerr)), "rot_max_deg": float(rerr.max()),
            "centre_median_pct": float(100 * np.median(cerr)),
            "centre_max_pct": float(100 * cerr.max()),
            "outliers": int((rerr > OUTLIER_DEG).sum())}


REAL = {"flower": "images_8", "fox": "images", "lounge": "images_2"}
"""The real captures of ``real/`` and their photo folders."""


def real_reference(root: Path, folder: str | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """The published poses of a real capture ``root``: photo name -> OpenGL c2w, and
    ``{"focal": pixels of the photos, "cx", "cy": principal point offset from the centre,
    "bounds": name -> (near, far)}`` (bounds: LLFF files only)."""
    from PIL import Image

    from plenoctree.datasets.llff import read_poses_bounds

    if (root / "poses_bounds.npy").is_file():
        c2w, bounds, hwf = read_poses_bounds(root / "poses_bounds.npy")
        photos = root / (folder or REAL[root.name])
        names = sorted(p.name for p in photos.iterdir())      # LLFF's order (lexicographic)
        w = Image.open(photos / names[0]).size[0]
        return (dict(zip(names, c2w)), {"focal": float(hwf[0, 2] * w / hwf[0, 1]), "cx": 0.0,
                "cy": 0.0, "bounds": dict(zip(names, bounds.tolist()))})
    meta = json.loads((root / "transforms.json").read_text())
    gt = {Path(f["file_path"]).name: np.array(f["transform_matrix"], dtype=np.float64)
          for f in meta["frames"]}
    return gt, {"focal": float(meta["fl_x"]), "cx": meta["cx"] - meta["w"] / 2,
                "cy": meta["cy"] - meta["h"] / 2, "bounds": {}}


def process_intrinsics(out: Path) -> dict:
    """Focal length and principal-point offset (pixels) of ``process``'s undistorted camera
    (``out/colmap/sparse/0``, before the crop), and the size it wrote."""
    from plenoctree.datasets.colmap_model import read_colmap_model

    cam = next(iter(read_colmap_model(out / "colmap" / "sparse" / "0").cameras.values()))
    p = cam.params
    f, cx, cy = (p[0], p[1], p[2]) if cam.model == "SIMPLE_PINHOLE" else (p[0], p[2], p[3])
    return {"focal": float(f), "cx": float(cx - cam.width / 2), "cy": float(cy - cam.height / 2),
            "undistorted_size": [cam.width, cam.height]}


def compare_bounds(est: dict, ref: dict, scale: float) -> dict:
    """Near / far of ``process`` (``est``: name -> (near, far), its units times ``scale``, the
    similarity's) against the published ones: medians and the ratio far / near overall."""
    names = sorted(set(est) & set(ref))
    e = np.array([est[n] for n in names]) * scale
    r = np.array([ref[n] for n in names])
    return {"near_median": float(np.median(e[:, 0])), "far_median": float(np.median(e[:, 1])),
            "ref_near_median": float(np.median(r[:, 0])),
            "ref_far_median": float(np.median(r[:, 1])),
            "ratio": float(e[:, 1].max() / e[:, 0].min()),
            "ref_ratio": float(r[:, 1].max() / r[:, 0].min())}


def read_output(out: Path) -> tuple[np.ndarray, list[str], dict]:
    """OpenGL c2w, the photo names and (LLFF output) name -> bounds of a ``process`` output."""
    from plenoctree.datasets.llff import read_poses_bounds

    if (out / "poses_bounds.npy").is_file():
        c2w, bounds, _ = read_poses_bounds(out / "poses_bounds.npy")
        names = sorted(p.name for p in (out / "images").iterdir())
        return c2w, names, dict(zip(names, bounds.tolist()))
    tj = json.loads((out / "transforms.json").read_text())
    return (np.array([f["transform_matrix"] for f in tj["frames"]]),
            [f["colmap_name"] for f in tj["frames"]], {})


def run_process(images: Path, out: Path, sfm, frames: int = 150
                ) -> tuple[dict, np.ndarray, list[str], float]:
    from plenoctree.process import ProcessConfig, process

    import resource

    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    summary = process(ProcessConfig(images=str(images), out=str(out), sfm=sfm, overwrite=True,
                                    frames=frames))
    minutes = (time.perf_counter() - t0) / 60
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    summary["cpu_minutes"] = (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime) / 60
    summary["peak_rss_mb"] = r1.ru_maxrss / 1024
    c2w, names, summary["bounds"] = read_output(out)
    return summary, c2w, names, minutes


def main(argv: list[str] | None = None) -> int:
    from plenoctree._log import configure_cli
    from plenoctree.process import SfmOptions

    configure_cli()                          # process's progress lines on stdout

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=400)
    ap.add_argument("--work", default=str(CACHE / "colmap_poses"),
                    help="folder of the photos and process's outputs (kept)")
    ap.add_argument("--camera-model", default=None)
    ap.add_argument("--refine-principal-point", choices=("auto", "on", "off"), default=None,
                    help="process's final bundle adjustment (default: process's off)")
    ap.add_argument("--guided", choices=("on", "off"), default=None)
    ap.add_argument("--matcher", default=None)
    ap.add_argument("--mapping", nargs="+", default=None,
                    choices=("incremental", "global"),
                    help="process's mapper; several: one run of process each, in turn")
    ap.add_argument("--max-image-size", type=int, default=None)
    ap.add_argument("--overlap", type=int, default=None, help="sequential_overlap")
    ap.add_argument("--retry", choices=("on", "off"), default=None,
                    help="register the left-out images again (default: process's on)")
    ap.add_argument("--real", choices=sorted(REAL), default=None,
                    help="a real capture of the data root's real/ instead of lego")
    ap.add_argument("--folder", default=None,
                    help="the --real capture's photo folder (default: images_8 for flower, "
                         "images for fox, images_2 for lounge)")
    ap.add_argument("--baseline", action="store_true",
                    help="also run pycolmap's defaults on the same photos")
    ap.add_argument("--video", type=int, default=0, metavar="N",
                    help="the video path: the lego test orbit as an MP4, N frames kept")
    add_data_root(ap)
    add_out(ap, "colmap_poses.json")
    args = ap.parse_args(argv)
    lego = data_path(args.data_root, "nerf_synthetic", "lego")
    real = data_path(args.data_root, "real", args.real) if args.real else None
    if not (lego / "transforms_train.json").is_file() and real is None:
        print(f"lego not found at {lego}", file=sys.stderr)
        return 2
    work = Path(args.work)
    ref_info: dict = {}
    if real is not None:
        source = real / (args.folder or REAL[args.real])
        gt, ref_info = real_reference(real, args.folder)
    elif args.video:
        source, orbit = prepare_video(lego, args.size, work)
        gt = {f"frame_{k:05d}.png": c for k, c in enumerate(orbit)}
    else:
        source = work / f"images_{args.size}"
        gt = prepare(lego, args.size, source)
    runs = {}
    ours = SfmOptions()
    if args.camera_model:
        ours.camera_model = args.camera_model
    if args.refine_principal_point:
        ours.refine_principal_point = args.refine_principal_point
    for flag, name in (("matcher", "matcher"), ("max_image_size", "max_image_size"),
                       ("overlap", "sequential_overlap")):
        if getattr(args, flag) is not None:
            setattr(ours, name, getattr(args, flag))
    if args.guided:
        ours.guided_matching = args.guided == "on"
    if args.retry:
        ours.retry = args.retry == "on"
    variants = [("process defaults", ours)]
    if args.mapping:
        from dataclasses import replace

        variants = [(f"mapping {m}", replace(ours, mapping=m)) for m in args.mapping]
    if args.baseline:
        variants.append(("pycolmap defaults", SfmOptions(
            camera_model="SIMPLE_RADIAL", single_camera=False, guided_matching=False,
            mapper={})))
    load_before = os.getloadavg()
    for name, opts in variants:
        print(f"{name}: {opts}", flush=True)
        out = work / f"{args.real or 'lego'}_{name.replace(' ', '_')}"
        summary, c2w, names, minutes = run_process(source, out, opts, frames=args.video or 150)
        ref = np.stack([gt[n] for n in names])
        row = {"registered": len(names), "images": summary["n_images"],
               "models": summary["n_models"], "pairs": summary.get("pairs"),
               "retry": summary.get("retry"),
               "minutes": minutes, "cpu_minutes": summary["cpu_minutes"],
               "peak_rss_mb": summary["peak_rss_mb"], "kind": summary["kind"],
               **pose_errors(c2w, ref), "options": {k: v for k, v in vars(opts).items()},
               "seconds": summary["seconds"], "image_size": summary["image_size"]}
        if real is not None:
            row["intrinsics"] = {"process": process_intrinsics(out),
                                 "published": {k: ref_info[k] for k in ("focal", "cx", "cy")}}
            if ref_info["bounds"] and summary["bounds"]:
                s_est = umeyama(c2w[:, :3, 3], ref[:, :3, 3])[0]
                row["bounds"] = compare_bounds(summary["bounds"],
                                               ref_info["bounds"], s_est)
        runs[name] = row
    machine = machine_info(load_before)
    hdr = (f"{'run':<20} {'reg':>7} {'rot med':>8} {'rot max':>8} {'ctr med%':>9} "
           f"{'ctr max%':>9} {'outl':>5} {'min':>6} {'cpu min':>7}")
    print(hdr)
    for name, r in runs.items():
        print(f"{name:<20} {r['registered']:>3}/{r['images']:<3} {r['rot_median_deg']:8.3f} "
              f"{r['rot_max_deg']:8.3f} {r['centre_median_pct']:9.3f} {r['centre_max_pct']:9.3f} "
              f"{r['outliers']:5d} {r['minutes']:6.2f} {r['cpu_minutes']:7.2f}")
    print(f"load average before {load_before[0]:.1f}, after {machine['loadavg'][0]:.1f} on "
          f"{machine['cpu_count']} cores")
    import pycolmap

    for name, r in runs.items():
        print(f"{name}: {r['models']} model(s), {r['pairs']} pairs matched"
              + (f", retry {r['retry']}" if r.get("retry") else ""))
        if "intrinsics" in r:
            print(f"{name}: focal {r['intrinsics']['process']['focal']:.1f} px (published "
                  f"{r['intrinsics']['published']['focal']:.1f}); seconds "
                  + ", ".join(f"{k} {v:.0f}" for k, v in r["seconds"].items())
                  + f"; peak RSS {r['peak_rss_mb']:.0f} MB")
        if "bounds" in r:
            b = r["bounds"]
            print(f"{name}: near/far median {b['near_median']:.1f}/{b['far_median']:.1f} "
                  f"(published {b['ref_near_median']:.1f}/{b['ref_far_median']:.1f}), far/near "
                  f"ratio {b['ratio']:.1f} (published {b['ref_ratio']:.1f})")
    out = write_json(args.out, {
        "benchmark": "colmap_poses", "real": args.real, "size": args.size,
        "video_frames": args.video,
        "runs": runs, "pycolmap": pycolmap.__version__, "machine": machine,
        "goals": {"rot_median_deg": 0.5, "centre_pct": 1.0, "outliers": 0,
                  "registered_frac": 0.95, "minutes": 10}})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
