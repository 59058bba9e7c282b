"""``plenoctree compress / decompress / lod``: the web codec (paper B.2) and level of detail.

Every option is a field of :class:`CompressConfig`, :class:`DecompressConfig` or
:class:`LodConfig` (the codec's and the level of detail's own settings nested:
:class:`~plenoctree.compression.CompressOptions`, :class:`~plenoctree.compression.LodOptions`).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path

from ..compression.codec import CompressOptions
from ..compression.lod import LodOptions
from ..errors import ConfigError


@dataclass
class CompressConfig:
    """Options of ``plenoctree compress``."""

    tree: str = ""
    """tree file (.npz native or svox)"""
    out: str | None = None
    """output .plnz (default: TREE with .plnz)"""
    codec: CompressOptions = field(default_factory=CompressOptions)
    """the codec's settings"""
    data: str | None = None
    """dataset folder: report the PSNR change on its --split views"""
    split: str = "test"
    """dataset split"""
    downscale: int = 4
    """integer image downscale for the PSNR check"""
    limit: int | None = None
    """only the first N views of --data's split (0 or default: all; needs --data)"""
    views: int = 4
    """orbit views for the fidelity check without --data"""
    size: int = 128
    """orbit view size in px"""
    backend: str = "auto"
    """renderer backend"""
    evaluate: bool = True
    """the PSNR renders (--no-eval: sizes and timings only)"""


@dataclass
class DecompressConfig:
    """Options of ``plenoctree decompress``."""

    tree: str = ""
    """compressed tree (.plnz)"""
    out: str | None = None
    """output .npz (default: TREE_decompressed.npz)"""
    precision: str = field(default="fp32", metadata={"choices": ("fp16", "fp32")})
    """data precision of the output"""


@dataclass
class LodConfig:
    """Options of ``plenoctree lod``."""

    tree: str = ""
    """tree file (.npz or .plnz)"""
    out: str = ""
    """output: .plnz (compressed) or .npz (float16)"""
    target_mb: float | None = None
    """largest output size in MB"""
    lod: LodOptions = field(default_factory=LodOptions)
    """the level of detail"""
    codec: CompressOptions = field(default_factory=CompressOptions)
    """the codec's settings (.plnz output)"""


def _check_out(src: Path, out: Path, suffixes: tuple[str, ...], what: str) -> None:
    if out.suffix not in suffixes:
        raise ConfigError(f"--out must end in {what}, got {out}")
    if out.absolute() == src.absolute() or (out.exists() and src.exists()
                                            and out.samefile(src)):
        raise ConfigError(f"--out {out} would overwrite the input")


def _run_compress(cfg: CompressConfig, args: argparse.Namespace) -> int:
    from ..compression_report import compression_report, format_report
    from ._output import check_json, output_file, views_or_all, write_json

    src = Path(cfg.tree)
    out = Path(cfg.out) if cfg.out else src.with_suffix(".plnz")
    _check_out(src, out, (".plnz",), ".plnz")
    if isinstance(cfg.views, bool) or not isinstance(cfg.views, int) or cfg.views < 1:
        raise ConfigError(f"--orbit-views must be a positive integer (orbit views for the "
                          f"fidelity check), got {cfg.views!r}")
    if cfg.limit is not None and not cfg.data:
        raise ConfigError(f"--views {cfg.limit} counts views of --data's split, and no --data "
                          "was given; the orbit views of the fidelity check are --orbit-views")
    check_json(args)
    data = None
    with output_file(out, "compress", overwrite=args.overwrite, kind="tree"):
        if cfg.data:
            from ..datasets import load_dataset

            data = load_dataset(cfg.data, split=cfg.split, downscale=cfg.downscale,
                                limit=views_or_all(cfg.limit))
        rep = compression_report(src, out, cfg.codec.validated(), data=data,
                                 n_views=cfg.views, size=cfg.size, backend=cfg.backend,
                                 evaluate=cfg.evaluate)
    print(format_report(rep))
    write_json(args.json, rep)
    return 0


def _run_decompress(cfg: DecompressConfig, args: argparse.Namespace) -> int:
    from ..compression import decompress, load_compressed
    from ..octree.io import save_tree
    from ._output import output_file

    src = Path(cfg.tree)
    out = Path(cfg.out) if cfg.out else src.with_name(src.stem + "_decompressed.npz")
    _check_out(src, out, (".npz",), ".npz")
    with output_file(out, "decompress", overwrite=args.overwrite, kind="tree"):
        tree = decompress(load_compressed(src), name=str(src))
        save_tree(tree, out, precision=cfg.precision)
    print(f"{src} -> {out}: {tree.data_format}, {tree.n_leaves} leaves, "
          f"{out.stat().st_size / 1e6:.2f} MB ({cfg.precision})")
    return 0


def _run_lod(cfg: LodConfig, args: argparse.Namespace) -> int:
    from ..compression import fit_to_size, load_any_tree, make_lod
    from ..compression.lod import write_tree_file
    from ._output import check_json, output_file, write_json

    src, out = Path(cfg.tree), Path(cfg.out)
    _check_out(src, out, (".plnz", ".npz"), ".plnz (compressed) or .npz")
    check_json(args)
    base = cfg.lod.validated()
    copts = cfg.codec.validated()
    with output_file(out, "lod", overwrite=args.overwrite, kind="tree"):
        tree = load_any_tree(src)
        print(f"{src}: {tree.data_format}, {tree.n_leaves} leaves, depth {tree.max_depth + 1}, "
              f"{src.stat().st_size / 1e6:.2f} MB")
        if cfg.target_mb is not None:
            used, size = fit_to_size(tree, out, cfg.target_mb, base, copts)
        else:
            used = base
            size = write_tree_file(make_lod(tree, base), out, copts)
    print(f"-> {out}: {used.describe()}, {size / 1e6:.2f} MB")
    write_json(args.json, {"source": str(src), "output": str(out), "bytes": size,
                           "options": json.loads(json.dumps(used.__dict__))})
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``compress``, ``decompress`` and ``lod`` commands."""
    from ._options import add_command
    from ._output import VIEWS, add_json, add_overwrite

    codec = {"codec": {}}
    p = add_command(sub, "compress", CompressConfig, _run_compress,
                    help="compress a tree for the web (median cut + DEFLATE, .plnz)",
                    description="Quantise each SH basis's RGB coefficients by median cut into "
                    "2^bits float16 colours (uint16 index per leaf), keep sigma as float16, "
                    "DEFLATE the file. Prints the size ratio, timings and the PSNR change.",
                    positional=("tree",), nested=codec,
                    fields={"evaluate": {"flag": "eval"}, "limit": VIEWS,
                            "views": {"flag": "orbit-views", "metavar": "N"}})
    add_json(p, "the report")
    add_overwrite(p)
    p = add_command(sub, "decompress", DecompressConfig, _run_decompress,
                    help="turn a .plnz (or svox compressed .npz) into a normal tree",
                    positional=("tree",))
    add_overwrite(p)
    p = add_command(sub, "lod", LodConfig, _run_lod,
                    help="a smaller tree for the web (SH degree, depth, pruning, size)",
                    description="Reduce a tree: keep SH bands up to --sh-degree, merge cells "
                    "below --max-depth, empty leaves with opacity below --prune-alpha. With "
                    "--target-mb, reduce further step by step (prune 1 %, SH degree 2, prune "
                    "5 %, shallower depths, SH 1, SH 0) until the file fits.",
                    positional=("tree",), fields={"out": {"required": True}},
                    nested={"lod": {}, **codec})
    add_json(p, "a summary")
    add_overwrite(p)
