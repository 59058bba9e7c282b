"""Render a tree over a dataset split and score it: PNGs, per-view metrics and timings.

:func:`score_views` is the one render-and-score loop: ``render`` / ``eval`` and the demo
(:func:`evaluate_tree`), the network's validation and ``render-nerf``
(:func:`plenoctree.nerf.evaluate.evaluate_views`), the fine-tuner's validation
(``optim._loop.render_views_psnr``) and the compression report all score through it. Imports
render, datasets and metrics (below ``nerf``/``convert``/``optim``/``compress``, which use it).
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._util import atomic_save_json, atomic_write, progress, save_png
from .datasets import Dataset
from .metrics import lpips as lpips_score
from .metrics import psnr, ssim
from .octree import Octree

# The renderer (torch) is imported inside the functions: EvalConfig is read by `--help`.

logger = logging.getLogger(__name__)

__all__ = ["EvalConfig", "EvalResult", "eval_markdown", "eval_tree_file",
           "evaluate_tree", "metrics_markdown", "score_views"]


@dataclass
class EvalResult:
    """Per-view and mean scores of one rendering pass over a dataset split.

    ``psnr``/``ssim`` are per view (dB / unitless), ``ms`` the render wall time of each view in
    milliseconds (excluding the first, warm-up render's compilation when ``warmup`` was used).
    ``lpips`` is per view (lower is better) when it was computed, else empty.
    """

    names: list[str]
    psnr: list[float]
    ssim: list[float]
    ms: list[float]
    width: int
    height: int
    backend: str
    extra: dict = field(default_factory=dict)
    lpips: list[float] = field(default_factory=list)

    @property
    def mean_psnr(self) -> float:
        return float(np.mean(self.psnr)) if self.psnr else float("nan")

    @property
    def mean_ssim(self) -> float:
        return float(np.mean(self.ssim)) if self.ssim else float("nan")  # NaN if any is NaN

    @property
    def mean_lpips(self) -> float:
        """Mean LPIPS, NaN when it was not computed."""
        return float(np.mean(self.lpips)) if self.lpips else float("nan")

    @property
    def ms_per_frame(self) -> float:
        """Median milliseconds per frame."""
        return float(np.median(self.ms)) if self.ms else float("nan")

    @property
    def fps(self) -> float:
        return 1000.0 / self.ms_per_frame if self.ms else float("nan")

    def to_json(self) -> dict:
        """A JSON-ready dict with per-view rows and the means (NaN written as null).

        ``lpips`` appears in the rows and the means only when it was computed.
        """
        views = [{"name": n, "psnr": p, "ssim": s, "ms": m}
                 for n, p, s, m in zip(self.names, self.psnr, self.ssim, self.ms)]
        mean = {"psnr": self.mean_psnr, "ssim": self.mean_ssim}
        if self.lpips:
            for row, value in zip(views, self.lpips):
                row["lpips"] = value
            mean["lpips"] = self.mean_lpips
        mean.update({"ms_per_frame": self.ms_per_frame, "fps": self.fps})
        return _nan_to_none({
            "width": self.width,
            "height": self.height,
            "backend": self.backend,
            "views": views,
            "mean": mean,
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


def save_view_images(out: Path, name: str, rgb: np.ndarray, gt: np.ndarray, depth: np.ndarray,
                     alpha: np.ndarray, depth_range: tuple[float, float],
                     background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> None:
    """Write one view's pictures under ``out`` (atomically):

    ``<name>.png`` render; ``<name>_depth.png`` depth as a Turbo colour map over
    ``depth_range = (near, far)`` (near red, far blue, nothing hit = background); ``<name>_depth.npy`` raw
    float32 depth ``[H, W]`` (world units along the unit ray, NDC units for NDC cameras; 0 where
    nothing was hit) and ``<name>_alpha.npy`` (float32 opacity); ``<name>_compare.png`` ground
    truth | render | error map (mean |Δ| per pixel, Turbo, ``plots.ERROR_VMAX`` = dark red).
    """
    from .plots import comparison_image, depth_colormap

    save_png(out / f"{name}.png", rgb)
    save_png(out / f"{name}_depth.png", depth_colormap(depth, alpha, *depth_range, background))
    for suffix, arr in (("depth", depth), ("alpha", alpha)):
        with atomic_write(out / f"{name}_{suffix}.npy", "wb") as f:
            np.save(f, np.asarray(arr, dtype=np.float32), allow_pickle=False)
    save_png(out / f"{name}_compare.png", comparison_image(gt, rgb))


def evaluate_tree(tree: Octree, data: Dataset, out_dir: str | Path | None = None,
                  options: RenderOptions | None = None, backend: str = "auto",
                  show_progress: bool | None = None, lpips_net: str | None = None,
                  device: Any = "cpu") -> EvalResult:
    """Render every view of ``data`` with ``tree`` and score it against the images.

    Args:
        tree: the octree to render.
        data: dataset split; its cameras give the rays, its images the ground truth
            ([N, H, W, 3] in [0, 1]). Its background is used unless ``options`` sets one.
        out_dir: if given, writes each view's pictures there (:func:`save_view_images`:
            render, depth colour map + raw ``.npy``, ground truth | render | error) and
            ``metrics.json`` / ``metrics.md`` (atomically).
        options: renderer options; default: stop at T < 0.01, the dataset's background.
        backend: ``"auto"``, ``"numba"``, ``"triton"`` or ``"torch"``.
        device: where to render: ``"cpu"`` (numpy rays), ``"cuda"`` (the tree is copied to
            the GPU once; per-view times include waiting for the GPU), or ``"auto"``. The
            first view is rendered once untimed first (JIT compilation, cache load).
        lpips_net: also score LPIPS with this backbone (``"vgg"``, ``"alex"``, ``"squeeze"``);
            raises :class:`~plenoctree.errors.BackendError` when it cannot run offline (check
            :func:`~plenoctree.metrics.lpips_available` first).

    Returns:
        An :class:`EvalResult` with PSNR/SSIM/ms (and LPIPS) per view.
    """
    from .render import RenderOptions, render_image

    if options is None:
        options = RenderOptions(background=tuple(float(b) for b in data.background))
    from .device import resolve_device
    from .render import tree_to_device

    dev = resolve_device(str(device))
    tree = tree_to_device(tree, dev)
    cams = data.cameras
    out = Path(out_dir) if out_dir is not None else None
    names = [data.names[i] if i < len(data.names) else f"view_{i:03d}" for i in range(len(cams))]

    def keep(i, name, o, rgb, gt):
        if out is not None:
            save_view_images(out, name, rgb, gt, o.depth.detach().cpu().numpy(),
                             o.alpha.detach().cpu().numpy(), (data.near, data.far),
                             options.background)

    def render(i: int) -> Any:
        return render_image(tree, cams, i, options, backend, device=dev)

    if len(cams):
        render(0)                # untimed warm-up: JIT compilation or cache load
    res = score_views(render, data.images[:len(cams)], names=names, lpips_net=lpips_net,
                      show_progress=show_progress, on_view=keep)
    res.width, res.height, res.extra = cams.width, cams.height, {"device": str(dev)}
    res.backend = backend
    if out is not None:
        atomic_save_json(out / "metrics.json", res.to_json())
        with atomic_write(out / "metrics.md", "w") as f:
            f.write(metrics_markdown(res))
    return res


def _rgb_of(o: Any) -> np.ndarray:
    """The RGB image of a renderer's output: an array, a tensor, ``.rgb`` or ``["rgb"]``."""
    if isinstance(o, dict):
        o = o["rgb"]
    o = getattr(o, "rgb", o)
    if hasattr(o, "detach"):
        o = o.detach().cpu().numpy()
    return np.asarray(o)


def score_views(render: Callable[[int], Any], images: Sequence[np.ndarray], *,
                names: Sequence[str] = (), with_ssim: bool = True, lpips_net: str | None = None,
                show_progress: bool | None = False,
                rgb_of: Callable[[Any], np.ndarray] = _rgb_of,
                on_view: Callable[..., None] | None = None) -> EvalResult:
    """The one render-and-score loop (trees, the fine-tuner's views, the network, codecs).

    For each ``k`` in ``range(len(images))``: ``o = render(k)`` (timed, milliseconds),
    ``rgb = rgb_of(o)`` ([H, W, 3] numpy in [0, 1]; default: an array, a tensor, ``o.rgb`` or
    ``o["rgb"]``), then PSNR (dB; ``inf`` for identical images) against ``images[k]``, SSIM
    (NaN when ``with_ssim`` is False or the image is under the 11x11 window), LPIPS with
    ``lpips_net`` when given, and ``on_view(k, name, o, rgb, gt)`` (e.g. saving pictures).

    Args:
        render: view index -> the renderer's output.
        images: ground truth (or reference renders) per view, ``[H, W, 3]`` each.
        names: view names (default ``view_<k:03d>``).
        show_progress: progress bar (``None``: shown, as :func:`~plenoctree._util.progress`).

    Every render is timed: warm a JIT-compiled renderer up before (``render(0)``).

    Returns:
        An :class:`EvalResult` (``width``/``height`` of the first image, ``backend`` empty:
        the caller names it).
    """
    n = len(images)
    h, w = (int(images[0].shape[0]), int(images[0].shape[1])) if n else (0, 0)
    res = EvalResult([], [], [], [], w, h, "")
    disable = None if show_progress is None else not show_progress
    for k in progress(range(n), desc="render", disable=disable):
        t0 = time.perf_counter()
        o = render(k)
        ms = (time.perf_counter() - t0) * 1e3
        rgb, gt = rgb_of(o), images[k]
        name = names[k] if k < len(names) else f"view_{k:03d}"
        res.names.append(name)
        res.psnr.append(float(psnr(rgb, gt)))
        # SSIM's 11x11 window needs images at least that large; smaller ones score NaN.
        small = min(rgb.shape[:2]) < 11
        res.ssim.append(float(ssim(rgb, gt)) if with_ssim and not small else float("nan"))
        res.ms.append(ms)
        if lpips_net is not None:
            res.lpips.append(float(lpips_score(rgb, gt, lpips_net)))
        if on_view is not None:
            on_view(k, name, o, rgb, gt)
    return res


def metrics_markdown(res: EvalResult) -> str:
    """A markdown table of the per-view scores and their mean (LPIPS column when computed)."""
    has_lp = bool(res.lpips)
    lines = ["| view | PSNR (dB) | SSIM |" + (" LPIPS |" if has_lp else "") + " ms |",
             "|---|---|---|" + ("---|" if has_lp else "") + "---|"]
    lp = res.lpips if has_lp else [None] * len(res.names)
    for n, p, s, q, m in zip(res.names, res.psnr, res.ssim, lp, res.ms):
        lines.append(f"| {n} | {p:.2f} | {s:.4f} |" + (f" {q:.4f} |" if has_lp else "")
                     + f" {m:.1f} |")
    lines.append(f"| **mean** | **{res.mean_psnr:.2f}** | **{res.mean_ssim:.4f}** |"
                 + (f" **{res.mean_lpips:.4f}** |" if has_lp else "")
                 + f" **{res.ms_per_frame:.1f}** (median) |")
    return "\n".join(lines) + "\n"


# --- `plenoctree eval`: one tree file scored on one dataset split ---------------------------
@dataclass
class EvalConfig:
    """What :func:`eval_tree_file` scores, and where the report goes (``plenoctree eval``)."""

    tree: str | Path
    """Tree file: native or svox ``.npz``, ``.plnz`` or svox compressed ``.npz``."""
    data: str | Path
    """Dataset folder (format detected unless ``format`` is given)."""
    split: str = "test"
    """Dataset split to score."""
    format: str | None = None
    """Dataset format (one of ``plenoctree.datasets.FORMATS``); None = detect."""
    downscale: int = 1
    """Integer area downscale of the images (FPS is measured at the resulting size)."""
    limit: int | None = None
    """Only N views: the first N, or with ``spread`` N evenly spaced over the split."""
    spread: bool = False
    """With ``limit``: score N views evenly spaced over the split (0, 20, 40, … of 200, as
    ``render-nerf --views`` picks them) instead of the first N, which on a turntable split
    are neighbours and not representative."""
    out: str | Path | None = None
    """Folder for ``eval.json`` and ``eval.md``; default ``<tree stem>_eval_<split>/`` next to
    the tree."""
    json_path: str | Path | None = None
    """Also write the JSON report to this file."""
    save_images: bool = False
    """Also write each view's render, depth (colour PNG + raw .npy) and ground truth | render |
    error image under ``<out>/renders/``."""
    backend: str = "auto"
    """Renderer backend: auto, numba, triton or torch."""
    device: str = "auto"
    """Where to render: auto (CUDA when a GPU is present, else cpu), cpu, cuda or cuda:N."""
    stop_thresh: float = 0.01
    """Early ray termination when transmittance < this; 0 disables."""
    renormalize: bool = False
    """svox's fast rule: a ray stopped early (transmittance < --stop-thresh) gets its colour
    divided by its opacity instead of the background; with --stop-thresh 0.1 a faster, slightly
    softer picture"""
    background: tuple[float, float, float] | None = None
    """Background RGB in [0, 1] the images are composited on; None = the dataset's (black for
    real photos, white for renders: ``datasets.default_background``)."""
    lpips_net: str = "vgg"
    """LPIPS backbone; LPIPS is skipped (and reported so) unless it can run offline."""
    show_progress: bool | None = None
    """Progress bar: None = only on a terminal."""


def _resolved_backend(backend: str, device: Any = "cpu") -> str:
    from .backend import resolve

    return resolve("render", backend, device)


def eval_dataset(cfg: EvalConfig) -> Dataset:
    """The dataset split :func:`eval_tree_file` scores ``cfg`` on (its images decoded)."""
    from .datasets import load_dataset

    bg = tuple(float(b) for b in cfg.background) if cfg.background is not None else None
    return load_dataset(cfg.data, split=cfg.split, format=cfg.format, downscale=cfg.downscale,
                        background=bg, limit=cfg.limit, spread=cfg.spread)


def eval_tree_file(cfg: EvalConfig, data: Dataset | None = None) -> dict:
    """Score a tree file on a dataset split: PSNR, SSIM, LPIPS (or why it was skipped), render
    speed at the dataset resolution, tree size. Writes ``eval.json`` and ``eval.md`` (atomic).
    ``data``: the split already loaded by :func:`eval_dataset` for this ``cfg`` (``run`` scores
    its trees on one load of the images); None loads it.

    FPS is 1000 / the median per-view render time in ms, after one untimed warm-up render
    (numba compilation or cache load). MB are 10^6 bytes: ``file_mb`` on disk, ``memory_mb``
    of the loaded (decompressed, float32) arrays.

    Returns:
        The report (the content of ``eval.json``): ``tree`` {path, kind, file_bytes, file_mb,
        memory_mb, data_format, sh_degree, n_nodes, n_leaves, n_occupied_leaves, max_depth},
        ``dataset`` {root, format, split, n_views, width, height, downscale}, ``render``
        {backend, stop_thresh, background}, ``width``/``height``/``backend``, ``views`` (per
        view psnr, ssim, ms, lpips when computed), ``mean`` {psnr, ssim, lpips (float or
        ``"skipped: <reason>"``), ms_per_frame, fps}, ``lpips`` {net, status}, ``out``.

    Raises:
        TreeFormatError / DatasetError naming the file; ConfigError for bad option values;
        BackendError for an unavailable renderer backend.
    """
    from .compression import is_compressed_file, load_any_tree
    from .datasets import FORMATS
    from .errors import ConfigError, TreeFormatError
    from .metrics import _lpips_problem

    tree_path = Path(cfg.tree)
    if not tree_path.is_file():
        raise TreeFormatError(f"{tree_path}: no such tree file")
    if cfg.format is not None and cfg.format not in FORMATS:
        raise ConfigError(f"--format: expected one of {', '.join(FORMATS)}, got {cfg.format!r}")
    if not (0.0 <= cfg.stop_thresh < 1.0):
        raise ConfigError(f"--stop-thresh must be in [0, 1), got {cfg.stop_thresh}")
    if cfg.limit is not None and cfg.limit < 1:
        raise ConfigError(f"--limit must be a positive integer, got {cfg.limit}")
    from .device import device_report, resolve_device

    device = resolve_device(cfg.device)
    backend = _resolved_backend(cfg.backend, device)
    tree = load_any_tree(tree_path)
    data = eval_dataset(cfg) if data is None else data
    if len(data.cameras) == 0:
        raise ConfigError(f"{cfg.data}: split {cfg.split!r} has no views to evaluate")
    out = Path(cfg.out) if cfg.out is not None else \
        tree_path.parent / f"{tree_path.stem}_eval_{cfg.split}"

    problem = _lpips_problem(cfg.lpips_net)
    if problem is not None:
        logger.info(f"LPIPS skipped: {problem}")
    from .render import RenderOptions

    options = RenderOptions(stop_thresh=float(cfg.stop_thresh), background=data.background,
                            renormalize=bool(cfg.renormalize))
    res = evaluate_tree(tree, data, out / "renders" if cfg.save_images else None, options,
                        backend, show_progress=cfg.show_progress, device=device,
                        lpips_net=None if problem is not None else cfg.lpips_net)

    leaf_sigma = tree.data[..., -1][tree.child == 0]     # σ alone: no copy of every leaf's row
    report = res.to_json()
    if problem is not None:
        report["mean"]["lpips"] = f"skipped: {problem}"
    file_bytes = tree_path.stat().st_size
    report = {
        "tree": {
            "path": str(tree_path), "kind": "compressed" if is_compressed_file(tree_path) else "npz",
            "file_bytes": int(file_bytes), "file_mb": file_bytes / 1e6,
            "memory_mb": tree.nbytes / 1e6, "data_format": tree.data_format,
            "sh_degree": tree.sh_degree, "n_nodes": int(tree.n_nodes),
            "n_leaves": int(tree.n_leaves), "n_occupied_leaves": int((leaf_sigma > 0).sum()),
            "max_depth": int(tree.max_depth),
        },
        "dataset": {"root": str(cfg.data), "format": _data_format(data, cfg.format),
                    "split": cfg.split, "n_views": len(data.cameras),
                    "width": data.cameras.width, "height": data.cameras.height,
                    "downscale": cfg.downscale},
        "render": {"backend": backend, "stop_thresh": float(cfg.stop_thresh),
                   "renormalize": bool(cfg.renormalize), "background": list(data.background)},
        "device": device_report(device),
        "lpips": {"net": cfg.lpips_net,
                  "status": "computed" if problem is None else f"skipped: {problem}"},
        **report,
        "out": str(out),
    }
    report = _nan_to_none(report)
    atomic_save_json(out / "eval.json", report)
    if cfg.json_path is not None:
        atomic_save_json(cfg.json_path, report)
    with atomic_write(out / "eval.md", "w") as f:
        f.write(eval_markdown(report))
    return report


def _data_format(data: Dataset, given: str | None) -> str:
    """The dataset format name: ``given`` or the detected one."""
    if given is not None:
        return given
    from .datasets import detect_format

    return detect_format(data.root)


def _fmt(v, spec: str) -> str:
    if isinstance(v, str):
        return v
    return "n/a" if v is None else format(v, spec)


def eval_markdown(report: dict) -> str:
    """The summary table of an :func:`eval_tree_file` report, then its per-view table."""
    t, d, m = report["tree"], report["dataset"], report["mean"]
    lp = m.get("lpips")
    skipped = isinstance(lp, str)
    lines = [
        f"**{Path(t['path']).name}** on {d['format']} `{d['split']}` "
        f"({d['n_views']} views, {d['width']}x{d['height']}, backend {report['render']['backend']})",
        "",
        "| PSNR (dB) | SSIM | LPIPS | FPS | ms/frame | leaves | nodes | file MB | memory MB |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {_fmt(m['psnr'], '.2f')} | {_fmt(m['ssim'], '.4f')} | "
        f"{'skipped' if skipped else _fmt(lp, '.4f')} "
        f"| {_fmt(m['fps'], '.1f')} | {_fmt(m['ms_per_frame'], '.1f')} | {t['n_leaves']:,} "
        f"| {t['n_nodes']:,} | {t['file_mb']:.2f} | {t['memory_mb']:.2f} |",
        *(["", f"LPIPS {lp}"] if skipped else []),
        "",
        "| view | PSNR (dB) | SSIM | LPIPS | ms |",
        "|---|---|---|---|---|",
    ]
    for v in report["views"]:
        lines.append(f"| {v['name']} | {_fmt(v['psnr'], '.2f')} | {_fmt(v['ssim'], '.4f')} | "
                     f"{_fmt(v.get('lpips'), '.4f')} | {_fmt(v['ms'], '.1f')} |")
    return "\n".join(lines) + "\n"
