"""The summary of a pipeline run: ``summary.json``'s rows and ``summary.md``'s table."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ._config import config_dict

__all__ = ["pipeline_summary", "summary_markdown", "finetune_outcome"]


def finetune_outcome(tree_ft: Path) -> dict:
    """The fine-tuner's ``end`` record (validation before / best, on which views, the training
    views held out for it, best epoch, why it stopped, back-offs) from
    ``<tree_ft stem>.log.jsonl``; ``{}`` when absent."""
    path = tree_ft.with_name(tree_ft.stem + ".log.jsonl")
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return {}
    for line in reversed(lines):
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if rec.get("event") == "end":
            keys = ("val_psnr_before", "val_psnr_best", "validation", "held_out", "best_epoch",
                    "epochs_run", "stop_reason", "backoffs", "wall_seconds")
            return {k: rec.get(k) for k in keys}
    return {}


def pipeline_summary(cfg: Any, out: Path, r: Any, evals: dict, nerf: dict, train_info: dict,
                     ft: dict | None = None) -> dict:
    """The run's summary: one row per stage (PSNR, SSIM, FPS, MB, leaves, wall and CPU
    seconds, peak RSS), the fine-tuning note, the speed-up, the device. ``cfg``: the
    :class:`~plenoctree.pipeline.PipelineConfig`; ``r``: its stage runner (times, peaks,
    CPU seconds, skipped and given stages); ``evals``: each octree stage's eval.json."""
    rows = []
    nerf_mean = nerf.get("mean", {})
    nerf_fps = nerf_mean.get("fps")
    rows.append({"stage": "NeRF-SH", "psnr": nerf_mean.get("psnr"), "ssim": nerf_mean.get("ssim"),
                 "fps": nerf_fps, "mb": nerf.get("model_mb"),
                 "seconds": r.times.get("train"), "cpu_seconds": r.cpu.get("train"),
                 "views": nerf.get("n_views"), "peak_rss_mb": r.peaks.get("train"),
                 "given": bool(cfg.nerf)})
    names = {"raw": "PlenOctree", "refined": "PlenOctree refined",
             "ft": "PlenOctree fine-tuned", "compressed": "compressed"}
    stage_time = {"raw": "extract", "refined": "refine", "ft": "finetune",
                  "compressed": "compress"}
    for key, ev in evals.items():
        mean, tree = ev.get("mean", {}), ev.get("tree", {})
        rows.append({"stage": names[key], "psnr": mean.get("psnr"), "ssim": mean.get("ssim"),
                     "fps": mean.get("fps"), "mb": tree.get("file_mb"),
                     "leaves": tree.get("n_leaves"),
                     "peak_rss_mb": r.peaks.get(stage_time[key]),
                     "seconds": r.times.get(stage_time[key]),
                     "cpu_seconds": r.cpu.get(stage_time[key]),
                     "views": ev.get("dataset", {}).get("n_views")})
    ft_fps = evals.get("ft", {}).get("mean", {}).get("fps")
    speedup = (ft_fps / nerf_fps) if (ft_fps and nerf_fps) else None
    return {"config": config_dict(cfg), "rows": rows, "times_s": r.times,
            "skipped": r.skipped, "speedup_over_nerf": speedup, "peak_rss_mb": r.peaks,
            "cpu_s": r.cpu,
            "total_s": sum(v for k, v in r.times.items() if v and k not in r.given_stages),
            "given": list(r.given_stages),
            "finetune": _finetune_note(evals, ft or {}),
            "web": str(out / "web") if cfg.web else None,
            "video": str(out / "orbit.mp4") if cfg.video_frames else None,
            "train": train_info, "device": _device_json(cfg.device)}


def _device_json(name: str) -> dict:
    from .device import device_report, resolve_device

    return device_report(resolve_device(name))


def _finetune_note(evals: dict, ft: dict) -> dict:
    """Test-PSNR gain of fine-tuning over its input and, when the input tree was kept, why."""
    def psnr(key):
        return evals.get(key, {}).get("mean", {}).get("psnr")

    start = psnr("refined") if "refined" in evals else psnr("raw")
    after = psnr("ft")
    note = dict(ft)
    note["test_gain_db"] = (after - start) if (after is not None and start is not None) else None
    if ft.get("best_epoch") == 0:
        note["kept_input"] = ("no fine-tuning epoch raised the validation PSNR above the input "
                              f"tree's ({ft.get('stop_reason')}), so the input tree was kept")
    return note


def _validation_views(ft: dict) -> str:
    """What fine-tuning validated on, in words ("" when its log did not say)."""
    held = ft.get("held_out") or []
    if held:
        return f"{len(held)} training views held out of the updates ({', '.join(held)})"
    return {"val split": "the dataset's val split",
            "training views (in training)": "training views that stay in training"}.get(
        ft.get("validation") or "", ft.get("validation") or "")


def summary_markdown(summary: dict) -> str:
    """One markdown table: PSNR/SSIM, FPS, MB and time per stage, plus the speed-up."""
    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) else "–"

    lines = ["| stage | test views | PSNR (dB) | SSIM | FPS | leaves | MB | wall (s) | CPU (s) | "
             "peak RSS (MB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in summary["rows"]:
        wall = f(row['seconds'], '.0f') + (" (given run)" if row.get("given") else "")
        lines.append(f"| {row['stage']} | {f(row['views'], 'd')} | {f(row['psnr'], '.2f')} | "
                     f"{f(row['ssim'], '.4f')} | {f(row['fps'], '.3g')} | "
                     f"{f(row.get('leaves'), ',d')} | {f(row['mb'], '.1f')} "
                     f"| {wall} | {f(row.get('cpu_seconds'), '.0f')} "
                     f"| {f(row.get('peak_rss_mb'), '.0f')} |")
    ft = summary.get("finetune") or {}
    if ft:
        lines.append("")
        gain = ft.get("test_gain_db")
        text = f"Fine-tuning: {f(gain, '+.2f')} dB on the test views"
        if ft.get("val_psnr_before") is not None:
            on = _validation_views(ft)
            text += (f" (validation{f' on {on}:' if on else ''} "
                     f"{f(ft.get('val_psnr_before'), '.2f')} → "
                     f"{f(ft.get('val_psnr_best'), '.2f')} dB, best epoch "
                     f"{ft.get('best_epoch')} of {ft.get('epochs_run')}, "
                     f"{ft.get('backoffs') or 0} learning-rate back-offs; "
                     f"{ft.get('stop_reason')})")
        lines.append(text + ".")
        if ft.get("kept_input"):
            lines.append(f"The fine-tuned tree is the input tree: {ft['kept_input']}.")
    if summary.get("speedup_over_nerf"):
        lines.append("")
        lines.append(f"Render speed-up of the fine-tuned octree over the NeRF-SH: "
                     f"{summary['speedup_over_nerf']:,.0f}x (same views, same machine)")
    given = " (the given NeRF-SH's training not counted)" if summary.get("given") else ""
    lines.append(f"Total wall time of the stages run: {summary['total_s']:.0f} s{given}")
    return "\n".join(lines) + "\n"
