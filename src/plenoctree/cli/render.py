"""``plenoctree render``: render a tree over a dataset split, write PNGs and metrics.

Every option is a field of :class:`RenderConfig` (help = its docstrings).
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError


def resize_dataset(data, width: int, height: int):
    """Return ``data`` with cameras and images resampled to ``width`` x ``height``.

    Intrinsics scale with the size; images are area-resampled (PIL box filter).
    """
    from PIL import Image

    new_cams = data.cameras.resized(width, height)
    def resample(plane: np.ndarray) -> np.ndarray:
        img = Image.fromarray(np.ascontiguousarray(plane, dtype=np.float32), mode="F")
        return np.asarray(img.resize((width, height), Image.Resampling.BOX))

    imgs = np.stack([np.stack([resample(im[..., c]) for c in range(3)], -1) for im in data.images])
    alphas = None
    if getattr(data, "alphas", None) is not None:
        alphas = np.stack([resample(a) for a in data.alphas])
    return dataclasses.replace(data, images=imgs.astype(np.float32), alphas=alphas,
                               cameras=new_cams)


@dataclass
class RenderConfig:
    """Options of ``plenoctree render``."""

    tree: str = ""
    """tree file (.npz native or svox layout, or compressed .plnz)"""
    data: str | None = None
    """dataset folder (default: the one recorded next to the tree)"""
    camera_path: str | None = None
    """render along a nerfstudio camera-path JSON instead (frames, depth; no scores);
    --width/--height override its size"""
    dataparser_transforms: str | None = None
    """with --camera-path: nerfstudio's dataparser_transforms.json, mapping nerfstudio-viewer
    poses back to the dataset's world"""
    split: str = "test"
    """dataset split"""
    format: str | None = None
    """dataset format (default: detected)"""
    out: str | None = None
    """output folder (default: next to the tree)"""
    downscale: int = 1
    """integer area downscale of the images"""
    width: int | None = None
    """render width (with --height)"""
    height: int | None = None
    """render height (with --width)"""
    limit: int | None = None
    """use only the first N views of the split (0 or default: all)"""
    backend: str = "auto"
    """auto, numba, triton or torch"""
    device: str = "auto"
    """auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N"""
    stop_thresh: float = 0.01
    """early ray termination when transmittance < this; 0 disables"""
    renormalize: bool = False
    """svox's fast rule: a ray stopped early (transmittance < --stop-thresh) gets its colour
    divided by its opacity instead of the background; with --stop-thresh 0.1 a faster, slightly
    softer picture"""
    background: tuple[float, float, float] | None = None
    """white, black or R,G,B (default: the dataset's background)"""
    show_progress: bool | None = None
    """progress bar (default: when stderr is a terminal)"""


def _render_options(cfg: RenderConfig, data_background):
    """The :class:`RenderOptions` of ``cfg`` (background: ``cfg``'s, else the dataset's)."""
    from ..render import RenderOptions

    if cfg.stop_thresh < 0 or cfg.stop_thresh >= 1:
        raise ConfigError(f"--stop-thresh must be in [0, 1), got {cfg.stop_thresh}")
    bg = tuple(cfg.background) if cfg.background else tuple(data_background)
    return RenderOptions(stop_thresh=cfg.stop_thresh, background=bg,
                         renormalize=bool(cfg.renormalize))


def _check_size(cfg: RenderConfig) -> None:
    """--width/--height: both or neither, positive, at most ``MAX_IMAGE_PIXELS`` together."""
    from ..datasets import check_image_size

    if (cfg.width is None) != (cfg.height is None):
        raise ConfigError("--width and --height must be given together")
    if cfg.width is not None:
        check_image_size(cfg.width, cfg.height, "--width/--height")


def _run(cfg: RenderConfig, args: argparse.Namespace) -> int:
    from ._output import output_dir

    _check_size(cfg)
    if cfg.camera_path:
        out = Path(cfg.out) if cfg.out else Path(cfg.tree).parent / (
            Path(cfg.tree).stem + f"_render_{Path(cfg.camera_path).stem}")
        with output_dir(out, "render"):
            return _run_camera_path(cfg, out)
    out = Path(cfg.out) if cfg.out else Path(cfg.tree).with_suffix("").parent / (
        Path(cfg.tree).stem + f"_render_{cfg.split}")
    with output_dir(out, "render"):
        return _run_dataset(cfg, out)


def _run_dataset(cfg: RenderConfig, out: Path) -> int:
    """``render TREE``: the views of a dataset split, with scores."""
    from ..datasets import load_dataset
    from ..evaluation import evaluate_tree
    from ..compression import load_any_tree
    from ._output import views_or_all

    if not cfg.data:
        from ._provenance import data_from_provenance

        cfg.data = data_from_provenance(cfg.tree, "render")
    tree = load_any_tree(cfg.tree)
    bg = tuple(cfg.background) if cfg.background else None       # None: the dataset's
    data = load_dataset(cfg.data, split=cfg.split, format=cfg.format,
                        downscale=cfg.downscale, background=bg, limit=views_or_all(cfg.limit))
    if cfg.width is not None:
        data = resize_dataset(data, cfg.width, cfg.height)
    options = _render_options(cfg, data.background)
    res = evaluate_tree(tree, data, out, options, cfg.backend, device=cfg.device,
                        show_progress=cfg.show_progress)
    print(f"{len(res.names)} views at {res.width}x{res.height} -> {out}")
    ssim = (f"{res.mean_ssim:.4f}" if res.mean_ssim == res.mean_ssim
            else "n/a (images under the 11x11 SSIM window)")
    print(f"PSNR {res.mean_psnr:.2f} dB  SSIM {ssim}  "
          f"{res.ms_per_frame:.1f} ms/frame ({res.fps:.1f} FPS, backend {res.backend} on "
          f"{res.extra.get('device', 'cpu')})")
    return 0


def _run_camera_path(cfg: RenderConfig, out: Path) -> int:
    """``render TREE --camera-path JSON``: frames along a nerfstudio camera path, no scores."""
    from ..camera_path import load_camera_path
    from ..compression import load_any_tree
    from ..video import render_path_images

    if cfg.data is not None:
        raise ConfigError("--camera-path renders its own cameras: leave out --data")
    cp = load_camera_path(cfg.camera_path, cfg.width, cfg.height, cfg.dataparser_transforms)
    tree = load_any_tree(cfg.tree)
    options = _render_options(cfg, (1.0, 1.0, 1.0))
    cams = cp.cameras if tree.ndc is None else tree.ndc.apply(cp.cameras)   # NDC tree: NDC rays
    from ._output import views_or_all

    if views_or_all(cfg.limit):
        cams = cams.select(np.arange(min(cfg.limit, len(cams))))
    paths = render_path_images(tree, cams, out, options, cfg.backend,
                               show_progress=cfg.show_progress)
    print(f"{len(paths)} frames at {cams.width}x{cams.height} along {cfg.camera_path} -> {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``render`` command (one flag per :class:`RenderConfig` field)."""
    from ..datasets import FORMATS
    from ._options import add_command
    from ._output import VIEWS

    add_command(sub, "render", RenderConfig, _run,
                help="render a tree over a dataset split (PNGs + metrics.json)",
                positional=("tree",),
                fields={"limit": VIEWS, "camera_path": {"metavar": "JSON"},
                        "dataparser_transforms": {"metavar": "JSON"},
                        "format": {"choices": FORMATS}})
