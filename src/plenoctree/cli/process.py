"""``plenoctree process``: photos or a video → COLMAP poses → a dataset for ``run``."""

from __future__ import annotations

import argparse
import dataclasses


def add_sfm_flags(p: argparse.ArgumentParser) -> None:
    """One flag per :class:`~plenoctree.process.sfm.SfmOptions` field (help = its docstring)."""
    from ..nerf.config import field_docs
    from ..process.sfm import SfmOptions

    docs, defaults = field_docs(SfmOptions), SfmOptions()
    for f in dataclasses.fields(SfmOptions):
        if f.name == "mapper":
            continue
        flag = "--" + f.name.replace("_", "-")
        default = getattr(defaults, f.name)
        help_ = f"{docs.get(f.name, '')} (default {default})"
        if isinstance(default, bool):
            p.add_argument(flag, dest=f"sfm_{f.name}", action=argparse.BooleanOptionalAction,
                           default=default, help=help_)
        else:
            p.add_argument(flag, dest=f"sfm_{f.name}", type=type(default), default=default,
                           metavar=f.name.upper(), help=help_)


def sfm_options(args: argparse.Namespace):
    """The :class:`SfmOptions` of parsed ``args`` (flags added by :func:`add_sfm_flags`)."""
    from ..process.sfm import SfmOptions

    return SfmOptions(**{f.name: getattr(args, f"sfm_{f.name}")
                         for f in dataclasses.fields(SfmOptions) if f.name != "mapper"})


def _run(args: argparse.Namespace) -> int:
    from ..process import ProcessConfig, process

    cfg = ProcessConfig(images=args.images, out=args.out, scene=args.scene, frames=args.frames,
                        drop_blurry=args.drop_blurry, overwrite=args.overwrite,
                        sfm=sfm_options(args))
    summary = process(cfg)
    print(f"next: plenoctree run --data {cfg.out} --out <run folder> "
          f"({summary['kind']} capture, {summary['format']} format)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``process`` command."""
    p = sub.add_parser(
        "process", help="photos or a video -> camera poses (COLMAP) -> dataset for `run`",
        description="Recover camera poses of your own photos (or frames of a video) with "
                    "COLMAP (pycolmap: pip install 'plenoctree[colmap]'), undistort them and "
                    "write a dataset that `plenoctree run --data` reads without flags: "
                    "nerfstudio transforms.json for 360° captures, LLFF poses_bounds.npy (NDC) "
                    "for forward-facing ones.")
    p.add_argument("images", help="folder of photos (PNG/JPEG) or a video file")
    p.add_argument("--out", required=True, help="output dataset folder")
    p.add_argument("--scene", choices=["auto", "360", "forward"], default="auto",
                   help="capture kind (default auto: decided from the cameras)")
    p.add_argument("--frames", type=int, default=150,
                   help="video only: frames kept, evenly spread (default 150)")
    p.add_argument("--drop-blurry", type=float, default=0.5,
                   help="video only: fraction of the evenly spaced candidate frames dropped, "
                        "each kept frame the sharpest of its run of 1 / (1 - DROP) "
                        "consecutive candidates (default 0.5: the sharper of two)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    add_sfm_flags(p)
    p.set_defaults(func=_run)
