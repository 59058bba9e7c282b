"""``plenoctree extract RUN_DIR --out tree.npz``: convert a trained NeRF-SH into a PlenOctree.

Every option is a field of :class:`plenoctree.convert.ExtractConfig`; its docstring is the
``--help`` text. This module only parses, calls :func:`plenoctree.convert.extract` and prints.
"""

from __future__ import annotations

import argparse

from ..errors import ConfigError


def _check(cfg) -> None:
    """Option checks the ExtractConfig fields cannot express."""
    if len(cfg.radius) not in (0, 1, 3):
        raise ConfigError(f"--radius needs 1 or 3 numbers, got {list(cfg.radius)}")


def _mb(n: float) -> str:
    return f"{n / 2**20:.1f} MB"


def report(res) -> str:
    """Human-readable summary: per-stage time and peak RSS, leaves, size, PSNR."""
    lines = ["stage      seconds   peak RSS (MB)"]
    for name, st in res.stages.items():
        lines.append(f"{name:<9}{st['seconds']:>9.2f}   {st['peak_rss_mb']:>10.1f}")
    total = sum(st["seconds"] for st in res.stages.values())
    lines.append(f"{'total':<9}{total:>9.2f}")
    b = res.box
    lines.append(f"box ({b.source}): center {[round(float(x), 4) for x in b.center]} "
                 f"radius {[round(float(x), 4) for x in b.radius]}"
                 + (f" (depth stretched {b.depth_stretch:g}x: forward-facing)"
                    if b.depth_stretch != 1 else ""))
    t = res.tree
    unseen = res.extra.get("unseen_kept")
    lines.append(f"grid {res.grid}^3: {res.n_candidates} candidate voxels, {res.n_kept} kept "
                 + (f"({unseen} outside every training view) " if unseen else "")
                 + f"-> {t.n_leaves} leaves ({t.n_nodes} nodes, {t.data_format})")
    if res.out is not None:
        lines.append(f"saved {res.out} ({_mb(res.file_bytes)}, {res.extra.get('precision')})")
    if res.eval_views:
        line = (f"raw tree test PSNR {res.psnr:.2f} dB  SSIM {res.ssim:.4f} over "
                f"{res.eval_views} views")
        if res.nerf_psnr is not None:
            line += f"  (NeRF-SH validation PSNR {res.nerf_psnr:.2f} dB)"
        lines.append(line)
    if res.extra.get("sigma_clamped_fp16"):
        lines.append(f"{res.extra['sigma_clamped_fp16']} leaves had σ above the float16 maximum "
                     "and were clamped to 65504 (opaque either way)")
    if res.extra.get("nonfinite_values"):
        lines.append(f"warning: {res.extra['nonfinite_values']} non-finite network outputs were "
                     "replaced by 0")
    return "\n".join(lines)


def _run(cfg, args: argparse.Namespace) -> int:
    from ..convert import extract

    _check(cfg)
    print(report(extract(cfg)))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``extract`` command (one flag per ExtractConfig field)."""
    from ..convert.extraction import ExtractConfig
    from ._options import add_command

    add_command(sub, "extract", ExtractConfig, _run,
                help="convert a trained NeRF-SH run into a PlenOctree",
                description="Convert a trained NeRF-SH (RUN_DIR/checkpoint.pt) into a "
                "PlenOctree (paper section 4.2): auto box, sigma grid, visibility filter over "
                "the training views, per-voxel sampling, octree, test PSNR.",
                positional=("run_dir",), fields={"out": {"short": "-o"}})
