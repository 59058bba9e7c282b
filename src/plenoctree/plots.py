"""Pictures of results: depth and error colour maps, the fine-tuning curve, the stage plot.

The colour maps are numpy only (no matplotlib): :func:`turbo` is Google's Turbo colour map
(33 knots, linearly interpolated, within 3.3/255 of matplotlib's 256-entry table). The plots need matplotlib
(the ``plot`` extra, in the ``test`` extra too); without it they return ``False`` and write
nothing. Every file is written atomically.

- :func:`depth_colormap`: depth ``[H, W]`` → RGB, near = red/yellow end, far = blue end of
  Turbo; pixels with no content get the background colour.
- :func:`error_map`: per-pixel mean absolute error → Turbo, 0 → dark blue, ``vmax`` → dark red.
- :func:`comparison_image`: ground truth | render | error map, side by side.
- :func:`plot_finetune_curve`: train and validation PSNR per epoch of a ``.log.jsonl``.
- :func:`plot_stages`: PSNR against FPS and against MB for the stages of a ``run``.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ._util import atomic_write

__all__ = ["turbo", "depth_colormap", "error_map", "comparison_image", "plot_finetune_curve",
           "plot_stages", "ERROR_VMAX"]

#: Mean absolute error (per pixel, over RGB in [0, 1]) shown as the top of the error colour map.
ERROR_VMAX = 0.25

# Turbo (Google, 2019) sampled at 33 evenly spaced points, 8-bit; linear interpolation between
# them stays within 3.3/255 of the 256-entry table.
_TURBO_KNOTS = np.array([
    [48, 18, 59], [57, 42, 115], [64, 64, 162], [68, 86, 199], [70, 107, 227], [70, 128, 246],
    [66, 148, 255], [55, 168, 250], [40, 188, 235], [28, 205, 216], [24, 221, 194],
    [31, 233, 175], [50, 242, 152], [78, 249, 125], [109, 254, 98], [139, 255, 75],
    [164, 252, 60], [185, 246, 53], [205, 236, 52], [223, 223, 55], [238, 207, 58],
    [248, 190, 57], [253, 172, 52], [254, 150, 43], [251, 126, 33], [244, 102, 23],
    [235, 80, 14], [223, 63, 8], [208, 47, 5], [190, 33, 2], [169, 22, 1], [146, 11, 1],
    [122, 4, 3]], dtype=np.float64) / 255.0


def turbo(x: Any) -> np.ndarray:
    """Turbo colour map of ``x`` in [0, 1] (clipped; NaN → 0): float32 ``[..., 3]`` in [0, 1]."""
    x = np.nan_to_num(np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0))
    pos = x * (len(_TURBO_KNOTS) - 1)
    i = np.minimum(pos.astype(np.int64), len(_TURBO_KNOTS) - 2)
    f = (pos - i)[..., None]
    return (_TURBO_KNOTS[i] * (1.0 - f) + _TURBO_KNOTS[i + 1] * f).astype(np.float32)


def depth_colormap(depth: Any, alpha: Any, near: float, far: float,
                   background: Sequence[float] = (1.0, 1.0, 1.0),
                   alpha_min: float = 0.05) -> np.ndarray:
    """Depth ``[H, W]`` (world units) as a Turbo image ``[H, W, 3]``: near → red, far → blue.

    ``x = 1 - (depth - near) / (far - near)`` (clipped), so near is the warm end; pixels with
    ``alpha < alpha_min`` (nothing hit) get ``background``.
    """
    d = np.asarray(depth, dtype=np.float64)
    x = 1.0 - (d - near) / max(far - near, 1e-8)
    img = turbo(x)
    img[np.asarray(alpha) < alpha_min] = np.asarray(background, dtype=np.float32)
    return img


def error_map(pred: Any, gt: Any, vmax: float = ERROR_VMAX) -> np.ndarray:
    """``mean_c |pred - gt|`` per pixel as Turbo ``[H, W, 3]``; 0 → dark blue, ``vmax`` → red."""
    err = np.abs(np.asarray(pred, np.float64) - np.asarray(gt, np.float64)).mean(-1)
    return turbo(err / vmax)


def comparison_image(gt: Any, pred: Any, vmax: float = ERROR_VMAX, gap: int = 2) -> np.ndarray:
    """Ground truth | render | error map, ``[H, 3W + 2 gap, 3]`` float32 (white gaps)."""
    gt = np.asarray(gt, np.float32)[..., :3]
    pred = np.asarray(pred, np.float32)[..., :3]
    h = gt.shape[0]
    sep = np.ones((h, gap, 3), np.float32)
    return np.concatenate([gt, sep, pred, sep, error_map(pred, gt, vmax)], 1)


def _pyplot() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def _save(fig: Any, plt: Any, path: str | os.PathLike) -> None:
    fig.tight_layout()
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png")
    plt.close(fig)


def read_finetune_log(path: str | os.PathLike) -> dict:
    """``{"train": [(epoch, psnr)], "val": [(epoch, psnr)]}`` of a fine-tuning ``.log.jsonl``.

    A resumed run's log repeats epochs; the last record of an epoch wins. Unreadable lines
    (a run killed mid-write) are skipped.
    """
    train: dict[int, float] = {}
    val: dict[int, float] = {}
    for line in Path(path).read_text().splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if rec.get("event") == "epoch":
            train[int(rec["epoch"])] = float(rec["train_psnr"])
        elif rec.get("event") == "val" and rec.get("val_psnr") is not None:
            val[int(rec["epoch"])] = float(rec["val_psnr"])
    return {"train": sorted(train.items()), "val": sorted(val.items())}


def plot_finetune_curve(log_path: str | os.PathLike, out: str | os.PathLike,
                        title: str | None = None) -> bool:
    """Plot train and validation PSNR per epoch of a fine-tuning log to ``out`` (PNG).

    Epoch 0 is the tree before fine-tuning (validation only); the best validation epoch is
    marked (the fine-tuned tree keeps those values). Returns False (nothing written) without
    matplotlib or when the log has no epoch.
    """
    plt = _pyplot()
    curve = read_finetune_log(log_path)
    if plt is None or not (curve["train"] or curve["val"]):
        return False
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    if curve["train"]:
        e, p = zip(*curve["train"])
        ax.plot(e, p, ".-", lw=1.0, label="training PSNR (epoch mean)")
    if curve["val"]:
        e, p = zip(*curve["val"])
        ax.plot(e, p, "o-", lw=1.6, label="validation PSNR")
        i = int(np.argmax(p))
        ax.annotate(f"best {p[i]:.2f} dB (epoch {e[i]})", (e[i], p[i]),
                    textcoords="offset points", xytext=(-40, 10))
    ax.set_xlabel("epoch")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    ax.set_title(title or f"fine-tuning — {Path(log_path).name.removesuffix('.log.jsonl')}")
    _save(fig, plt, out)
    return True


#: ``benchmarks/paper_table.py`` row keys -> stage labels of the stage plot (in its order).
PAPER_TABLE_STAGES = (("nerf_sh", "NeRF-SH"), ("raw", "PlenOctree raw"),
                      ("refined", "refined"), ("ft", "fine-tuned"),
                      ("compressed", "compressed .plnz"), ("sh2", "fine-tuned, SH 2"),
                      ("sh1", "fine-tuned, SH 1"))


def stage_rows(obj: Any) -> tuple[list[dict], str | None]:
    """The stage plot's rows (``stage, psnr, fps, mb``) and a default title from any of:
    a run's ``summary.json`` (``{"rows": [...]}``), a JSON list of such rows, or
    ``benchmarks/paper_table.py``'s ``paper_table.json`` (``{"rows": {key: {psnr, fps_400,
    fps_800, mb, ...}}, "size": 400, "views": ...}``: FPS at the table's image size, MB on
    disk; rows not measured, e.g. ``refined`` without a refined tree, are left out).
    Raises ``ValueError`` for anything else."""
    rows = obj.get("rows") if isinstance(obj, dict) else obj
    if isinstance(rows, dict) and isinstance(obj, dict):             # paper_table.json
        size = int(obj.get("size") or 400)
        out = []
        for key, label in PAPER_TABLE_STAGES:
            r = rows.get(key)
            if isinstance(r, dict) and r.get("psnr") is not None:
                out.append({"stage": label, "psnr": r.get("psnr"), "fps": r.get(f"fps_{size}"),
                            "mb": r.get("mb")})
        title = f"lego {size}²: stages (benchmarks/paper_table.py, {obj.get('views')} test views)"
        return out, title
    if isinstance(rows, list) and all(isinstance(r, dict) for r in rows):
        return list(rows), None
    raise ValueError("expected a run's summary.json, benchmarks/paper_table.py's "
                     "paper_table.json, or a list of rows with stage, psnr, fps, mb")


def plot_stages(rows: Sequence[dict], out: str | os.PathLike, title: str | None = None) -> bool:
    """PSNR against FPS (log scale) and against MB (log scale) of each stage, to ``out``.

    ``rows``: dicts with ``stage``, ``psnr``, ``fps``, ``mb`` (``summary.json``'s rows; rows
    missing a value are left out of that panel). Returns False without matplotlib or data.
    """
    plt = _pyplot()
    def ok(v: Any) -> bool:
        return isinstance(v, (int, float)) and math.isfinite(v) and v > 0

    rows = [r for r in rows if ok(r.get("psnr"))]
    if plt is None or not any(ok(r.get("fps")) or ok(r.get("mb")) for r in rows):
        return False
    from matplotlib.ticker import FuncFormatter, NullFormatter

    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.2), dpi=110, sharey=True)
    for ax, key, label, unit in ((axes[0], "fps", "frames per second (log)", "FPS"),
                                 (axes[1], "mb", "size, MB (log)", "MB")):
        for i, r in enumerate(rows):
            if not ok(r.get(key)):
                continue
            ax.scatter([r[key]], [r["psnr"]], s=60, color=f"C{i}", zorder=3,
                       label=f"{r['stage']}: {r['psnr']:.2f} dB" if key == "fps" or
                       not ok(rows[i].get("fps")) else None)
            ax.annotate(f"{r[key]:.3g} {unit}", (r[key], r["psnr"]), textcoords="offset points",
                        xytext=(6, -3 - 9 * (i % 2)), fontsize=8, color=f"C{i}")
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(label)
        ax.grid(alpha=0.3, which="both")
        ax.margins(x=0.3, y=0.2)
    axes[0].set_ylabel("PSNR (dB)")
    fig.legend(loc="lower center", ncol=min(len(rows), 3), fontsize=8, frameon=False)
    fig.suptitle(title or "stages: quality, speed and size")
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    with atomic_write(out, "wb") as f:
        fig.savefig(f, format="png")
    plt.close(fig)
    return True
