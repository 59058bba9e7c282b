"""Render a tree over a dataset split and score it: PNGs, per-view metrics and timings.

Used by ``plenoctree render`` / ``plenoctree eval`` and the demo. Imports render, datasets and
metrics (same layer as ``nerf``/``convert``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._util import atomic_save_json, atomic_write, progress, save_png
from .datasets import Dataset
from .metrics import psnr, ssim
from .octree import Octree
from .render import RenderOptions, render_image

__all__ = ["EvalResult", "depth_to_image", "evaluate_tree", "metrics_markdown"]


@dataclass
class EvalResult:
    """Per-view and mean scores of one rendering pass over a dataset split.

    ``psnr``/``ssim`` are per view (dB / unitless), ``ms`` the render wall time of each view in
    milliseconds (excluding the first, warm-up render's compilation when ``warmup`` was used).
    """

    names: list[str]
    psnr: list[float]
    ssim: list[float]
    ms: list[float]
    width: int
    height: int
    backend: str
    extra: dict = field(default_factory=dict)

    @property
    def mean_psnr(self) -> float:
        return float(np.mean(self.psnr)) if self.psnr else float("nan")

    @property
    def mean_ssim(self) -> float:
        return float(np.mean(self.ssim)) if self.ssim else float("nan")  # NaN if any is NaN

    @property
    def ms_per_frame(self) -> float:
        """Median milliseconds per frame."""
        return float(np.median(self.ms)) if self.ms else float("nan")

    @property
    def fps(self) -> float:
        return 1000.0 / self.ms_per_frame if self.ms else float("nan")

    def to_json(self) -> dict:
        """A JSON-ready dict with per-view rows and the means (NaN written as null)."""
        return _nan_to_none({
            "width": self.width,
            "height": self.height,
            "backend": self.backend,
            "views": [
                {"name": n, "psnr": p, "ssim": s, "ms": m}
                for n, p, s, m in zip(self.names, self.psnr, self.ssim, self.ms)
            ],
            "mean": {"psnr": self.mean_psnr, "ssim": self.mean_ssim,
                     "ms_per_frame": self.ms_per_frame, "fps": self.fps},
            **self.extra,
        })


def _nan_to_none(obj):
    """Replace float NaNs in nested dicts/lists by None (strict JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    if isinstance(obj, float) and obj != obj:
        return None
    return obj


def depth_to_image(depth: np.ndarray, alpha: np.ndarray, near: float, far: float) -> np.ndarray:
    """Map depth [H, W] (world units) to a grey image in [0, 1]: near → white, far → black.

    Pixels with no content (alpha < 0.05) are black.
    """
    d = np.clip((np.asarray(depth) - near) / max(far - near, 1e-8), 0.0, 1.0)
    img = 1.0 - d
    img[np.asarray(alpha) < 0.05] = 0.0
    return img


def evaluate_tree(tree: Octree, data: Dataset, out_dir: str | Path | None = None,
                  options: RenderOptions | None = None, backend: str = "auto",
                  warmup: bool = True, show_progress: bool | None = None) -> EvalResult:
    """Render every view of ``data`` with ``tree`` and score it against the images.

    Args:
        tree: the octree to render.
        data: dataset split; its cameras give the rays, its images the ground truth
            ([N, H, W, 3] in [0, 1]). Its background is used unless ``options`` sets one.
        out_dir: if given, writes ``<name>.png`` (colour), ``<name>_depth.png`` and
            ``metrics.json`` there (atomically).
        options: renderer options; default: stop at T < 0.01, the dataset's background.
        backend: ``"auto"``, ``"numba"`` or ``"torch"``.
        warmup: render the first view once untimed first (JIT compilation).

    Returns:
        An :class:`EvalResult` with PSNR/SSIM/ms per view.
    """
    if options is None:
        options = RenderOptions(background=tuple(float(b) for b in data.background))
    cams = data.cameras
    if warmup and len(cams):
        render_image(tree, cams, 0, options, backend)
    out = Path(out_dir) if out_dir is not None else None
    res = EvalResult([], [], [], [], cams.width, cams.height, backend)
    disable = None if show_progress is None else not show_progress
    for i in progress(range(len(cams)), desc="render", disable=disable):
        t0 = time.perf_counter()
        o = render_image(tree, cams, i, options, backend)
        ms = (time.perf_counter() - t0) * 1e3
        rgb = o.rgb.detach().cpu().numpy()
        gt = data.images[i]
        name = data.names[i] if i < len(data.names) else f"view_{i:03d}"
        res.names.append(name)
        res.psnr.append(float(psnr(rgb, gt)))
        # SSIM's 11x11 window needs images at least that large; smaller ones score NaN.
        res.ssim.append(float(ssim(rgb, gt)) if min(rgb.shape[:2]) >= 11 else float("nan"))
        res.ms.append(ms)
        if out is not None:
            save_png(out / f"{name}.png", rgb)
            depth = depth_to_image(o.depth.detach().cpu().numpy(), o.alpha.detach().cpu().numpy(),
                                   data.near, data.far)
            save_png(out / f"{name}_depth.png", depth)
    if out is not None:
        atomic_save_json(out / "metrics.json", res.to_json())
        with atomic_write(out / "metrics.md", "w") as f:
            f.write(metrics_markdown(res))
    return res


def metrics_markdown(res: EvalResult) -> str:
    """A markdown table of the per-view scores and their mean."""
    lines = ["| view | PSNR (dB) | SSIM | ms |", "|---|---|---|---|"]
    for n, p, s, m in zip(res.names, res.psnr, res.ssim, res.ms):
        lines.append(f"| {n} | {p:.2f} | {s:.4f} | {m:.1f} |")
    lines.append(f"| **mean** | **{res.mean_psnr:.2f}** | **{res.mean_ssim:.4f}** | "
                 f"**{res.ms_per_frame:.1f}** (median) |")
    return "\n".join(lines) + "\n"
