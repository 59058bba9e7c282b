"""Render dataset views with the network and score them (validation, ``render-nerf``).

The NeRF-SH baseline the octree is compared with (paper Table 1: NeRF-SH 0.051 FPS vs.
PlenOctree 167.7 FPS): every pixel is a ray through the network, in chunks, no gradients.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._util import atomic_save_json, save_png
from ..datasets import Dataset, evenly_spaced
from ..errors import ConfigError
from ..evaluation import score_views
from .config import TrainConfig
from .model import NeRFModel
from .renderer import ImageOptions, render_image

__all__ = ["evenly_spaced", "evaluate_views", "render_nerf_views", "ImageOptions"]


def evaluate_views(model: NeRFModel, data: Dataset, cfg: TrainConfig,
                   indices: list[int] | None = None, out_dir: str | Path | None = None,
                   with_ssim: bool = True, opts: ImageOptions = ImageOptions()) -> dict:
    """Render views of ``data`` and score them against its images.

    Args:
        indices: views to render (default: all). out_dir: if given, PNGs of the renders
            (``<name>.png``) and ``metrics.json`` are written there.
        with_ssim: compute SSIM too (slower than PSNR).
        opts: bf16, chunk, device, and ``rows``: render only these image rows of each view
            (timing a part of a large frame).

    Returns:
        ``{"names", "psnr", "ssim", "seconds", "n_samples", "mean_psnr", "mean_ssim",
        "seconds_per_frame", "width", "height"}``; ``seconds`` are per view (per
        ``rows`` when given).
    """
    if indices is None:
        indices = list(range(len(data)))
    for i in indices:
        if not 0 <= i < len(data):
            raise ConfigError(f"view index {i} out of range for {len(data)} views of "
                              f"{data.root} ({data.split})")
    out = Path(out_dir) if out_dir is not None else None
    rows = opts.rows
    n_samples: list[int] = []

    def keep(k, name, r, pred, gt):
        n_samples.append(int(r["n_samples"]))
        if out is not None:
            save_png(out / f"{name}.png", pred)

    ev = score_views(
        lambda k: render_image(model, data, indices[k], cfg, opts),
        [data.images[i] if rows is None else data.images[i][rows] for i in indices],
        names=[data.names[i] for i in indices], with_ssim=with_ssim,
        rgb_of=lambda r: np.clip(r["rgb"], 0.0, 1.0), on_view=keep)
    res = {"names": ev.names, "psnr": ev.psnr, "ssim": ev.ssim,
           "seconds": [ms / 1e3 for ms in ev.ms], "n_samples": n_samples}
    res["mean_psnr"] = float(np.mean(res["psnr"])) if indices else float("nan")
    res["mean_ssim"] = float(np.mean(res["ssim"])) if indices and with_ssim else float("nan")
    res["seconds_per_frame"] = float(np.mean(res["seconds"])) if indices else float("nan")
    res["width"], res["height"] = data.cameras.width, data.cameras.height
    if out is not None:
        atomic_save_json(out / "metrics.json", res)
    return res


def render_nerf_views(run_dir: str | Path, split: str = "test", views: int = 0,
                      indices: list[int] | None = None, data: str | Path | None = None,
                      downscale: int | None = None, out: str | Path | None = None,
                      with_ssim: bool = True, amp: str | None = None, chunk: int | None = None,
                      rows: slice | None = None, threads: int = 0) -> dict:
    """Render views of a dataset split with a trained run's network and score them.

    The NeRF-SH baseline of ``plenoctree render-nerf`` and of the pipeline's speed-up figure.

    Args:
        run_dir: training run directory (or its ``checkpoint.pt``).
        split: dataset split. views: this many evenly spaced views (0 = all), unless
            ``indices`` names them. data / downscale: default the ones trained on.
        out: folder for the PNGs and ``metrics.json`` (default ``RUN_DIR/render_<split>``).
        rows: render only these image rows (timing probes on slow presets); the reported
            ``seconds_per_full_frame`` is scaled to the whole image.

    Returns:
        The ``metrics.json`` dict: per-view ``names``/``psnr``/``ssim``/``seconds``/
        ``n_samples``, ``mean_psnr``, ``mean_ssim``, ``seconds_per_frame``,
        ``seconds_per_full_frame``, ``fps``, ``width``, ``height``, ``mean`` {psnr, ssim, fps},
        ``n_views``, ``model_mb``.
    """
    from ..datasets import load_dataset
    from .checkpoint import load_run
    from ..runtime import resolve_amp, resolve_device, setup_threads

    setup_threads(threads)
    run = load_run(run_dir)
    cfg = run.config
    device = resolve_device(cfg.device)
    model = run.model.to(device)
    use_amp = resolve_amp(amp or cfg.amp, device)
    dataset = load_dataset(data or cfg.data, split, format=None if data else cfg.format,
                           downscale=downscale or cfg.downscale,
                           background=cfg.background)
    if indices is not None:
        bad = [i for i in indices if not 0 <= i < len(dataset)]
        if bad:
            raise ConfigError(f"view indices {bad} out of range: split {split!r} has "
                              f"{len(dataset)} views")
        idx = list(indices)
    elif views:
        idx = evenly_spaced(len(dataset), views)
    else:
        idx = list(range(len(dataset)))
    height = dataset.cameras.height
    if rows is not None and rows.stop > height:
        raise ConfigError(f"rows {rows.start}:{rows.stop}: the images have {height} rows")
    run_dir = Path(run_dir)
    run_dir = run_dir.parent if run_dir.is_file() else run_dir
    out = Path(out) if out else run_dir / f"render_{split}"
    res = evaluate_views(model, dataset, cfg, idx, out_dir=out, with_ssim=with_ssim,
                         opts=ImageOptions(amp=use_amp, chunk=chunk, device=device, rows=rows))
    frac = 1.0 if rows is None else (rows.stop - rows.start) / height
    spf = res["seconds_per_frame"] / frac
    n_params = sum(p.numel() * p.element_size() for p in model.parameters())
    res.update({
        "seconds_per_full_frame": spf, "fps": 1.0 / spf if spf > 0 else None,
        "width": dataset.cameras.width, "height": height, "n_views": len(idx),
        "model_mb": n_params / 2**20, "rows_fraction": frac,
        "mean": {"psnr": res["mean_psnr"], "ssim": res["mean_ssim"],
                 "fps": 1.0 / spf if spf > 0 else None},
    })
    atomic_save_json(out / "metrics.json", res)
    return res
