"""``plenoctree process``: photos or a video → COLMAP poses → a dataset for ``run``.

Every option is a field of :class:`plenoctree.process.ProcessConfig` or of its nested
:class:`~plenoctree.process.sfm.SfmOptions` (flat flags: ``--camera-model``, ...); help = the
fields' docstrings.
"""

from __future__ import annotations

import argparse


def _run(cfg, args: argparse.Namespace) -> int:
    from ..pipeline_config import working_downscale
    from ..process import process

    summary = process(cfg)
    w, h = summary["image_size"]
    f = working_downscale(w, h, summary["kind"] == "forward", gpu=False)
    print(f"next: plenoctree run --data {cfg.out} --out <run folder> "
          f"({summary['kind']} capture, {summary['format']} format; on a CPU it works at "
          f"{w // f}x{h // f}, downscale {f}; --downscale overrides)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``process`` command."""
    from ..process import ProcessConfig
    from ._options import add_command

    add_command(
        sub, "process", ProcessConfig, _run,
        help="photos or a video -> camera poses (COLMAP) -> dataset for `run`",
        description="Recover camera poses of your own photos (or frames of a video) with "
                    "COLMAP (pycolmap: pip install 'plenoctree[colmap]'), undistort them and "
                    "write a dataset that `plenoctree run --data` reads without flags: "
                    "nerfstudio transforms.json for 360° captures, LLFF poses_bounds.npy (NDC) "
                    "for forward-facing ones.",
        positional=("images",),
        fields={"out": {"required": True}, "scene": {"choices": ("auto", "360", "forward")}},
        nested={"sfm": {"skip": ("mapper",)}})
