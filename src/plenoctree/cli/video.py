"""``plenoctree video``: render a tree along an orbit, a dataset's cameras or an LLFF spiral
into an MP4 (colour, depth or both side by side)."""

from __future__ import annotations

import argparse

from ..errors import ConfigError
from .render import add_render_options, parse_background


def _depth_range(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        near, far = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--depth-range: expected NEAR,FAR, got {text!r}") from None
    return near, far


def _run(args: argparse.Namespace) -> int:
    from ..video import VideoConfig, make_video

    cfg = VideoConfig(
        tree=args.tree, out=args.out, data=args.data, path=args.path, split=args.split,
        format=args.format, downscale=args.downscale, frames=args.frames, fps=args.fps,
        width=args.width, height=args.height, radius=args.radius, elevation=args.elevation,
        up=args.up, fov=args.fov, camera_path=args.camera_path,
        dataparser_transforms=args.dataparser_transforms, mode=args.mode, depth_range=_depth_range(args.depth_range),
        backend=args.backend, stop_thresh=args.stop_thresh,
        background=parse_background(args.background) if args.background else None,
        quality=args.quality)
    res = make_video(cfg)
    where = f", up {res.up}, radius {res.radius:.3g}" if res.path == "orbit" else ""
    print(f"{res.n_frames} frames ({res.path}{where}, {res.mode}) at {res.width}x{res.height}, "
          f"{res.fps:g} fps -> {res.out}")
    print(f"rendering: {res.render_seconds:.1f} s, {res.render_fps:.1f} frames/s "
          f"at {res.render_width}x{res.render_height} (backend {args.backend})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``video`` command."""
    from ..datasets import FORMATS
    from ..video import MODES, PATHS, UP_AXES

    p = sub.add_parser(
        "video", help="render an orbit / dataset-path / spiral video of a tree (MP4)",
        description="Render a tree along a camera path into an H.264 video (needs the "
                    "plenoctree[video] extra: imageio, imageio-ffmpeg).")
    p.add_argument("tree", help="tree file (.npz native/svox, .plnz or svox compressed .npz)")
    p.add_argument("--data", default=None,
                   help="dataset folder: orbit up axis / radius / field of view / size from its "
                        "cameras; needed by --path dataset and spiral")
    p.add_argument("--path", default=None, choices=PATHS,
                   help="camera path (default: spiral for LLFF data, else orbit)")
    p.add_argument("--camera-path", default=None, metavar="JSON",
                   help="follow a nerfstudio camera-path JSON (the viewer's Render export: "
                        "poses, vertical fov, render size, fps) instead of --path")
    p.add_argument("--dataparser-transforms", default=None, metavar="JSON",
                   help="nerfstudio's dataparser_transforms.json, to map a camera path made in "
                        "the nerfstudio viewer back to the dataset's world")
    p.add_argument("--split", default="test", help="dataset split whose cameras are used")
    p.add_argument("--format", default=None, choices=FORMATS,
                   help="dataset format (default: detected)")
    p.add_argument("--downscale", type=int, default=1, help="integer downscale of the cameras")
    p.add_argument("--frames", type=int, default=None,
                   help="number of frames (default 120; dataset path: every camera)")
    p.add_argument("--fps", type=float, default=None,
                   help="video frame rate (default: the camera path's, else 30)")
    p.add_argument("--width", type=int, default=None,
                   help="frame width (with --height; default: the dataset's, else 800)")
    p.add_argument("--height", type=int, default=None, help="frame height (with --width)")
    p.add_argument("--radius", type=float, default=None,
                   help="orbit radius, world units (default: the dataset cameras' median "
                        "distance, else where the tree's box fits the view)")
    p.add_argument("--elevation", type=float, default=30.0,
                   help="orbit elevation in degrees above the centre (default 30, the original "
                        "gen_video's -30)")
    p.add_argument("--up", default="auto", choices=UP_AXES,
                   help="orbit up axis (default: from the dataset cameras, else +z)")
    p.add_argument("--fov", type=float, default=None,
                   help="orbit horizontal field of view, degrees (default: the dataset's, "
                        "else 39.6)")
    p.add_argument("--mode", default="color", choices=MODES,
                   help="color, depth, or both side by side (default: color)")
    p.add_argument("--depth-range", default=None, metavar="NEAR,FAR",
                   help="depth mapped white..black (default: the tree box along the rays)")
    p.add_argument("--quality", type=float, default=8.0,
                   help="H.264 quality, imageio's 0-10 scale (default 8)")
    p.add_argument("--out", default=None,
                   help="video file .mp4/.mov/.mkv (default: <tree>_<path>.mp4 next to the tree)")
    add_render_options(p)
    p.set_defaults(func=_run)
