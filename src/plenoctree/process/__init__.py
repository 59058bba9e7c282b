"""``plenoctree process``: photos or a video → camera poses (COLMAP) → a dataset the chain reads.

Steps: list and check the photos (or pick sharp, evenly spread frames of a video,
:mod:`.frames`); SIFT features, matching and incremental mapping with pycolmap (:mod:`.sfm`;
the images left out of the largest model are tried again, :mod:`.register`, and the largest
model is kept); COLMAP's undistortion to a pinhole camera; the scene normalised
(:func:`plenoctree.datasets.colmap.normalize_scene`: 360° object vs forward-facing decided from
the cameras); the dataset written in the format that carries that choice, so ``run`` needs no
flags:

* 360° capture → nerfstudio ``transforms.json`` (normalised OpenGL poses, ``PINHOLE`` camera,
  the scene cube as instant-ngp's ``aabb_scale`` 1 / ``scale`` / ``offset``) + ``images/``;
* forward-facing → LLFF ``poses_bounds.npy`` (+ ``images/``), which the LLFF loader reads with
  NDC rays.

Both get the downscaled copies ``images_2/``, ``images_4/``, ``images_8/`` the loaders use
for ``downscale``; undistorted images are cropped to a multiple of 8 pixels (forward-facing:
about the principal point, which LLFF assumes centred). ``colmap/sparse/0`` keeps the
undistorted COLMAP model, ``process.json`` what happened. Everything is written into a
temporary sibling folder that replaces ``out`` only when complete: a failure leaves no
half-written output.
"""

from __future__ import annotations

import logging
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .frames import (VIDEO_SUFFIXES, in_capture_order, is_video, list_photos,
                     require_video_reader, video_frames)
from .sfm import EXHAUSTIVE_MAX_IMAGES, ProcessError, SfmOptions, require_pycolmap, run_sfm

__all__ = ["ProcessConfig", "process", "ProcessError", "SfmOptions", "DOWNSCALES"]

logger = logging.getLogger(__name__)

DOWNSCALES = (2, 4, 8)


@dataclass
class ProcessConfig:
    """Settings of ``plenoctree process``."""

    images: str = ""
    """folder of photos (PNG / JPEG) or a video file"""
    out: str = ""
    """output dataset folder"""
    scene: str = "auto"
    """capture kind: auto (from the cameras), 360 (object seen from around) or forward (NDC)"""
    frames: int = 150
    """video only: frames kept (evenly spread, the blurriest candidates dropped)"""
    drop_blurry: float = 0.5
    """video only: fraction of the evenly spaced candidate frames dropped, each kept frame the
    sharpest of its run of 1 / (1 - drop) consecutive candidates (0.5: the sharper of two)"""
    overwrite: bool = False
    """replace an existing output folder"""
    sfm: SfmOptions = field(default_factory=SfmOptions)
    """COLMAP options (camera model, matcher, features, ...)"""

    def validated(self, need_out: bool = True) -> "ProcessConfig":
        """Check the options, the input's existence and the packages it needs, without
        reading the photos (``run --images`` calls it before any stage runs).

        Raises:
            ConfigError: a bad option value, no ``images`` (or ``out`` with ``need_out``).
            ProcessError: the input is missing, pycolmap (or imageio-ffmpeg for a video)
                is not installed.
        """
        from ..datasets.colmap import KINDS
        from .sfm import check_options

        if not self.images or (need_out and not self.out):
            raise ConfigError("both the images (folder or video) and --out are needed")
        if self.scene not in KINDS:
            raise ConfigError(f"--scene must be one of {', '.join(KINDS)}, got {self.scene!r}")
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or self.frames < 3:
            raise ConfigError(f"--frames must be an integer >= 3, got {self.frames!r}")
        if not 0 <= float(self.drop_blurry) < 1:
            raise ConfigError(f"--drop-blurry must be in [0, 1), got {self.drop_blurry!r}")
        check_options(self.sfm)
        src = Path(self.images)
        if not src.exists():
            raise ProcessError(f"{src}: no such folder of photos or video file")
        if src.is_file() and not is_video(src):
            raise ProcessError(f"{src}: not a folder of photos or a video file "
                               f"({', '.join(VIDEO_SUFFIXES)})")
        require_pycolmap()
        if is_video(src):
            require_video_reader()
        return self


def _check_out(out: Path, overwrite: bool) -> None:
    from .._util import check_output_dir

    check_output_dir(out)
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ConfigError(f"{out}: output folder exists and is not empty; choose another "
                          "--out or pass --overwrite")


def process(cfg: ProcessConfig) -> dict:
    """Run the whole processing (module docstring); returns the ``process.json`` summary.

    Raises:
        ProcessError: bad input photos / video, pycolmap missing, SfM failure.
        ConfigError: bad options or an existing output without ``overwrite``.
    """
    if not cfg.images or not cfg.out:
        raise ConfigError("both the images (folder or video) and --out are needed")
    src, out = Path(cfg.images), Path(cfg.out)
    _check_out(out, cfg.overwrite)
    video = is_video(src)
    if not video:
        photos = list_photos(src, cfg.sfm.single_camera)       # fail fast on bad photos
    cfg.validated()
    t_start = time.perf_counter()
    stage = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    try:
        work = stage / ".work"
        if video:
            photos = video_frames(src, work / "frames", cfg.frames, cfg.drop_blurry)
        image_dir = photos[0].parent
        names = [p.name for p in photos]
        logger.info(f"process: {len(names)} images from {src}")
        ordered = video or (len(names) > EXHAUSTIVE_MAX_IMAGES and in_capture_order(photos))
        res = run_sfm(image_dir, work, names, cfg.sfm, sequential=ordered, label=src,
                      scene=cfg.scene)
        summary = _write_dataset(res, image_dir, names, stage, work, cfg)
        summary.update(source=str(src), video=video, seconds_total=time.perf_counter() - t_start,
                       config={k: v for k, v in asdict(cfg).items()})
        shutil.rmtree(work)
        (stage / "process.json").write_text(json.dumps(summary, indent=1, default=str))
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            out.rename(old)
            stage.rename(out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            stage.rename(out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    logger.info(f"process: wrote {summary['format']} dataset ({summary['kind']} capture, "
        f"{summary['n_registered']} of {summary['n_images']} images registered) to {out}")
    logger.info("process: " + ", ".join(f"{k.replace('_', ' ')} {v:.0f} s"
                                        for k, v in summary["seconds"].items())
                + f" (total {summary['seconds_total']:.0f} s)")
    return summary


def _crop_box(w: int, h: int, cx: float, cy: float, centred: bool) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: a crop with sides a multiple of 8 (centred on the principal point
    when ``centred``)."""
    if centred:
        hw, hh = min(cx, w - cx), min(cy, h - cy)
        cw, ch = int(2 * hw) // 8 * 8, int(2 * hh) // 8 * 8
        x0, y0 = int(round(cx - cw / 2)), int(round(cy - ch / 2))
        return x0, y0, x0 + cw, y0 + ch
    return 0, 0, w // 8 * 8, h // 8 * 8


MIN_TRACK = 3
"""Points seen by fewer images do not bound the depths (:func:`observed_points`)."""


def observed_points(rec, names: list[str], min_track: int = MIN_TRACK) -> list[np.ndarray]:
    """The world points ``[P_i, 3]`` each image of ``names`` observes in the reconstruction
    ``rec`` (a ``pycolmap.Reconstruction``) that at least ``min_track`` images see (all it
    observes when fewer than 10 are).

    LLFF bounds each image's depths by the points it observes, not by every point in front of
    it (points beside the view, closer than anything in it, put the near plane of flower's
    photos ~4x too close); two-view points are left out as well: on flower the closest ones
    are two-view triangulations with 3-4x the median reprojection error, 3-7x closer than
    anything else in the photo (docs/capture.md).
    """
    by_name = {im.name: im for im in rec.images.values()}
    out = []
    for n in names:
        ids = [p.point3D_id for p in by_name[n].points2D if p.has_point3D()]
        kept = [i for i in ids if rec.points3D[i].track.length() >= min_track]
        ids = kept if len(kept) >= 10 else ids
        out.append(np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3))
    return out


def _holdout_lists(names: list[str], reg: list[str], paths: list[str]) -> dict:
    """``train/val/test_filenames`` of a written capture: the photos held out are every
    ``HOLDOUT``-th of the *input* photos sorted by name (``names``), so a chain on these poses
    is scored on the same photos as one on the capture's published poses, whichever photos
    failed to register. ``reg``: registered input names, ``paths``: their written file paths.
    Empty (the loader's own rule) when no held-out photo registered."""
    from ..datasets._files import HOLDOUT

    held = {n for i, n in enumerate(sorted(names)) if i % HOLDOUT == 0}
    test = [p for n, p in zip(reg, paths) if n in held]
    train = [p for n, p in zip(reg, paths) if n not in held]
    if not test or not train:
        return {}
    return {"train_filenames": train, "val_filenames": test, "test_filenames": test}


def _write_dataset(res, image_dir: Path, names: list[str], stage: Path, work: Path,
                   cfg: ProcessConfig) -> dict:
    """Undistort, normalise and write the dataset into ``stage``; returns the summary."""
    import pycolmap
    from PIL import Image

    from ..datasets.colmap import capture_kind, depth_bounds, normalize_scene
    from ..datasets.colmap_model import colmap_c2w, read_colmap_model
    from ..datasets.llff import POSES_FILE

    t0 = time.perf_counter()
    sparse = work / "model"
    sparse.mkdir(parents=True, exist_ok=True)
    res.reconstruction.write(sparse)
    und = work / "undistorted"
    pycolmap.logging.minloglevel = 2
    pycolmap.undistort_images(und, sparse, image_dir, output_type="COLMAP")
    model = read_colmap_model(und / "sparse")
    order = sorted(model.images, key=lambda i: model.images[i][0])
    reg = [model.images[i][0] for i in order]
    raw_c2w = np.stack([colmap_c2w(model.images[i][2], model.images[i][3]) for i in order])
    kind = capture_kind(raw_c2w) if cfg.scene == "auto" else cfg.scene
    frame = normalize_scene(raw_c2w, model.points, kind)
    forward = frame.kind == "forward"
    cams = [model.cameras[model.images[i][1]] for i in order]
    intr = []
    sizes = set()
    for c in cams:
        p = c.params
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if c.model == "SIMPLE_PINHOLE" else p[:4]
        x0, y0, x1, y1 = _crop_box(c.width, c.height, cx, cy, forward)
        intr.append((fx, fy, cx - x0, cy - y0, x0, y0, x1, y1))
        sizes.add((x1 - x0, y1 - y0))
    if len(sizes) != 1:
        raise ProcessError(f"{image_dir}: the undistorted cameras differ in size {sorted(sizes)}; "
                           "use one camera for all photos (--single-camera)")
    w, h = sizes.pop()
    if w < 8 or h < 8:
        raise ProcessError(f"{image_dir}: undistorted images are too small ({w}x{h})")
    suffix = ".png" if all(Path(n).suffix.lower() == ".png" for n in reg) else ".jpg"
    digits = max(5, len(str(len(reg))))
    out_names = [f"{Path(n).stem}{suffix}" if len(set(Path(n).stem for n in reg)) == len(reg)
                 else f"frame_{j:0{digits}d}{suffix}" for j, n in enumerate(reg)]
    fmt = "PNG" if suffix == ".png" else "JPEG"
    for folder in ["images"] + [f"images_{f}" for f in DOWNSCALES]:
        (stage / folder).mkdir()
    from .._util import progress

    for j, n in enumerate(progress(reg, desc="writing images", unit="img")):
        x0, y0, x1, y1 = (int(v) for v in intr[j][4:])
        with Image.open(und / "images" / n) as im:
            im = im.convert("RGB").crop((x0, y0, x1, y1))
            im.save(stage / "images" / out_names[j], fmt, quality=95)
            for f in DOWNSCALES:
                im.resize((w // f, h // f), Image.BOX).save(
                    stage / f"images_{f}" / out_names[j], fmt, quality=95)
    k = np.array([v[:4] for v in intr])
    bounds = depth_bounds(raw_c2w, observed_points(res.reconstruction, reg))  # as LLFF
    if forward:
        square = np.abs(k[:, 0] - k[:, 1]).max() <= 1e-3 * k[:, 0].max()
        if not square or np.ptp(k[:, 0]) > 1e-6 * k[0, 0]:
            raise ProcessError(f"{image_dir}: a forward-facing (LLFF) dataset needs one square-"
                               "pixel camera (use --camera-model SIMPLE_RADIAL or "
                               "SIMPLE_PINHOLE with --single-camera), or --scene 360")
        m = np.zeros((len(reg), 3, 5))
        m[:, :, 0], m[:, :, 1] = -raw_c2w[:, :3, 1], raw_c2w[:, :3, 0]
        m[:, :, 2], m[:, :, 3] = raw_c2w[:, :3, 2], raw_c2w[:, :3, 3]
        m[:, :, 4] = [h, w, k[0, 0]]
        np.save(stage / POSES_FILE, np.concatenate([m.reshape(len(reg), 15), bounds], 1))
        fmt_name = "llff"
    else:
        half = float(frame.bbox[1, 0])
        top = {"camera_model": "PINHOLE", "w": w, "h": h, "aabb_scale": 1,
               "scale": 0.5 / half, "offset": [0.5, 0.5, 0.5]}
        shared = np.ptp(k, axis=0).max() < 1e-6 * k[0, 0]
        if shared:
            top.update(fl_x=k[0, 0], fl_y=k[0, 1], cx=k[0, 2], cy=k[0, 3])
        frames = []
        for j in range(len(reg)):
            fr = {"file_path": f"images/{out_names[j]}",
                  "transform_matrix": frame.c2w[j].tolist(), "colmap_name": reg[j]}
            if not shared:
                fr.update(fl_x=k[j, 0], fl_y=k[j, 1], cx=k[j, 2], cy=k[j, 3])
            frames.append(fr)
        top["frames"] = frames
        top.update(_holdout_lists(names, reg, [f["file_path"] for f in frames]))
        top["plenoctree_transform"] = frame.transform.tolist()
        # the content's depths (LLFF's rule, normalised units): the loader's near plane
        top["plenoctree_bounds"] = [float(bounds[:, 0].min() * frame.scale),
                                    float(bounds[:, 1].max() * frame.scale)]
        (stage / "transforms.json").write_text(json.dumps(top, indent=1))
        fmt_name = "nerfstudio"
    model_out = stage / "colmap" / "sparse" / "0"
    model_out.mkdir(parents=True)
    for p in (und / "sparse").iterdir():
        shutil.copy2(p, model_out / p.name)
    logger.info(f"process: {frame.kind} capture -> {fmt_name} dataset, images {w}x{h}")
    return {"format": fmt_name, "kind": frame.kind, "n_images": len(names),
            "n_registered": len(reg), "n_models": res.n_models, "pairs": res.pairs,
            "retry": res.retry,
            "unregistered": sorted(set(names) - set(reg)), "image_size": [w, h],
            "camera": cams[0].model, "seconds": {**res.seconds,
                                                 "undistort_write": time.perf_counter() - t0},
            "scene_scale": frame.scale,
            "scene_bbox": None if frame.bbox is None else frame.bbox.tolist()}
