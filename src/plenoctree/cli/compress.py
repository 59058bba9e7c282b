"""``plenoctree compress / decompress / lod``: the web codec (paper B.2) and level of detail."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import ConfigError


def _compress_options(args: argparse.Namespace):
    from ..compress import CompressOptions

    return CompressOptions(bits=args.bits, retain=args.retain, sigma_thresh=args.sigma_thresh,
                           level=args.level).validated()


def _add_codec_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bits", type=int, default=16,
                   help="codebook size 2^bits per SH basis, 1..16 (default 16, as in the paper)")
    p.add_argument("--retain", type=int, default=0,
                   help="keep the first N bases unquantised (1 = exact DC colour; default 0)")
    p.add_argument("--sigma-thresh", type=float, default=0.0,
                   help="drop leaves with sigma <= this (1/world units; default 0 keeps all)")
    p.add_argument("--level", type=int, default=6, help="DEFLATE level 0..9 (default 6)")


def _run_compress(args: argparse.Namespace) -> int:
    from ..compress.report import compression_report, format_report

    src = Path(args.tree)
    out = Path(args.out) if args.out else src.with_suffix(".plnz")
    if out.suffix != ".plnz":
        raise ConfigError(f"--out must end in .plnz, got {out}")
    if out.resolve() == src.resolve():
        raise ConfigError(f"--out {out} would overwrite the input")
    data = None
    if args.data:
        from ..datasets import load_dataset

        data = load_dataset(args.data, split=args.split, downscale=args.downscale,
                            limit=args.limit)
    rep = compression_report(src, out, _compress_options(args), data=data,
                             n_views=args.views, size=args.size, backend=args.backend,
                             evaluate=not args.no_eval)
    print(format_report(rep))
    if args.json:
        from .._util import atomic_save_json

        atomic_save_json(args.json, rep)
    return 0


def _run_decompress(args: argparse.Namespace) -> int:
    from ..compress import decompress, load_compressed
    from ..octree.io import save_tree

    src = Path(args.tree)
    out = Path(args.out) if args.out else src.with_name(src.stem + "_decompressed.npz")
    if out.suffix != ".npz":
        raise ConfigError(f"--out must end in .npz, got {out}")
    tree = decompress(load_compressed(src), name=str(src))
    save_tree(tree, out, precision=args.precision)
    print(f"{src} -> {out}: {tree.data_format}, {tree.n_leaves} leaves, "
          f"{out.stat().st_size / 1e6:.2f} MB ({args.precision})")
    return 0


def _run_lod(args: argparse.Namespace) -> int:
    from ..compress import LodOptions, fit_to_size, load_any_tree, make_lod
    from ..compress.lod import write_tree_file

    src = Path(args.tree)
    out = Path(args.out)
    if out.suffix not in (".plnz", ".npz"):
        raise ConfigError(f"--out must end in .plnz (compressed) or .npz, got {out}")
    if out.resolve() == src.resolve():
        raise ConfigError(f"--out {out} would overwrite the input")
    tree = load_any_tree(src)
    base = LodOptions(sh_degree=args.sh_degree, max_depth=args.max_depth,
                      prune_alpha=args.prune_alpha).validated()
    copts = _compress_options(args)
    print(f"{src}: {tree.data_format}, {tree.n_leaves} leaves, depth {tree.max_depth + 1}, "
          f"{src.stat().st_size / 1e6:.2f} MB")
    if args.target_mb is not None:
        used, size = fit_to_size(tree, out, args.target_mb, base, copts, log=print)
    else:
        used = base
        size = write_tree_file(make_lod(tree, base), out, copts)
    print(f"-> {out}: {used.describe()}, {size / 1e6:.2f} MB")
    if args.json:
        from .._util import atomic_save_json

        atomic_save_json(args.json, {"source": str(src), "output": str(out), "bytes": size,
                                     "options": json.loads(json.dumps(used.__dict__))})
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``compress``, ``decompress`` and ``lod`` commands."""
    p = sub.add_parser("compress", help="compress a tree for the web (median cut + DEFLATE, .plnz)",
                       description="Quantise each SH basis's RGB coefficients by median cut into "
                       "2^bits float16 colours (uint16 index per leaf), keep sigma as float16, "
                       "DEFLATE the file. Prints the size ratio, timings and the PSNR change.")
    p.add_argument("tree", help="tree file (.npz native or svox)")
    p.add_argument("--out", default=None, help="output .plnz (default: TREE with .plnz)")
    _add_codec_flags(p)
    p.add_argument("--data", default=None,
                   help="dataset folder: report the PSNR change on its --split views")
    p.add_argument("--split", default="test", help="dataset split (default: test)")
    p.add_argument("--downscale", type=int, default=4,
                   help="integer image downscale for the PSNR check (default 4)")
    p.add_argument("--limit", type=int, default=None, help="only the first N views")
    p.add_argument("--views", type=int, default=4,
                   help="orbit views for the fidelity check without --data (default 4)")
    p.add_argument("--size", type=int, default=128, help="orbit view size in px (default 128)")
    p.add_argument("--backend", default="auto", help="renderer backend (default auto)")
    p.add_argument("--no-eval", action="store_true", help="skip the PSNR renders")
    p.add_argument("--json", default=None, help="also write the report as JSON here")
    p.set_defaults(func=_run_compress)

    p = sub.add_parser("decompress", help="turn a .plnz (or svox compressed .npz) into a normal tree")
    p.add_argument("tree", help="compressed tree (.plnz)")
    p.add_argument("--out", default=None, help="output .npz (default: TREE_decompressed.npz)")
    p.add_argument("--precision", choices=("fp16", "fp32"), default="fp32",
                   help="data precision of the output (default fp32)")
    p.set_defaults(func=_run_decompress)

    p = sub.add_parser("lod", help="a smaller tree for the web (SH degree, depth, pruning, size)",
                       description="Reduce a tree: keep SH bands up to --sh-degree, merge cells "
                       "below --max-depth, empty leaves with opacity below --prune-alpha. With "
                       "--target-mb, reduce further step by step (prune 1 %, SH degree 2, prune "
                       "5 %, shallower depths, SH 1, SH 0) until the file fits.")
    p.add_argument("tree", help="tree file (.npz or .plnz)")
    p.add_argument("--out", required=True, help="output: .plnz (compressed) or .npz (float16)")
    p.add_argument("--target-mb", type=float, default=None, help="largest output size in MB")
    p.add_argument("--sh-degree", type=int, default=None, help="keep SH degrees 0..N")
    p.add_argument("--max-depth", type=int, default=None,
                   help="merge cells deeper than this (root cells have depth 0)")
    p.add_argument("--prune-alpha", type=float, default=0.0,
                   help="empty leaves whose opacity 1-exp(-sigma*size) is below this")
    _add_codec_flags(p)
    p.add_argument("--json", default=None, help="also write a JSON summary here")
    p.set_defaults(func=_run_lod)
