"""Lego at 400² (or 800², ``--size 800``) on this CPU next to the paper's lego numbers
(Table 5 / Figure 5).

Rows: NeRF-SH (our CPU preset, hash grid), PlenOctree raw, adaptively refined
(``plenoctree refine``; "–" when no refined tree is given) and fine-tuned, the
compressed ``.plnz``, and the fine-tuned tree truncated to SH degree 1 and 2 — each with PSNR,
SSIM, FPS at 400² and 800², MB on disk and the wall time of the stage that made it; next to
the paper's lego figures. The speed-up over NeRF-SH is measured in the same run against two
baselines, both labelled: the paper-architecture NeRF-SH (8×256 PE MLP, 64 coarse + 128 fine
samples per ray; an untrained network costs the same per frame, timed on a band of middle
rows and extrapolated to the frame) and our CPU-preset NeRF-SH (full frames).

Modes:

* ``--from-artefacts`` (default): reads a trained run, the raw tree and the fine-tuned tree
  (``--nerf-run``, ``--tree``, ``--tree-ft``, optional ``--plnz``; the ft tree is compressed
  here if no ``.plnz`` is given) and measures everything above in one run. Stage wall times
  of training, extraction and fine-tuning are READ from the artefacts' JSON/log (marked
  ``read``); compression, SH truncation and all scores/speeds are MEASURED here.
* ``--full DIR``: runs the whole chain from scratch with
  :func:`plenoctree.pipeline.run_pipeline` into ``DIR`` (resumable), then measures as above::

      .venv/bin/python benchmarks/paper_table.py --full runs/lego_paper_table
      .venv/bin/python benchmarks/paper_table.py --full runs/lego_paper_800 --size 800 \
          --train-minutes 40

  (``--size 800`` trains, extracts, fine-tunes and scores at 800², the paper's protocol.) The
  per-stage wall minutes and peak RSS then come from the pipeline's ``summary.json``.
* ``--run-dir DIR``: the table of a chain ``plenoctree run --out DIR`` already ran (nothing is
  re-run): its artefacts, its own per-stage scores over the test views, wall minutes, CPU
  minutes and peak RSS from ``DIR/summary.json``; FPS, the SH-truncated rows and the NeRF-SH
  speed baselines are measured here::

      plenoctree run --data $PLENOCTREE_DATA/nerf_synthetic/lego --train.minutes 40 --out DIR
      .venv/bin/python benchmarks/paper_table.py --run-dir DIR --size 800

Scores: the first ``--views`` test views at 400² (default 200 = all) of ``--data`` (default
the data root's ``nerf_synthetic/lego``). FPS: 1000 / median per-view render ms (numba, after
one warm-up render) on ``--fps-views`` views at 400² and 800². MB: 10^6 bytes on disk. Writes
``--out`` (default ``benchmarks/results/paper_table.json``) and beside it, same stem, ``.md``,
``_stages.json`` (the rows ``plenoctree plot`` reads) and ``_psnr_fps.png`` (PSNR vs FPS at
800², log x, with the τ_w / grid variants of ``--table3`` when that file exists). As a script
it sets the process up as the CLI does (:func:`plenoctree.runtime.configure`).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

from _bench import RESULTS, add_data_root, add_out, data_path, fmt as _fmt, machine_info, \
    write_json

ROOT = Path(__file__).resolve().parents[1]

#: Paper Table 5 (lego column; FPS at 800² on a V100), Table 7 (GB), Table 8 (SH9 row).
PAPER = {
    "nerf_sh": {"psnr": 32.77, "ssim": 0.966, "fps": 0.051, "mb": None},
    "raw": {"psnr": 32.12, "ssim": 0.965, "fps": None, "mb": None},
    "refined": {"psnr": None, "ssim": None, "fps": None, "mb": None},
    "ft": {"psnr": 32.95, "ssim": 0.971, "fps": 186.8, "mb": 2067.0},
    "compressed": {"psnr": None, "ssim": None, "fps": None, "mb": None},
    "sh1": {"psnr": None, "ssim": None, "fps": None, "mb": None},
    "sh2": {"psnr": 32.79, "ssim": 0.970, "fps": 275.1, "mb": 1160.0},
}
PAPER_MEAN_FPS = {"nerf_sh": 0.051, "plenoctree": 167.68}

#: Rows of the table, in order, with their labels. Every one must be present.
ROWS = [
    ("nerf_sh", "NeRF-SH (CPU preset, hash grid)"),
    ("raw", "PlenOctree from NeRF-SH (raw)"),
    ("refined", "PlenOctree adaptively refined"),
    ("ft", "PlenOctree after fine-tuning"),
    ("compressed", "PlenOctree compressed (.plnz)"),
    ("sh2", "ft, SH degree 2 (SH9)"),
    ("sh1", "ft, SH degree 1 (SH4)"),
]

_SHORT = {"nerf_sh": "NeRF-SH (ours, CPU preset)", "raw": "raw", "refined": "refined",
          "ft": "fine-tuned", "compressed": "compressed", "sh2": "ft SH9", "sh1": "ft SH4"}


def _number(v):
    """``v`` when it is a finite number, else None (e.g. LPIPS "skipped: ..." or NaN)."""
    return float(v) if isinstance(v, (int, float)) and v == v else None


# --- measurements -----------------------------------------------------------------------
def measure_tree(path: Path, data: Path, views: int, fps_views: int, work: Path,
                 downscale: int = 2, known: dict | None = None) -> dict:
    """PSNR/SSIM (LPIPS when it runs) of tree file ``path`` on the first ``views`` test views at
    800/``downscale``², FPS at 400² and 800² (``fps_views`` views each; at 400² the scored
    views' when that is the scoring size), MB on disk.
    ``known``: an ``eval.json`` of the same tree, size and views (the pipeline's): its scores
    are used instead of rendering the views again (800² FPS is still measured here)."""
    from plenoctree.evaluation import EvalConfig, eval_tree_file

    t0 = time.perf_counter()
    if known and known.get("dataset", {}).get("n_views") == views:
        r4 = known
    else:
        r4 = eval_tree_file(EvalConfig(tree=path, data=data, downscale=downscale, limit=views,
                                       out=work / f"{path.stem}_400", show_progress=False))
    r8 = eval_tree_file(EvalConfig(tree=path, data=data, downscale=1, limit=fps_views,
                                   out=work / f"{path.stem}_800", show_progress=False))
    r4s = r4 if downscale == 2 else eval_tree_file(      # scored at 800²: time 400² here
        EvalConfig(tree=path, data=data, downscale=2, limit=fps_views,
                   out=work / f"{path.stem}_400fps", show_progress=False))
    lp = r4["mean"].get("lpips")
    return {"path": str(path), "psnr": r4["mean"]["psnr"], "ssim": r4["mean"]["ssim"],
            "lpips": _number(lp), "lpips_note": lp if isinstance(lp, str) else None,
            "fps_400": r4s["mean"]["fps"], "fps_800": r8["mean"]["fps"],
            "ms_400": r4s["mean"]["ms_per_frame"], "ms_800": r8["mean"]["ms_per_frame"],
            "mb": path.stat().st_size / 1e6, "n_leaves": r4["tree"]["n_leaves"],
            "data_format": r4["tree"]["data_format"], "views": r4["dataset"]["n_views"],
            "measure_s": time.perf_counter() - t0}


def measure_nerf_cpu(run: Path, views: int, work: Path, downscale: int = 2,
                     data: Path | None = None) -> dict:
    """Our CPU-preset NeRF-SH: PSNR/SSIM on ``views`` evenly spaced test views at
    800/``downscale``², s/frame at 400² (those views' median when they are 400², else one 400²
    view timed on its own) and at 800² (likewise). ``data``: the dataset (default: the
    run's own record, which may be relative to where it was trained)."""
    from plenoctree.nerf.evaluate import render_nerf_views

    scored = render_nerf_views(run, "test", views=views, downscale=downscale,
                               out=work / "nerf_scored", data=data)
    s_400 = (statistics.median(scored["seconds"]) if downscale == 2 else
             render_nerf_views(run, "test", views=1, downscale=2, out=work / "nerf_400",
                               with_ssim=False, data=data)["seconds_per_full_frame"])
    r8 = scored if downscale == 1 else render_nerf_views(
        run, "test", views=1, downscale=1, out=work / "nerf_800", with_ssim=False, data=data)
    return {"psnr": scored["mean_psnr"], "ssim": scored["mean_ssim"], "views": scored["n_views"],
            "s_400": s_400, "s_800": r8["seconds_per_full_frame"], "fps_400": 1.0 / s_400,
            "fps_800": 1.0 / r8["seconds_per_full_frame"],
            "mb": scored["model_mb"] * 2**20 / 1e6}


def measure_nerf_paper(data: Path, rows: int) -> dict:
    """Seconds per frame of the paper-architecture NeRF-SH (untrained weights: same cost) at
    400² and 800², from ``rows`` middle rows of test view 0, extrapolated to the frame."""
    import torch

    from plenoctree.datasets import load_dataset
    from plenoctree.nerf.config import preset
    from plenoctree.nerf.evaluate import ImageOptions, evaluate_views
    from plenoctree.nerf.model import NeRFModel

    cfg = preset("paper")
    torch.manual_seed(0)
    out = {"model": "8x256 PE MLP, SH16, 64 coarse + 128 fine samples/ray, fp32, untrained",
           "rows": rows}
    for ds, key in ((2, "s_400"), (1, "s_800")):
        test = load_dataset(data, "test", downscale=ds, limit=1, background=cfg.background)
        model = NeRFModel(cfg.model, test.scene_bbox).eval()
        h = test.cameras.height
        sl = slice(h // 2 - rows // 2, h // 2 - rows // 2 + rows)
        r = evaluate_views(model, test, cfg, [0], with_ssim=False, opts=ImageOptions(rows=sl))
        out[key] = r["seconds"][0] * h / rows
        out[f"samples_per_ray_{ds}"] = r["n_samples"][0] / (rows * test.cameras.width)
    out["fps_400"], out["fps_800"] = 1.0 / out["s_400"], 1.0 / out["s_800"]
    return out


def read_stage_times(nerf_run: Path, tree: Path, tree_ft: Path) -> dict:
    """Wall times read from the artefacts: training (summary.json), extraction (the tree's
    ``.extract.json`` stages, eval excluded), fine-tuning (the last line of its log)."""
    out = {}
    summ = nerf_run / "summary.json"
    if summ.is_file():
        s = json.loads(summ.read_text())
        out["train_s"] = s.get("train_time_s")
        out["nerf_val_psnr"] = s.get("val_psnr")
    ej = tree.with_suffix(".extract.json")
    if ej.is_file():
        e = json.loads(ej.read_text())
        out["extract_s"] = sum(v["seconds"] for k, v in e.get("stages", {}).items()
                               if k != "eval")
        out["raw_psnr_all_views"] = e.get("test_psnr")
    jl = tree_ft.with_name(tree_ft.stem + ".log.jsonl")      # the fine-tuner's JSON-lines log
    if jl.is_file():
        for line in jl.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if rec.get("event") == "end":
                out["finetune_s"] = rec.get("wall_seconds")
                out["ft_psnr_all_views"] = rec.get("test_psnr_after")
    for log in (tree_ft.parent / "log.txt", tree_ft.with_suffix(".log.txt")):
        if log.is_file():
            m = re.findall(r"([\d.]+) s, [\d.]+ M rays/s", log.read_text())
            if m:
                out["finetune_s"] = float(m[-1])
            m = re.findall(r"test PSNR after:\s+([\d.]+)", log.read_text())
            if m:
                out["ft_psnr_all_views"] = float(m[-1])
            break
    return out


# --- table and plot ---------------------------------------------------------------------
def markdown_table(res: dict) -> str:
    """The results as markdown: the per-row table next to the paper's lego numbers, then the
    speed-ups. ``res`` needs ``rows`` with every key of :data:`ROWS` (each with psnr, ssim,
    fps_400, fps_800, mb, stage_s, stage_src) and ``speedup``; a missing row is an error."""
    from plenoctree.errors import ConfigError

    missing = [k for k, _ in ROWS if k not in res.get("rows", {})]
    if missing:
        raise ConfigError(f"paper table: result has no row for {', '.join(missing)}")
    views = res.get("views", "?")
    size = res.get("size", 400)
    lines = [f"| lego, {views} test views at {size}² | PSNR | SSIM | LPIPS | FPS 400² | FPS 800² "
             "| leaves | MB | stage min (wall / CPU) | peak RSS MB | paper PSNR | paper SSIM | "
             "paper FPS (800², V100) | paper MB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, label in ROWS:
        r, p = res["rows"][key], PAPER[key]
        cpu = "" if r.get("cpu_s") is None else f" / {r['cpu_s'] / 60:.1f}"
        stage = ("–" if r.get("stage_s") is None
                 else f"{r['stage_s'] / 60:.1f}{cpu} ({r['stage_src']})")
        lines.append(f"| {label} | {_fmt(r['psnr'], '.2f')} | {_fmt(r['ssim'], '.3f')} | "
                     f"{_fmt(r.get('lpips'), '.3f')} | "
                     f"{_fmt(r['fps_400'], '.3g')} | {_fmt(r['fps_800'], '.3g')} | "
                     f"{_fmt(r.get('n_leaves'), ',d')} | "
                     f"{_fmt(r['mb'], '.1f')} | {stage} | {_fmt(r.get('peak_rss_mb'), '.0f')} | "
                     f"{_fmt(p['psnr'], '.2f')} | "
                     f"{_fmt(p['ssim'], '.3f')} | {_fmt(p['fps'], '.4g')} | "
                     f"{_fmt(p['mb'], '.0f')} |")
    sp = res["speedup"]
    lines += ["", "| speed-up of the fine-tuned PlenOctree (numba, CPU) | 400² | 800² |",
              "|---|---|---|",
              f"| over paper-architecture NeRF-SH (8×256 MLP, 64+128 samples; rows-extrapolated)"
              f" | {sp['paper_nerf_400']:.0f}× | {sp['paper_nerf_800']:.0f}× |",
              f"| over our CPU-preset NeRF-SH (hash grid, occupancy skipping) | "
              f"{sp['cpu_nerf_400']:.0f}× | {sp['cpu_nerf_800']:.0f}× |",
              f"| paper (V100, lego 186.8 / 0.051 FPS; mean 167.68 / 0.051) | – | "
              f"{186.8 / 0.051:.0f}× |"]
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path, variants: dict | None = None) -> None:
    """PSNR vs FPS at 800² (log x), in the spirit of the paper's Figure 5: our rows, the
    paper-architecture NeRF-SH time (at our NeRF-SH PSNR), and τ_w / grid variants (FPS at
    800² from ``extract_table3.json`` rows: ``{name: {"psnr", "fps"}}``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, (key, _) in enumerate(ROWS):
        r = res["rows"][key]
        if r.get("psnr") is None or not r.get("fps_800"):
            continue
        ax.scatter(r["fps_800"], r["psnr"], s=40, zorder=3, label=_SHORT[key],
                   marker="o^vDsp"[i % 6])
    pn = res.get("paper_nerf")
    if pn and res["rows"]["nerf_sh"].get("psnr") is not None:
        ax.scatter(pn["fps_800"], res["rows"]["nerf_sh"]["psnr"], marker="x", color="k",
                   label="paper-arch. NeRF-SH (timed here; PSNR of ours)")
    first = next(iter(variants or {}), None)
    for name, v in (variants or {}).items():
        ax.scatter(v["fps"], v["psnr"], marker="s", color="tab:gray", s=25, zorder=2,
                   label="raw-tree variants (extract_table3.json)" if name == first else None)
        ax.annotate(name, (v["fps"], v["psnr"]), fontsize=6, color="tab:gray",
                    xytext=(4, -8), textcoords="offset points")
    ax.scatter([PAPER["nerf_sh"]["fps"], PAPER["ft"]["fps"]],
               [PAPER["nerf_sh"]["psnr"], PAPER["ft"]["psnr"]], marker="*", s=80,
               color="tab:red", label="paper lego (V100)")
    ax.set_xscale("log")
    ax.set_xlabel("FPS at 800² (log)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title("lego: PSNR vs speed (CPU, this run) — cf. paper Fig. 5")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def stage_rows(res: dict, fps_key: str = "fps_800") -> list[dict]:
    """The rows as ``plenoctree plot`` reads them (``stage``, ``psnr``, ``fps``, ``mb``, with
    leaves and SSIM): the JSON of ``docs/lego_stages.json``; FPS at 800² by default."""
    out = []
    for key, label in ROWS:
        r = res["rows"].get(key, {})
        if r.get("psnr") is None:
            continue
        row = {"stage": _SHORT[key], "psnr": round(r["psnr"], 3),
               "fps": None if r.get(fps_key) is None else round(r[fps_key], 3),
               "mb": None if r.get("mb") is None else round(r["mb"], 1)}
        if r.get("ssim") is not None:
            row["ssim"] = round(r["ssim"], 4)
        if r.get("n_leaves") is not None:
            row["leaves"] = r["n_leaves"]
        if r.get("views") is not None:
            row["views"] = r["views"]
        out.append(row)
    return out


def table3_variants(path: Path) -> dict:
    """``{name: {"psnr", "fps"}}`` from ``extract_table3.json`` (raw trees, FPS at its
    ``fps_size``), or {} when the file is missing."""
    if not path.is_file():
        return {}
    d = json.loads(path.read_text())
    return {k: {"psnr": r["psnr"], "fps": r["render"]["fps"]}
            for k, r in d.get("rows", {}).items()
            if r.get("psnr") is not None and r.get("render", {}).get("fps")}


# --- driver -----------------------------------------------------------------------------
def run_full(out: Path, data: Path, views: int, downscale: int = 2, nerf: str = "",
             finetune_epochs: int = 0, train_minutes: float = 0.0
             ) -> tuple[Path, Path, Path | None, Path, Path | None, dict]:
    """Run the whole chain on lego at 800/``downscale``² into ``out`` (resumable, with the
    ``plenoctree run`` defaults; ``nerf``: a trained NeRF-SH run to start from, as
    ``plenoctree run --nerf``; ``finetune_epochs`` / ``train_minutes``: 0 = the run's
    default); return :func:`read_run_dir` of ``out``."""
    from plenoctree.pipeline import PipelineConfig, layer_settings, run_pipeline

    cfg = PipelineConfig(data=str(data), out=str(out), downscale=downscale,
                         eval_views=views, stage_eval_views=0, video_frames=0, web=False,
                         nerf=nerf)
    if finetune_epochs:
        cfg.finetune.epochs = finetune_epochs
    if train_minutes:
        layer_settings(cfg, {"train": {"minutes": train_minutes}}, "paper_table")
    run_pipeline(cfg)
    return read_run_dir(out)


def pipeline_evals(out: Path) -> dict:
    """``{row key: eval.json}`` of the pipeline's own scoring in ``out`` (eval_raw, ...)."""
    paths = {k: out / f"eval_{k}" / "eval.json" for k in ("raw", "refined", "ft", "compressed")}
    return {k: json.loads(p.read_text()) for k, p in paths.items() if p.is_file()}


def read_run_dir(run_dir: Path) -> tuple[Path, Path, Path | None, Path, Path | None, dict]:
    """The artefacts and summary of a finished ``plenoctree run --out run_dir``: NeRF-SH run
    (``run_dir/nerf`` or the ``--nerf`` it was given), raw, refined, fine-tuned and
    compressed trees (layout of :func:`plenoctree.pipeline.run_pipeline`), ``summary.json``."""
    from plenoctree.errors import ConfigError
    from plenoctree.pipeline import run_layout

    summ = run_layout(run_dir).summary
    if not summ.is_file():
        raise ConfigError(f"--run-dir {run_dir}: no summary.json (has `plenoctree run --out "
                          f"{run_dir}` finished?)")
    summary = json.loads(summ.read_text())
    lay = run_layout(run_dir, summary.get("config", {}).get("nerf") or "")
    for p in (lay.tree, lay.ft):
        if not p.is_file():
            raise ConfigError(f"--run-dir {run_dir}: {p.name} missing")
    return (lay.nerf, lay.tree,
            lay.refined if lay.refined.is_file() else None, lay.ft,
            lay.compressed if lay.compressed.is_file() else None, summary)


class Inputs(NamedTuple):
    """A table's NeRF-SH run, tree files (``refined``, ``plnz`` optional) and image size, and
    the chain's summary and own scores (``{}`` unless a chain made them)."""

    nerf_run: Path
    tree: Path
    refined: Path | None
    ft: Path
    plnz: Path | None
    size: int
    summary: dict
    known: dict


def resolve_inputs(a: argparse.Namespace, data: Path) -> Inputs:
    """The inputs of the mode (``--run-dir``, ``--full`` or the artefact flags); ``--full``
    runs the chain here."""
    if a.run_dir:
        nerf_run, tree, ref, ft, plnz, summary = read_run_dir(Path(a.run_dir))
        run_size = 800 // int(summary.get("config", {}).get("downscale", 1))
        size = a.size or run_size
        if run_size != size:
            print(f"note: the run was made at {run_size}², scored here at {size}²", flush=True)
        known = pipeline_evals(Path(a.run_dir)) if run_size == size else {}
        return Inputs(nerf_run, tree, ref, ft, plnz, size, summary, known)
    size = a.size or 400
    if a.full:
        nerf_run, tree, ref, ft, plnz, summary = run_full(
            Path(a.full), data, a.views, 800 // size, a.nerf_run or "", a.finetune_epochs,
            a.train_minutes)
        print(f"pipeline done ({summary.get('total_s', 0):.0f} s of stages); measuring",
              flush=True)
        return Inputs(nerf_run, tree, ref, ft, plnz, size, summary,
                      pipeline_evals(Path(a.full)))
    return Inputs(Path(a.nerf_run or ROOT / "runs/lego_cpu"), Path(a.tree),
                  Path(a.tree_refined) if a.tree_refined else None, Path(a.tree_ft),
                  Path(a.plnz) if a.plnz else None, size, {}, {})


def measure_rows(inp: Inputs, a: argparse.Namespace, data: Path, read: dict, work: Path
                 ) -> tuple[dict, dict]:
    """The rows (:data:`ROWS`) measured here, and the paper-architecture NeRF-SH timing."""
    down = 800 // inp.size
    rows = {}
    print("NeRF-SH (CPU preset) ...", flush=True)
    rows["nerf_sh"] = {**measure_nerf_cpu(inp.nerf_run, a.nerf_views, work, down, data),
                       "stage_s": read.get("train_s"), "stage_src": "read: training"}
    print("paper-architecture NeRF-SH timing ...", flush=True)
    paper_nerf = measure_nerf_paper(data, a.paper_rows)
    print("raw tree ...", flush=True)
    rows["raw"] = {**measure_tree(inp.tree, data, a.views, a.fps_views, work, down,
                                  inp.known.get("raw")),
                   "stage_s": read.get("extract_s"), "stage_src": "read: extraction"}
    if inp.refined is not None and inp.refined.is_file():
        print("refined tree ...", flush=True)
        rj = inp.refined.with_name(inp.refined.stem + ".refine.json")
        ref_s = json.loads(rj.read_text()).get("seconds") if rj.is_file() else None
        rows["refined"] = {**measure_tree(inp.refined, data, a.views, a.fps_views, work, down,
                                          inp.known.get("refined")),
                           "stage_s": ref_s, "stage_src": "read: refinement"}
    else:
        rows["refined"] = {"psnr": None, "ssim": None, "fps_400": None, "fps_800": None,
                           "mb": None, "stage_s": None, "stage_src": "not run"}
    print("fine-tuned tree ...", flush=True)
    rows["ft"] = {**measure_tree(inp.ft, data, a.views, a.fps_views, work, down,
                                 inp.known.get("ft")),
                  "stage_s": read.get("finetune_s"), "stage_src": "read: fine-tuning"}
    rows.update(measure_derived(inp, a, data, work))
    return rows, paper_nerf


def measure_derived(inp: Inputs, a: argparse.Namespace, data: Path, work: Path) -> dict:
    """The rows made from the fine-tuned tree here: compressed (unless a ``.plnz`` is given)
    and truncated to SH degree 2 and 1."""
    from plenoctree.compression import CompressOptions, compress, load_any_tree, save_compressed
    from plenoctree.compression.lod import truncate_sh, write_tree_file

    down, rows = 800 // inp.size, {}
    ft_tree = load_any_tree(inp.ft)
    plnz = inp.plnz
    if plnz is None or not plnz.is_file():
        print("compressing the ft tree ...", flush=True)
        plnz = work / "tree_ft.plnz"
        t0 = time.perf_counter()
        save_compressed(compress(ft_tree, CompressOptions(bits=16)), plnz)
        c_s, c_src = time.perf_counter() - t0, "measured: compression"
    else:
        cj = plnz.parent / "compress.json"
        c_s = json.loads(cj.read_text()).get("compress_s") if cj.is_file() else None
        c_src = "read: compression" if c_s is not None else "given .plnz"
    rows["compressed"] = {**measure_tree(plnz, data, a.views, a.fps_views, work, down,
                                         inp.known.get("compressed")),
                          "stage_s": c_s, "stage_src": c_src}
    for deg in (2, 1):
        print(f"SH degree {deg} ...", flush=True)
        t0 = time.perf_counter()
        p = work / f"tree_ft_sh{deg}.npz"
        write_tree_file(truncate_sh(ft_tree, deg), p)
        rows[f"sh{deg}"] = {**measure_tree(p, data, a.views, a.fps_views, work, down),
                            "stage_s": time.perf_counter() - t0,
                            "stage_src": "measured: truncate+save"}
    return rows


def apply_stage_figures(res: dict, summary: dict) -> None:
    """A chain's own wall time, peak RSS and CPU time of the stage that made each row, from its
    ``summary.json`` (``times_s`` / ``peak_rss_mb`` / ``cpu_s``), onto the rows."""
    stage = {"nerf_sh": "train", "raw": "extract", "refined": "refine", "ft": "finetune",
             "compressed": "compress"}
    for key, name in stage.items():
        row, sec = res["rows"][key], summary.get("times_s", {}).get(name)
        if sec is not None:
            given = key == "nerf_sh" and res["nerf_given"]
            row["stage_s"], row["stage_src"] = sec, "read: given run" if given else "pipeline"
        row["peak_rss_mb"] = summary.get("peak_rss_mb", {}).get(name)
        row["cpu_s"] = summary.get("cpu_s", {}).get(name)


def write_outputs(res: dict, a: argparse.Namespace, read: dict, argv: list[str] | None) -> Path:
    """``--out`` and, beside it, the markdown table, the stage rows and the plot."""
    md = markdown_table(res)
    res["markdown"] = md
    out = Path(a.out)
    variants = table3_variants(Path(a.table3))
    res["table3_variants_plotted"] = variants
    write_json(out, res)
    meta = res["machine"]
    given = (f", NeRF-SH given: {res['inputs']['nerf_run']} (trained before this run; its "
             "training time is not counted)" if res["nerf_given"] else "")
    text = (f"# lego {a.size}², CPU ({meta['cpu_count']} cores, load {meta['loadavg']})"
            f"{given}\n\n{md}\nStage times marked `read` come from the artefacts; the rest "
            f"were measured in this run ({res['wall_s']:.0f} s). Raw / ft PSNR over all 200 "
            f"views (read): {_fmt(read.get('raw_psnr_all_views'), '.2f')} / "
            f"{_fmt(read.get('ft_psnr_all_views'), '.2f')} dB.\n")
    from plenoctree._util import atomic_write

    with atomic_write(out.with_suffix(".md"), "w") as f:
        f.write(text)
    plot(res, out.with_name(out.stem + "_psnr_fps.png"), variants)
    src = (f"python benchmarks/paper_table.py {' '.join(sys.argv[1:] if argv is None else argv)}"
           f" (lego {a.size}², {a.views} test views; NeRF-SH: {res['rows']['nerf_sh'].get('views')}"
           f" views; FPS at 800²; {meta['cpu_count']} CPU cores, load {meta['loadavg']})")
    write_json(out.with_name(out.stem + "_stages.json"), {"source": src, "rows": stage_rows(res)})
    print(md)
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--from-artefacts", action="store_true", default=True)
    mode.add_argument("--full", default="", metavar="DIR",
                      help="run the pipeline from scratch into DIR (resumable)")
    mode.add_argument("--run-dir", default="",
                      help="a finished `plenoctree run --out DIR`: its artefacts and figures")
    ap.add_argument("--data", default=None,
                    help="dataset (default: nerf_synthetic/lego of the data root)")
    ap.add_argument("--nerf-run", default=None,
                    help="trained NeRF-SH run (default runs/lego_cpu); with --full the chain "
                         "starts from it instead of training (plenoctree run --nerf)")
    ap.add_argument("--tree", default=str(ROOT / "runs/lego_cpu_extract/tree.npz"))
    ap.add_argument("--tree-refined", default="", help="adaptively refined tree (optional)")
    ap.add_argument("--tree-ft", default=str(ROOT / "runs/lego_ft/tree_ft.npz"))
    ap.add_argument("--size", type=int, choices=(400, 800), default=None,
                    help="image size of training (--full) and scoring (default 400; with "
                         "--run-dir the run's own)")
    ap.add_argument("--finetune-epochs", type=int, default=0,
                    help="--full: maximum fine-tuning epochs (0 = plenoctree run's default)")
    ap.add_argument("--train-minutes", type=float, default=0.0,
                    help="--full: NeRF-SH training budget (0 = plenoctree run's default)")
    ap.add_argument("--plnz", default="", help="compressed ft tree (default: compress here)")
    ap.add_argument("--views", type=int, default=200, help="test views scored at 400²")
    ap.add_argument("--fps-views", type=int, default=3, help="views timed at 800²")
    ap.add_argument("--nerf-views", type=int, default=5)
    ap.add_argument("--paper-rows", type=int, default=4)
    ap.add_argument("--table3", default=str(RESULTS / "extract_table3.json"),
                    help="extract_table3.py's JSON: its variants go into the plot when it "
                         "exists")
    ap.add_argument("--keep", action="store_true", help="keep the scratch folder (renders, "
                    "SH-truncated trees, .plnz)")
    add_data_root(ap)
    add_out(ap, "paper_table.json")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    t_start = time.perf_counter()
    load_before = os.getloadavg()
    data = Path(a.data) if a.data else data_path(a.data_root, "nerf_synthetic", "lego")
    inp = resolve_inputs(a, data)
    a.size = inp.size
    read = read_stage_times(inp.nerf_run, inp.tree, inp.ft)
    work = Path(tempfile.mkdtemp(prefix="paper_table_"))
    chain = bool(a.full or a.run_dir)
    res = {"benchmark": "paper_table",
           "mode": "full" if a.full else ("run-dir" if a.run_dir else "from-artefacts"),
           "views": a.views, "size": a.size, "fps_views": a.fps_views,
           "read_from_artefacts": read,
           "inputs": {"nerf_run": str(inp.nerf_run), "tree": str(inp.tree),
                      "tree_ft": str(inp.ft)},
           "nerf_given": bool(a.full and a.nerf_run) or bool(
               a.run_dir and inp.summary.get("config", {}).get("nerf")),
           "finetune": inp.summary.get("finetune") if chain else None}
    res["rows"], res["paper_nerf"] = measure_rows(inp, a, data, read, work)
    if chain:
        apply_stage_figures(res, inp.summary)
    ft, nerf, pn = res["rows"]["ft"], res["rows"]["nerf_sh"], res["paper_nerf"]
    res["speedup"] = {
        "paper_nerf_400": ft["fps_400"] * pn["s_400"], "paper_nerf_800": ft["fps_800"] * pn["s_800"],
        "cpu_nerf_400": ft["fps_400"] * nerf["s_400"], "cpu_nerf_800": ft["fps_800"] * nerf["s_800"],
        "paper_reported_lego": 186.8 / 0.051,
        "paper_reported_mean": PAPER_MEAN_FPS["plenoctree"] / PAPER_MEAN_FPS["nerf_sh"]}
    res["paper"] = PAPER
    res["wall_s"] = time.perf_counter() - t_start
    res["machine"] = machine_info(load_before)
    if a.keep:
        print(f"renders and variant trees kept in {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    out = write_outputs(res, a, read, argv)
    print(f"wrote {out}, {out.stem}.md, {out.stem}_stages.json, {out.stem}_psnr_fps.png "
          f"({res['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    from plenoctree import runtime

    runtime.configure()         # as the CLI: before torch / numba load (OMP_WAIT_POLICY, malloc)
    sys.exit(main())
