"""Videos of a tree: camera paths (orbit, a dataset's own cameras, an LLFF spiral), colour /
depth / side-by-side frames, MP4 written through imageio + imageio-ffmpeg (``plenoctree[video]``).

>>> cams = orbit_cameras(tree.center, 4.0, 120, 400, 400)     # doctest: +SKIP
>>> make_video(VideoConfig(tree="tree.npz", out="orbit.mp4"))  # doctest: +SKIP

The camera paths themselves (orbit convention, up axis, NDC spiral) live in
:mod:`plenoctree.datasets.trajectories` and are re-exported here. Same layer as
:mod:`plenoctree.evaluation`.
"""

from __future__ import annotations

import logging
import dataclasses
import importlib.util
import math
import os
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._util import progress, to_uint8
from .datasets import Cameras
from .datasets.trajectories import (DEFAULT_FOV_X, DEFAULT_FRAMES, UP_AXES, axis_vector,
                                    check_frames, check_size, detect_up_axis, fit_radius,
                                    ndc_spiral_cameras, orbit_cameras, orbit_poses)
from .errors import BackendError, ConfigError, TreeFormatError

__all__ = ["PATHS", "MODES", "UP_AXES", "VideoConfig", "VideoResult", "axis_vector",
           "ndc_spiral_cameras", "detect_up_axis", "fit_radius", "orbit_poses", "orbit_cameras",
           "resize_cameras", "depth_bounds", "compose_frame", "pad_even", "write_video",
           "video_cameras", "make_video", "render_path_images"]

logger = logging.getLogger(__name__)

PATHS = ("orbit", "dataset", "spiral")
MODES = ("color", "depth", "both")
DEFAULT_SIZE = 800                   # orbit video size without a dataset (as gen_video.py)
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv")


# --- camera paths ---------------------------------------------------------------------------
def resize_cameras(cams: Cameras, width: int, height: int) -> Cameras:
    """``cams`` rendered at ``width`` x ``height``: intrinsics scaled per axis (the field of
    view is kept)."""
    check_size(width, height)
    return cams.resized(int(width), int(height))


# --- frames ---------------------------------------------------------------------------------
def _ray_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Slab test: entry/exit distances ``[N]`` of rays ``o + t d`` (``d`` unit) with a box."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta, tb = (lo - o) * inv, (hi - o) * inv
    ta = np.where(np.isnan(ta), -np.inf, ta)
    tb = np.where(np.isnan(tb), np.inf, tb)
    return np.minimum(ta, tb).max(axis=1), np.maximum(ta, tb).min(axis=1)


def depth_bounds(tree, cams: Cameras, grid: int = 9) -> tuple[float, float]:
    """A fixed depth range (world units along unit rays, NDC units for NDC cameras) for a whole
    video: min entry / max exit distance of the tree's box over a ``grid`` x ``grid`` pixel
    lattice (corners included) of every camera. Rays missing the box are ignored; if all miss,
    ``(0, 1)``."""
    n = len(cams)
    cols = np.linspace(0, cams.width - 1, grid).round().astype(np.int64)
    rows = np.linspace(0, cams.height - 1, grid).round().astype(np.int64)
    cc, rr = np.meshgrid(cols, rows)
    img = np.repeat(np.arange(n), cc.size)
    o, d = cams.pixel_rays(img, np.tile(cc.ravel(), n), np.tile(rr.ravel(), n))
    o, d = np.asarray(o, dtype=np.float64), np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    bbox = np.asarray(tree.bbox, dtype=np.float64)
    t0, t1 = _ray_box(o, d, bbox[0], bbox[1])
    t0 = np.maximum(t0, 0.0)
    hit = t1 > t0
    if not hit.any():
        return 0.0, 1.0
    return float(t0[hit].min()), float(t1[hit].max())


def compose_frame(out, mode: str, near: float, far: float) -> np.ndarray:
    """Frame float32 in [0, 1] from a :class:`~plenoctree.render.RenderOutput` of one image:
    ``color`` ``[H, W, 3]``, ``depth`` ``[H, W, 3]`` Turbo colour map (near red, far blue,
    empty black, see :func:`~plenoctree.plots.depth_colormap`), ``both`` ``[H, 2W, 3]`` side by
    side."""
    from .plots import depth_colormap

    if mode not in MODES:
        raise ConfigError(f"--mode: expected one of {', '.join(MODES)}, got {mode!r}")
    rgb = out.rgb.detach().cpu().numpy().astype(np.float32)
    if mode == "color":
        return rgb
    depth = depth_colormap(out.depth.detach().cpu().numpy(), out.alpha.detach().cpu().numpy(),
                           near, far, background=(0.0, 0.0, 0.0))
    return depth if mode == "depth" else np.concatenate([rgb, depth], axis=1)


def pad_even(frame: np.ndarray) -> np.ndarray:
    """Pad ``[H, W, 3]`` by repeating the last row / column to even sizes (H.264 with yuv420p
    chroma subsampling needs even dimensions)."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


# --- writing --------------------------------------------------------------------------------
def _imageio():
    for mod in ("imageio", "imageio_ffmpeg"):
        if importlib.util.find_spec(mod) is None:
            raise BackendError(f"writing videos needs the `{mod.replace('_', '-')}` package, "
                               "which is not installed: pip install 'plenoctree[video]'")
    import imageio.v2 as iio
    import imageio_ffmpeg

    try:
        imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError as e:
        raise BackendError(f"imageio-ffmpeg found no ffmpeg executable ({e}); reinstall "
                           "'plenoctree[video]' or set IMAGEIO_FFMPEG_EXE") from None
    return iio


def _prep(frame, path: Path, i: int) -> np.ndarray:
    img = to_uint8(frame)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or min(img.shape[:2]) < 1:
        raise ConfigError(f"{path}: frame {i} has shape {list(img.shape)}, expected [H, W, 3]")
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=-1)
    return pad_even(img[..., :3])


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float = 30.0,
                quality: float = 8.0) -> tuple[int, int, int]:
    """Encode ``frames`` (each ``[H, W, 3]``, uint8 or float in [0, 1], all the same size) as
    H.264 (yuv420p) into ``path`` (``.mp4``, ``.mov`` or ``.mkv``), atomically: a temporary
    file next to it is renamed on success and removed on any error. Odd sizes are padded to
    even ones (:func:`pad_even`). ``quality``: imageio's 0–10 scale (10 = best).

    Frames are consumed one at a time (nothing is held in memory). Returns
    ``(n_frames, width, height)`` of the written video.

    Raises:
        BackendError: imageio / imageio-ffmpeg missing (names the ``plenoctree[video]`` extra).
        ConfigError: no frames, a bad suffix, fps or quality, frames of different sizes.
    """
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise ConfigError(f"{path}: video file must end in {', '.join(VIDEO_SUFFIXES)}")
    if not (np.isfinite(fps) and fps > 0):
        raise ConfigError(f"--fps must be a positive number, got {fps}")
    if not 0 <= quality <= 10:
        raise ConfigError(f"quality must be in [0, 10], got {quality}")
    iio = _imageio()
    it: Iterator[np.ndarray] = iter(frames)
    first = next(it, None)       # rendered before the encoder starts: early errors leave no file
    if first is None:
        raise ConfigError(f"{path}: no frames to write")
    first = _prep(first, path, 0)
    h, w = first.shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    n = 0
    try:
        writer = iio.get_writer(str(tmp), format="FFMPEG", mode="I", fps=float(fps),
                                codec="libx264", pixelformat="yuv420p", quality=quality,
                                macro_block_size=1, ffmpeg_log_level="error")
        try:
            frame = first
            while frame is not None:
                if frame.shape[:2] != (h, w):
                    raise ConfigError(f"{path}: frame {n} is {frame.shape[1]}x{frame.shape[0]}, "
                                      f"the first was {w}x{h}")
                writer.append_data(np.ascontiguousarray(frame))
                n += 1
                nxt = next(it, None)
                frame = None if nxt is None else _prep(nxt, path, n)
        finally:
            writer.close()
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return n, w, h


# --- the command ----------------------------------------------------------------------------
@dataclass
class VideoConfig:
    """What :func:`make_video` renders (``plenoctree video``)."""

    tree: str | Path
    """Tree file: native or svox ``.npz``, ``.plnz`` or svox compressed ``.npz``."""
    out: str | Path | None = None
    """Video file (.mp4/.mov/.mkv); default ``<tree stem>_<path>[_<mode>].mp4`` next to it."""
    data: str | Path | None = None
    """Dataset folder: its cameras give the up axis, radius, field of view and size of an
    orbit; required by the ``dataset`` and ``spiral`` paths."""
    path: str | None = None
    """Camera path: orbit, dataset (the split's own cameras) or spiral (LLFF); default spiral
    for LLFF data, else orbit."""
    split: str = "test"
    """Dataset split whose cameras are used."""
    format: str | None = None
    """Dataset format (one of ``plenoctree.datasets.FORMATS``); None = detect."""
    downscale: int = 1
    """Integer downscale of the dataset's cameras."""
    frames: int | None = None
    """Number of frames; default 120 (orbit, spiral) or every camera (dataset path; fewer are
    picked evenly)."""
    fps: float | None = None
    """Frames per second of the video; default the camera path file's ``fps``, else 30."""
    width: int | None = None
    """Frame width in pixels (with height); default the dataset's, else 800."""
    height: int | None = None
    """Frame height in pixels (with width)."""
    radius: float | None = None
    """Orbit radius, world units; default the median camera distance of the dataset, else the
    distance at which the tree box's bounding sphere fits the view (:func:`fit_radius`)."""
    elevation: float = 30.0
    """Orbit elevation in degrees above the centre (the original gen_video's -30)."""
    up: str = "auto"
    """Orbit up axis: auto (from the dataset's cameras, else +z), or +x, -x, +y, -y, +z, -z."""
    fov: float | None = None
    """Orbit horizontal field of view in degrees; default the dataset's, else 39.6 (Blender)."""
    camera_path: str | Path | None = None
    """nerfstudio camera-path JSON to follow instead of ``path`` (see
    :mod:`plenoctree.camera_path`); ``width``/``height`` override its render size."""
    dataparser_transforms: str | Path | None = None
    """nerfstudio ``dataparser_transforms.json``: maps a nerfstudio-viewer path back to the
    dataset's world."""
    mode: str = "color"
    """color, depth, or both (side by side)."""
    depth_range: tuple[float, float] | None = None
    """Depth mapped to white..black; default the tree box's extent along the rays."""
    backend: str = "auto"
    """Renderer backend: auto, numba, triton or torch."""
    device: str = "auto"
    """Where to render: auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N."""
    stop_thresh: float = 0.01
    """Early ray termination when transmittance < this; 0 disables."""
    renormalize: bool = False
    """svox's fast rule: a ray stopped early (transmittance < --stop-thresh) gets its colour
    divided by its opacity instead of the background; with --stop-thresh 0.1 a faster, slightly
    softer picture"""
    background: tuple[float, float, float] | None = None
    """Background RGB in [0, 1]; None = the dataset's with ``data`` (black for real photos,
    white for renders), else white."""
    quality: float = 8.0
    """H.264 quality on imageio's 0-10 scale."""
    show_progress: bool | None = None
    """Progress bar: None = only on a terminal."""
    overwrite: bool = False
    """replace an existing --out file even if it does not look like a video"""


@dataclass
class VideoResult:
    """What :func:`make_video` wrote and how fast it rendered."""

    out: Path
    path: str                 # orbit | dataset | spiral | camera_path
    mode: str
    n_frames: int
    width: int                # video frame size (side by side and even padding included)
    height: int
    render_width: int         # rendered image size
    render_height: int
    fps: float                # video frame rate
    render_seconds: float     # total render time
    render_fps: float         # 1000 / median ms per frame, the first (warm-up) frame excluded
    depth_range: tuple[float, float]
    up: str | None            # orbit up axis used
    radius: float | None      # orbit radius used
    device: str = "cpu"
    """Where the frames were rendered (cpu, cuda:N)."""

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["out"] = str(self.out)
        d["depth_range"] = list(self.depth_range)
        return d


def _load_data(cfg: VideoConfig):
    from .datasets import load_dataset

    bg = tuple(cfg.background) if cfg.background is not None else None   # the dataset's
    return load_dataset(cfg.data, split=cfg.split, format=cfg.format, downscale=cfg.downscale,
                        background=bg)


def video_cameras(cfg: VideoConfig, tree) -> tuple[Cameras, dict]:
    """The cameras of ``cfg``'s path for ``tree`` and what was chosen (``path``, ``up``,
    ``radius``). Raises :class:`ConfigError` for impossible combinations."""
    from .datasets import FORMATS, detect_format

    if cfg.format is not None and cfg.format not in FORMATS:
        raise ConfigError(f"--format: expected one of {', '.join(FORMATS)}, got {cfg.format!r}")
    if cfg.frames is not None:
        check_frames(cfg.frames)
    if (cfg.width is None) != (cfg.height is None):
        raise ConfigError("--width and --height must be given together")
    if cfg.width is not None:
        check_size(cfg.width, cfg.height)
    if cfg.up not in UP_AXES:
        raise ConfigError(f"--up: expected one of {', '.join(UP_AXES)}, got {cfg.up!r}")
    if cfg.camera_path is not None:
        from .camera_path import load_camera_path

        if cfg.path is not None:
            raise ConfigError("give either --path or --camera-path, not both")
        cp = load_camera_path(cfg.camera_path, cfg.width, cfg.height, cfg.dataparser_transforms)
        if cfg.frames is not None and cfg.frames != len(cp):
            raise ConfigError(f"--frames {cfg.frames}: the camera path {cfg.camera_path} has "
                              f"{len(cp)} frames (leave --frames out)")
        cams = cp.cameras if tree.ndc is None else tree.ndc.apply(cp.cameras)
        return cams, {"path": "camera_path", "up": None, "radius": None, "fps": cp.fps}
    elif cfg.dataparser_transforms is not None:
        raise ConfigError("--dataparser-transforms goes with --camera-path")
    fmt = None
    if cfg.data is not None:
        fmt = cfg.format or detect_format(cfg.data)
    ndc = getattr(tree, "ndc", None)
    kind = cfg.path or ("spiral" if fmt == "llff" or ndc is not None else "orbit")
    if kind not in PATHS:
        raise ConfigError(f"--path: expected one of {', '.join(PATHS)}, got {kind!r}")
    if kind == "orbit" and ndc is not None:
        raise ConfigError(f"{cfg.tree}: a forward-facing (NDC) tree cannot be orbited (it holds "
                          "only what lies in front of its cameras): use --path spiral, "
                          "--path dataset or --camera-path")
    if kind == "spiral" and cfg.data is None and ndc is not None:
        cams = ndc_spiral_cameras(ndc, cfg.frames or DEFAULT_FRAMES)
        if cfg.width is not None and (cams.width, cams.height) != (cfg.width, cfg.height):
            cams = resize_cameras(cams, int(cfg.width), int(cfg.height))
        return cams, {"path": "spiral", "up": None, "radius": None}
    if kind != "orbit" and cfg.data is None:
        raise ConfigError(f"--path {kind} needs --data (the dataset whose cameras to follow)")
    info: dict = {"path": kind, "up": None, "radius": None}
    if kind == "spiral":
        from .datasets import llff_render_cameras

        if fmt != "llff":
            raise ConfigError(f"--path spiral needs an LLFF dataset; {cfg.data} is {fmt}")
        cams = llff_render_cameras(cfg.data, cfg.frames or DEFAULT_FRAMES, cfg.downscale)
    elif kind == "dataset":
        cams = _load_data(cfg).cameras
        if len(cams) == 0:
            raise ConfigError(f"{cfg.data}: split {cfg.split!r} has no cameras")
        if cfg.frames is not None:
            if cfg.frames > len(cams):
                raise ConfigError(f"--frames {cfg.frames}: split {cfg.split!r} of {cfg.data} "
                                  f"has only {len(cams)} cameras")
            cams = cams.select(np.round(np.linspace(0, len(cams) - 1, cfg.frames)).astype(int))
    else:
        data_cams = _load_data(cfg).cameras if cfg.data is not None else None
        if data_cams is not None and data_cams.ndc:
            raise ConfigError(f"{cfg.data}: an orbit needs a 360° scene, this forward-facing "
                              "dataset uses NDC: use --path spiral or --path dataset")
        center = np.asarray(tree.center, dtype=np.float64)
        up = cfg.up if cfg.up != "auto" else (
            detect_up_axis(data_cams.c2w) if data_cams is not None and len(data_cams) else "+z")
        if cfg.width is not None:
            width, height = int(cfg.width), int(cfg.height)
        elif data_cams is not None:
            width, height = data_cams.width, data_cams.height
        else:
            width = height = DEFAULT_SIZE
        if cfg.fov is not None:
            fov = math.radians(cfg.fov)
        elif data_cams is not None and len(data_cams):
            fov = 2.0 * math.atan(0.5 * data_cams.width / data_cams.intrinsics(0)[0])
        else:
            fov = DEFAULT_FOV_X
        radius = cfg.radius
        if radius is None and data_cams is not None and len(data_cams):
            radius = float(np.median(np.linalg.norm(data_cams.centers - center, axis=1)))
        elif radius is None:
            radius = fit_radius(tree.radius, fov, width, height)
        cams = orbit_cameras(center, float(radius), cfg.frames or DEFAULT_FRAMES, width, height,
                             fov, cfg.elevation, up)
        info.update(up=up, radius=float(radius))
    if cfg.width is not None and (cams.width, cams.height) != (cfg.width, cfg.height):
        cams = resize_cameras(cams, int(cfg.width), int(cfg.height))
    return cams, info


def make_video(cfg: VideoConfig) -> VideoResult:
    """Render ``cfg.tree`` along a camera path and write the video (see :class:`VideoConfig`).

    Frames are rendered and encoded one by one; ``render_fps`` counts rendering only (and the
    frame composition), not encoding. Raises TreeFormatError / DatasetError naming the file,
    ConfigError for bad options, BackendError for a missing renderer or video backend (checked
    before anything is rendered).
    """
    from .compression import load_any_tree
    from .device import resolve_device
    from .render import RenderOptions, render_image, tree_to_device

    if cfg.mode not in MODES:
        raise ConfigError(f"--mode: expected one of {', '.join(MODES)}, got {cfg.mode!r}")
    if not 0.0 <= cfg.stop_thresh < 1.0:
        raise ConfigError(f"--stop-thresh must be in [0, 1), got {cfg.stop_thresh}")
    if cfg.depth_range is not None and not cfg.depth_range[0] < cfg.depth_range[1]:
        raise ConfigError(f"--depth-range: need NEAR < FAR, got {cfg.depth_range}")
    _imageio()
    tree_path = Path(cfg.tree)
    if not tree_path.is_file():
        raise TreeFormatError(f"{tree_path}: no such tree file")
    tree = load_any_tree(tree_path)
    device = resolve_device(cfg.device)
    cams, info = video_cameras(cfg, tree)
    kind = info["path"]
    if cfg.out is not None:
        out = Path(cfg.out)
    else:
        tail = "" if cfg.mode == "color" else f"_{cfg.mode}"
        out = tree_path.parent / f"{tree_path.stem}_{kind}{tail}.mp4"
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        raise ConfigError(f"--out {out}: a video file must end in {', '.join(VIDEO_SUFFIXES)}")
    from ._util import check_output_file, run_lock

    check_output_file(out, "--out", cfg.overwrite, kind=None)
    near, far = (tuple(float(v) for v in cfg.depth_range) if cfg.depth_range is not None
                 else depth_bounds(tree, cams))
    if cfg.background is not None:
        bg = tuple(float(b) for b in cfg.background)
    else:
        from .datasets.dataset import RENDER_BACKGROUND, default_background

        bg = default_background(cfg.data, cfg.format) if cfg.data else RENDER_BACKGROUND
    options = RenderOptions(stop_thresh=float(cfg.stop_thresh), background=bg,
                            renormalize=bool(cfg.renormalize))
    ms: list[float] = []
    dev_tree = tree_to_device(tree, device)

    def frames() -> Iterator[np.ndarray]:
        for i in progress(range(len(cams)), desc="video",
                          disable=None if cfg.show_progress is None else not cfg.show_progress):
            t0 = time.perf_counter()
            img = compose_frame(render_image(dev_tree, cams, i, options, cfg.backend,
                                             device=device), cfg.mode, near, far)
            ms.append((time.perf_counter() - t0) * 1e3)
            yield img

    fps = float(cfg.fps or info.get("fps") or 30.0)
    if not fps > 0:
        raise ConfigError(f"--fps must be positive, got {cfg.fps}")
    with run_lock(out, "video", folder=False):
        n, w, h = write_video(out, frames(), fps, cfg.quality)
    timed = ms[1:] if len(ms) > 1 else ms
    res = VideoResult(out=out, path=kind, mode=cfg.mode, n_frames=n, width=w, height=h,
                      render_width=cams.width, render_height=cams.height, fps=fps,
                      render_seconds=sum(ms) / 1e3, render_fps=1000.0 / float(np.median(timed)),
                      depth_range=(near, far), up=info["up"], radius=info["radius"],
                      device=str(device))
    if (w, h) != ((2 if cfg.mode == "both" else 1) * cams.width, cams.height):
        logger.info(f"note: frames padded to even size {w}x{h} for H.264")
    return res


def render_path_images(tree, cams: Cameras, out_dir: str | Path, options=None,
                       backend: str = "auto", depth_range: tuple[float, float] | None = None,
                       show_progress: bool | None = None) -> list[Path]:
    """Render every camera of ``cams`` into ``out_dir`` (no ground truth: no scores).

    Per frame ``i``: ``frame_<i:05d>.png`` colour, ``frame_<i>_depth.png`` Turbo depth over
    ``depth_range`` (default :func:`depth_bounds`), ``frame_<i>_depth.npy`` raw float32 depth
    (0 where nothing was hit). All written atomically. Returns the colour PNG paths.
    """
    from ._util import save_png
    from .plots import depth_colormap
    from .render import RenderOptions, render_image

    options = options or RenderOptions()
    out = Path(out_dir)
    near, far = depth_range if depth_range is not None else depth_bounds(tree, cams)
    paths = []
    for i in progress(range(len(cams)), desc="render", unit="view",
                      disable=None if show_progress is None else not show_progress):
        o = render_image(tree, cams, i, options, backend)
        depth, alpha = o.depth.detach().cpu().numpy(), o.alpha.detach().cpu().numpy()
        stem = out / f"frame_{i:05d}"
        save_png(stem.with_suffix(".png"), o.rgb.detach().cpu().numpy())
        save_png(stem.with_name(stem.name + "_depth.png"),
                 depth_colormap(depth, alpha, near, far, options.background))
        from ._util import atomic_write

        with atomic_write(stem.with_name(stem.name + "_depth.npy"), "wb") as f:
            np.save(f, depth.astype(np.float32), allow_pickle=False)
        paths.append(stem.with_suffix(".png"))
    return paths
