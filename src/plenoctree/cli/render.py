"""``plenoctree render``: render a tree over a dataset split, write PNGs and metrics."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ._options import parse_background  # noqa: F401  (re-exported: eval, video, compress)


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


def add_render_options(p: argparse.ArgumentParser) -> None:
    """Add the renderer knobs shared by render-like commands."""
    p.add_argument("--backend", default="auto",
                   help="auto, numba, triton or torch (default: auto)")
    p.add_argument("--device", default="auto",
                   help="auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N")
    p.add_argument("--stop-thresh", type=float, default=0.01,
                   help="early ray termination when transmittance < this; 0 disables (default 0.01)")
    p.add_argument("--background", default=None,
                   help="white, black or R,G,B (default: the dataset's background)")


def render_options_from_args(args: argparse.Namespace, data_background):
    """Build a :class:`RenderOptions` from parsed arguments."""
    from ..render import RenderOptions

    bg = parse_background(args.background) if args.background else tuple(data_background)
    if args.stop_thresh < 0 or args.stop_thresh >= 1:
        raise ConfigError(f"--stop-thresh must be in [0, 1), got {args.stop_thresh}")
    return RenderOptions(stop_thresh=args.stop_thresh, background=bg)


def _run(args: argparse.Namespace) -> int:
    from ..datasets import load_dataset
    from ..evaluation import evaluate_tree
    from ..compress import load_any_tree

    if args.camera_path:
        return _run_camera_path(args)
    if not args.data:
        from ._provenance import data_from_provenance

        args.data = data_from_provenance(args.tree, "render")
    tree = load_any_tree(args.tree)
    bg = parse_background(args.background) if args.background else (1.0, 1.0, 1.0)
    data = load_dataset(args.data, split=args.split, format=args.format,
                        downscale=args.downscale, background=bg, limit=args.limit)
    if (args.width is None) != (args.height is None):
        raise ConfigError("--width and --height must be given together")
    if args.width is not None:
        if args.width <= 0 or args.height <= 0:
            raise ConfigError("--width/--height must be positive")
        data = resize_dataset(data, args.width, args.height)
    options = render_options_from_args(args, data.background)
    out = Path(args.out) if args.out else Path(args.tree).with_suffix("").parent / (
        Path(args.tree).stem + f"_render_{args.split}")
    res = evaluate_tree(tree, data, out, options, args.backend, device=args.device)
    print(f"{len(res.names)} views at {res.width}x{res.height} -> {out}")
    print(f"PSNR {res.mean_psnr:.2f} dB  SSIM {res.mean_ssim:.4f}  "
          f"{res.ms_per_frame:.1f} ms/frame ({res.fps:.1f} FPS, backend {res.backend} on "
          f"{res.extra.get('device', 'cpu')})")
    return 0


def _run_camera_path(args: argparse.Namespace) -> int:
    """``render TREE --camera-path JSON``: frames along a nerfstudio camera path, no scores."""
    from ..camera_path import load_camera_path
    from ..compress import load_any_tree
    from ..video import render_path_images

    if (args.width is None) != (args.height is None):
        raise ConfigError("--width and --height must be given together")
    if args.data is not None:
        raise ConfigError("--camera-path renders its own cameras: leave out --data")
    cp = load_camera_path(args.camera_path, args.width, args.height, args.dataparser_transforms)
    tree = load_any_tree(args.tree)
    options = render_options_from_args(args, (1.0, 1.0, 1.0))
    out = Path(args.out) if args.out else Path(args.tree).parent / (
        Path(args.tree).stem + f"_render_{Path(args.camera_path).stem}")
    cams = cp.cameras if tree.ndc is None else tree.ndc.apply(cp.cameras)   # NDC tree: NDC rays
    if args.limit is not None:
        cams = cams.select(np.arange(min(args.limit, len(cams))))
    paths = render_path_images(tree, cams, out, options, args.backend)
    print(f"{len(paths)} frames at {cams.width}x{cams.height} along {args.camera_path} -> {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``render`` command."""
    from ..datasets import FORMATS
    from ._output import add_views

    p = sub.add_parser("render", help="render a tree over a dataset split (PNGs + metrics.json)")
    p.add_argument("tree", help="tree file (.npz native or svox layout, or compressed .plnz)")
    p.add_argument("--data", default=None,
                   help="dataset folder (default: the one recorded next to the tree)")
    p.add_argument("--camera-path", default=None, metavar="JSON",
                   help="render along a nerfstudio camera-path JSON instead (frames, depth; "
                        "no scores); --width/--height override its size")
    p.add_argument("--dataparser-transforms", default=None, metavar="JSON",
                   help="with --camera-path: nerfstudio's dataparser_transforms.json, mapping "
                        "nerfstudio-viewer poses back to the dataset's world")
    p.add_argument("--split", default="test", help="dataset split (default: test)")
    p.add_argument("--format", default=None, choices=FORMATS,
                   help="dataset format (default: detected)")
    p.add_argument("--out", default=None, help="output folder (default: next to the tree)")
    p.add_argument("--downscale", type=int, default=1, help="integer area downscale of the images")
    p.add_argument("--width", type=int, default=None, help="render width (with --height)")
    p.add_argument("--height", type=int, default=None, help="render height (with --width)")
    add_views(p, dest="limit", legacy="--limit")
    add_render_options(p)
    p.set_defaults(func=_run)
