"""Measuring a compression: file sizes, ratio, timings and the PSNR change on test views.

:func:`compression_report` is what ``plenoctree compress`` prints and what
``benchmarks/compress_bench.py`` records. With a dataset split, both trees are rendered from its
cameras and scored against its images (the PSNR change is the paper's figure); without one,
the compressed tree's renders are scored against the uncompressed tree's from an orbit of
cameras around the tree (a fidelity PSNR: how close the two trees render).

It sits above :mod:`plenoctree.compression` and :mod:`plenoctree.evaluation` (it scores
renders), so that the codec package itself imports neither.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from .compression.codec import CompressOptions, compress, decompress
from .compression.fileio import load_any_tree, load_compressed, save_compressed
from .datasets import Cameras
from .datasets.trajectories import DEFAULT_FOV_X, orbit_cameras
from .evaluation import score_views
from .octree import Octree
from .render import RenderOptions, render_image

__all__ = ["tree_orbit_cameras", "compression_report", "format_report"]


def tree_orbit_cameras(tree: Octree, n: int = 4, size: int = 128, elevation_deg: float = 30.0,
                       distance: float = 2.6, fov_x: float = DEFAULT_FOV_X) -> Cameras:
    """``n`` cameras on a 30° turntable around the tree's box, z up (Blender convention):
    :func:`~plenoctree.datasets.trajectories.orbit_cameras` (the one orbit) at ``distance``
    times the box's largest radius (lego: radius 1.5, cameras at ~4), horizontal field of
    view ``fov_x`` radians (NeRF-synthetic's camera_angle_x), ``size`` x ``size`` pixels."""
    r = float(np.max(tree.radius)) * float(distance)
    return orbit_cameras(np.asarray(tree.center, dtype=np.float64), r, n, size, size,
                         fov_x=fov_x, elevation_deg=elevation_deg, up="+z")


def _psnrs(tree: Octree, cams: Cameras, options: RenderOptions, backend: str,
           targets: Any) -> list[float]:
    """PSNR (dB) per view of ``tree`` rendered from ``cams`` against ``targets[i]``."""
    return score_views(lambda i: render_image(tree, cams, i, options, backend), targets,
                       with_ssim=False).psnr


def compression_report(src: str | os.PathLike, dst: str | os.PathLike,
                       options: CompressOptions | None = None, data: Any = None,
                       n_views: int = 4, size: int = 128, backend: str = "auto",
                       evaluate: bool = True) -> dict[str, Any]:
    """Compress the tree file ``src`` to ``dst`` (``.plnz``) and measure the result.

    Args:
        data: a :class:`~plenoctree.datasets.Dataset` split (e.g. test) to score against, or
            None for the orbit-camera fidelity comparison (``n_views`` views of ``size`` px).
        evaluate: False skips the renders (sizes and timings only).

    Returns:
        A dict: ``raw_bytes``, ``compressed_bytes``, ``ratio``, ``compress_s`` (quantise +
        write), ``decompress_s`` (read + decode), ``n_leaves_kept``, ``options``, and when
        evaluated ``psnr_raw`` / ``psnr_compressed`` / ``psnr_change`` (dataset; dB) or
        ``psnr_fidelity`` (orbit; dB), ``views``, ``eval_size``.
    """
    opts = options or CompressOptions()
    raw_bytes = Path(src).stat().st_size
    tree = load_any_tree(src)
    t0 = time.perf_counter()
    ctree = compress(tree, opts)
    comp_bytes = save_compressed(ctree, dst)
    compress_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    restored = decompress(load_compressed(dst), name=os.fspath(dst))
    decompress_s = time.perf_counter() - t0
    rep: dict[str, Any] = {
        "source": os.fspath(src), "output": os.fspath(dst),
        "raw_bytes": raw_bytes, "compressed_bytes": comp_bytes,
        "ratio": raw_bytes / max(comp_bytes, 1),
        "compress_s": compress_s, "decompress_s": decompress_s,
        "data_format": tree.data_format, "n_leaves": tree.n_leaves,
        "n_leaves_kept": ctree.n_kept,
        "options": {"bits": opts.bits, "retain": opts.retain,
                    "sigma_thresh": opts.sigma_thresh, "level": opts.level},
    }
    if not evaluate:
        return rep
    if data is not None:
        ropts = RenderOptions(background=tuple(float(b) for b in data.background))
        gt = data.images
        a = _psnrs(tree, data.cameras, ropts, backend, gt)
        b = _psnrs(restored, data.cameras, ropts, backend, gt)
        rep.update(psnr_raw=float(np.mean(a)), psnr_compressed=float(np.mean(b)),
                   psnr_change=float(np.mean(b) - np.mean(a)), views=len(gt),
                   eval_size=[data.cameras.width, data.cameras.height], eval="dataset")
    else:
        cams = tree_orbit_cameras(tree, n_views, size)
        ropts = RenderOptions()
        ref = [render_image(tree, cams, i, ropts, backend).rgb.detach().cpu().numpy()
               for i in range(len(cams))]
        vals = _psnrs(restored, cams, ropts, backend, ref)
        finite = [v for v in vals if math.isfinite(v)]
        rep.update(psnr_fidelity=float(np.mean(finite)) if finite else float("inf"),
                   views=len(cams), eval_size=[size, size], eval="orbit")
    return rep


def format_report(rep: dict[str, Any]) -> str:
    """Human-readable lines for a :func:`compression_report` dict."""
    lines = [
        f"{rep['source']} -> {rep['output']}",
        f"  size       {rep['raw_bytes'] / 1e6:10.2f} MB -> {rep['compressed_bytes'] / 1e6:.2f} MB"
        f"   ratio {rep['ratio']:.1f}x",
        f"  time       compress {rep['compress_s']:.2f} s, decompress {rep['decompress_s']:.2f} s",
        f"  leaves     {rep['n_leaves_kept']} kept of {rep['n_leaves']} ({rep['data_format']}, "
        f"{rep['options']['bits']} bits, retain {rep['options']['retain']})",
    ]
    if rep.get("eval") == "dataset":
        lines.append(f"  PSNR       {rep['psnr_raw']:.2f} dB -> {rep['psnr_compressed']:.2f} dB"
                     f"   change {rep['psnr_change']:+.3f} dB  ({rep['views']} views, "
                     f"{rep['eval_size'][0]}x{rep['eval_size'][1]})")
    elif rep.get("eval") == "orbit":
        fid = rep["psnr_fidelity"]
        fid_text = f"{fid:.2f} dB" if math.isfinite(fid) else "identical"
        lines.append(f"  PSNR       compressed vs uncompressed renders: {fid_text}"
                     f"  ({rep['views']} orbit views, {rep['eval_size'][0]}px; pass --data DIR "
                     "for the change against ground truth)")
    return "\n".join(lines)
