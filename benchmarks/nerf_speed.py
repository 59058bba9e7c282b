"""NeRF-SH speed on this machine: training throughput of both presets, render-nerf frame time.

Method: every figure comes from the package's own code paths on real data (lego by default).

* CPU preset: ``train()`` for ``--cpu-minutes`` of training from scratch; throughput is the
  median of the log rows of the second half (the occupancy grid has settled by then) — the
  rays/s and samples/s the trainer itself logs (samples = network evaluations).
* Paper preset (fp32, and bf16 autocast as a variant): ``--paper-steps`` steps of 1024 rays
  with 64 coarse + 192 fine network samples per ray; median over the steps after the first two.
* ``--resume RUN``: only the steady-state throughput of a trained run continued for
  ``--resume-steps`` steps (see :func:`bench_resume`); run under two code versions
  (``PYTHONPATH=OLD/src``) to compare them.
* render-nerf: seconds per 800x800 frame with the network, chunked, no gradients. The paper
  preset is timed on ``--render-rows`` rows of test view 0 and extrapolated (a full frame takes
  minutes); the CPU preset renders the whole frame.

The data (``--data``) defaults to ``nerf_synthetic/lego`` of the data root (``--data-root``).
Prints a markdown table and writes JSON (figures, config, machine, load average) to ``--out``.
Run as a script it sets the process up as the CLI does (:func:`plenoctree.runtime.configure`:
``OMP_WAIT_POLICY=PASSIVE`` before torch loads, the malloc thresholds); ``--threads`` sets the
torch / numba thread count (0: all cores).
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

from _bench import add_data_root, add_out, data_path, machine_info, write_json


def _rows(run: Path) -> list[dict]:
    return json.loads((run / "log.json").read_text())["train"]


def bench_cpu(data: str, downscale: int, minutes: float, root: Path) -> dict:
    from plenoctree.nerf import preset, train

    cfg = preset("cpu")
    cfg.data, cfg.out, cfg.downscale = data, str(root / "cpu"), downscale
    cfg.minutes, cfg.max_steps, cfg.val_views, cfg.log_every = minutes, 10**9, 0, 10
    cfg.ckpt_every_s = 0.0
    res = train(cfg, quiet=True)
    rows = [r for r in _rows(Path(cfg.out)) if r["train_s"] >= 0.5 * res.train_time_s]
    return {"steps": res.step, "train_s": res.train_time_s,
            "rays_per_s": statistics.median(r["rays_per_s"] for r in rows),
            "samples_per_s": statistics.median(r["samples_per_s"] for r in rows),
            "samples_per_ray": statistics.median(r["samples_per_ray"] for r in rows),
            "rays_per_step": statistics.median(r["rays"] for r in rows),
            "occupancy": rows[-1]["occupancy"], "run": cfg.out}


def bench_resume(run: str, data: str, steps: int, root: Path) -> dict:
    """Steady-state CPU-preset throughput: a copy of the trained run ``run`` (a ``train`` or
    ``plenoctree run`` NeRF directory with its optimizer state) trained ``steps`` more steps;
    median of the log rows after the first 10 steps (the late-training state where most of a
    run's steps are spent: settled occupancy grid, ~6 samples per ray)."""
    from plenoctree.nerf import train
    from plenoctree.nerf.checkpoint import CheckpointError, read_checkpoint

    dst = root / "resumed"
    shutil.copytree(Path(run), dst, ignore=shutil.ignore_patterns("val", "render_*"))
    try:
        ck = read_checkpoint(dst)
        cfg, step0 = ck["config"], int(ck["step"])
        cfg.out, cfg.data = str(dst), data
        cfg.minutes, cfg.max_steps, cfg.val_views, cfg.log_every = 0.0, step0 + steps, 0, 5
        cfg.ckpt_every_s, cfg.val_every_s, cfg.preview_every_s = 0.0, 0.0, 0.0   # at the end only
        train(cfg, resume=True, quiet=True)
    except CheckpointError as e:
        raise SystemExit(f"nerf_speed.py --resume {run}: {e} (it needs a run that can resume: "
                         "the NeRF directory of `train` or `plenoctree run`, with its optimizer "
                         "state)") from None
    rows = [r for r in _rows(dst) if r["step"] > step0 + 10]
    return {"run": run, "from_step": step0, "steps": steps,
            "rays_per_s": statistics.median(r["rays_per_s"] for r in rows),
            "samples_per_s": statistics.median(r["samples_per_s"] for r in rows),
            "samples_per_ray": statistics.median(r["samples_per_ray"] for r in rows)}


def bench_paper(data: str, downscale: int, steps: int, amp: str, root: Path) -> dict:
    from plenoctree.nerf import preset, train

    cfg = preset("paper")
    cfg.data, cfg.out, cfg.downscale = data, str(root / f"paper_{amp}"), downscale
    cfg.max_steps, cfg.log_every, cfg.val_views, cfg.amp = steps, 1, 0, amp
    cfg.ckpt_every_s = 0.0
    train(cfg, quiet=True)
    rows = _rows(Path(cfg.out))[2:] or _rows(Path(cfg.out))
    return {"steps": steps, "rays_per_s": statistics.median(r["rays_per_s"] for r in rows),
            "samples_per_s": statistics.median(r["samples_per_s"] for r in rows),
            "samples_per_ray": rows[-1]["samples_per_ray"], "run": cfg.out}


def bench_render(run: str, data: str, rows: int | None) -> dict:
    import torch

    from plenoctree.datasets import load_dataset
    from plenoctree.nerf import load_run
    from plenoctree.nerf.evaluate import ImageOptions, evaluate_views
    from plenoctree.runtime import resolve_amp

    nerf_run = load_run(run)
    model, cfg = nerf_run.model, nerf_run.config
    amp = resolve_amp(cfg.amp, torch.device("cpu"))
    test = load_dataset(data, "test", limit=1, background=cfg.background)
    sl = slice(0, rows) if rows else None
    r = evaluate_views(model, test, cfg, [0], with_ssim=False,
                       opts=ImageOptions(amp=amp, rows=sl))
    frac = 1.0 if sl is None else rows / test.cameras.height
    return {"width": test.cameras.width, "height": test.cameras.height,
            "rows_rendered": rows or test.cameras.height,
            "seconds_per_frame": r["seconds"][0] / frac,
            "samples_per_ray": r["n_samples"][0] / (frac * test.cameras.width * test.cameras.height),
            "extrapolated": sl is not None, "psnr_of_rendered_part": r["psnr"][0]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None,
                    help="dataset (default: nerf_synthetic/lego of the data root)")
    ap.add_argument("--downscale", type=int, default=2, help="training resolution (2: 400x400)")
    ap.add_argument("--cpu-minutes", type=float, default=1.5)
    ap.add_argument("--paper-steps", type=int, default=8)
    ap.add_argument("--render-rows", type=int, default=8,
                    help="rows of the 800x800 frame timed for the paper preset")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--resume", default="",
                    help="measure only the steady-state throughput of this trained run "
                         "(e.g. DIR/nerf of `plenoctree run`) continued --resume-steps steps; "
                         "run it under each code version to compare them")
    ap.add_argument("--resume-steps", type=int, default=100)
    add_data_root(ap)
    add_out(ap, "nerf_speed.json")
    args = ap.parse_args(argv)
    args.data = args.data or str(data_path(args.data_root, "nerf_synthetic", "lego"))
    from plenoctree.runtime import setup_threads

    setup_threads(args.threads)
    machine = machine_info()
    out: dict = {"benchmark": "nerf_speed", "machine": machine, "args": vars(args)}
    if args.resume:
        with tempfile.TemporaryDirectory(prefix="nerf_speed_") as tmp:
            r = out["cpu_resumed"] = bench_resume(args.resume, args.data, args.resume_steps,
                                                  Path(tmp))
        out["machine"] = machine = machine_info(machine["loadavg"])
        text = (f"NeRF-SH CPU preset, steady state: {args.resume} from step {r['from_step']}, "
                f"{r['steps']} steps: {r['rays_per_s']:.0f} rays/s, {r['samples_per_s']:.0f} "
                f"samples/s, {r['samples_per_ray']:.2f} samples/ray (load average "
                f"{machine['loadavg_before'][0]:.2f} → {machine['loadavg'][0]:.2f})")
        return _finish(out, text, args.out)
    with tempfile.TemporaryDirectory(prefix="nerf_speed_") as tmp:
        root = Path(tmp)
        out["cpu_train"] = bench_cpu(args.data, args.downscale, args.cpu_minutes, root)
        out["paper_train_fp32"] = bench_paper(args.data, args.downscale, args.paper_steps, "off",
                                              root)
        out["paper_train_bf16"] = bench_paper(args.data, args.downscale, args.paper_steps,
                                              "bf16", root)
        out["paper_render_800"] = bench_render(out["paper_train_fp32"]["run"], args.data,
                                               args.render_rows)
        out["cpu_render_800"] = bench_render(out["cpu_train"]["run"], args.data, None)
    out["machine"] = machine = machine_info(machine["loadavg"])
    c, p, pb = out["cpu_train"], out["paper_train_fp32"], out["paper_train_bf16"]
    pr, cr = out["paper_render_800"], out["cpu_render_800"]
    lines = [
        f"NeRF-SH speed — {machine['cpu_count']} cores, torch {machine['torch']}, numba "
        f"{machine['numba']}, load average {machine['loadavg_before'][0]:.2f} → "
        f"{machine['loadavg'][0]:.2f}",
        "",
        "| preset | training rays/s | training samples/s | samples/ray | 800×800 render s/frame |",
        "|---|---|---|---|---|",
        f"| cpu (hash grid, occupancy, bf16) | {c['rays_per_s']:.0f} | {c['samples_per_s']:.0f} "
        f"| {c['samples_per_ray']:.1f} | {cr['seconds_per_frame']:.2f} |",
        f"| paper (8×256 PE MLP, 64+128, fp32) | {p['rays_per_s']:.0f} | "
        f"{p['samples_per_s']:.0f} | {p['samples_per_ray']:.0f} | "
        f"{pr['seconds_per_frame']:.0f} (from {pr['rows_rendered']} rows) |",
        f"| paper, bf16 autocast | {pb['rays_per_s']:.0f} | {pb['samples_per_s']:.0f} | "
        f"{pb['samples_per_ray']:.0f} | — |",
        "",
        f"cpu preset vs paper preset training: {c['rays_per_s'] / p['rays_per_s']:.0f}x rays/s; "
        f"render: {pr['seconds_per_frame'] / cr['seconds_per_frame']:.0f}x faster per frame",
    ]
    return _finish(out, "\n".join(lines), args.out)


def _finish(out: dict, text: str, path: str) -> int:
    print(text)
    out["table"] = text
    print(f"\nwrote {write_json(path, out)}")
    return 0


if __name__ == "__main__":
    from plenoctree import runtime

    runtime.configure()         # as the CLI: before torch / numba load (OMP_WAIT_POLICY, malloc)
    sys.exit(main())
