"""``plenoctree video``: render a tree along an orbit, a dataset's cameras or an LLFF spiral
into an MP4 (colour, depth or both side by side).

Every option is a field of :class:`plenoctree.video.VideoConfig`; help = its docstrings.
"""

from __future__ import annotations

import argparse


def _run(cfg, args: argparse.Namespace) -> int:
    from ..video import make_video

    res = make_video(cfg)
    where = f", up {res.up}, radius {res.radius:.3g}" if res.path == "orbit" else ""
    print(f"{res.n_frames} frames ({res.path}{where}, {res.mode}) at {res.width}x{res.height}, "
          f"{res.fps:g} fps -> {res.out}")
    print(f"rendering: {res.render_seconds:.1f} s, {res.render_fps:.1f} frames/s "
          f"at {res.render_width}x{res.render_height} (backend {cfg.backend})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``video`` command (one flag per :class:`~plenoctree.video.VideoConfig` field)."""
    from ..datasets import FORMATS
    from ..video import MODES, PATHS, UP_AXES, VideoConfig
    from ._options import add_command

    add_command(sub, "video", VideoConfig, _run,
                help="render an orbit / dataset-path / spiral video of a tree (MP4)",
                description="Render a tree along a camera path into an H.264 video (needs the "
                            "plenoctree[video] extra: imageio, imageio-ffmpeg).",
                base=lambda: VideoConfig(tree=""), positional=("tree",),
                fields={"camera_path": {"metavar": "JSON"},
                        "dataparser_transforms": {"metavar": "JSON"},
                        "path": {"choices": PATHS}, "format": {"choices": FORMATS},
                        "up": {"choices": UP_AXES}, "mode": {"choices": MODES}})
