"""The fixed-shape training step (issue 47, ``nerf/fixed.py``) against the cpu preset's
marching waves, at equal steps and sample budget: quality per step on the CPU.

Method: the cpu preset (2^17 trained samples a step) on lego at ``--downscale`` (400² by
default) for ``--steps`` steps, one run per variant in this process, one after the other, from
the same seed; then the validation PSNR on ``--val-views`` test views (evenly spaced, the
trainer's own validation). Variants:

- ``waves``: the cpu preset as it is (marching waves, early ray termination at
  ``train_stop_thresh``; host round trips each wave) — the baseline, measured in the same run;
- ``fixed k=1``: ``fixed_step`` with ``fixed_candidates = 1``: no early termination, every
  marched sample trained (the step before early termination);
- ``fixed k=K`` for each ``--candidates K``: ``fixed_step`` with early termination, ``K × 2^17``
  candidate slots, a density pass without gradients over them.

Columns: validation PSNR (dB), wall seconds of the whole run (set-up, steps, the final
validation; the machine may be shared: the load average is printed), and from the last log
row the rays a step and the samples a ray trained with gradients (``samples_per_ray``; for
the fixed step the budget over the rays, empty slots included). The JSON also has each fixed
run's marched candidates and kept samples a ray (``spr_marched``, ``spr`` of the trainer's
state: running means) and the log rows.
The GPU speed of the fixed step is not measured here (``gpu_bench.py``).

Usage::

    python benchmarks/fixed_vs_waves.py [--data DIR] [--steps 300] [--candidates 8]
        [--out SCRATCH_DIR] [--json FILE.json]

~6 minutes on 2 cores at the defaults.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from _bench import REPO, RESULTS, machine_info, machine_line, markdown_table, write_json

DEFAULT_DATA = (REPO / ".." / "shared" / "data" / "nerf_synthetic" / "lego").resolve()


def variants(candidates: list[int]) -> list[tuple[str, dict]]:
    """``(name, config overrides)`` of every run, the baseline first."""
    out = [("waves", {"fixed_step": False}),
           ("fixed k=1 (no early termination)", {"fixed_step": True, "fixed_candidates": 1})]
    out += [(f"fixed k={k} (early termination)", {"fixed_step": True, "fixed_candidates": k})
            for k in candidates]
    return out


def run_variant(name: str, overrides: dict, args: argparse.Namespace, scratch: Path) -> dict:
    """Train one variant into a fresh folder under ``scratch``; its figures."""
    from plenoctree.nerf import preset, train
    from plenoctree.nerf.checkpoint import read_checkpoint

    out = scratch / name.split(" ")[0].replace("=", "")
    shutil.rmtree(out, ignore_errors=True)
    cfg = preset("cpu")
    cfg.data, cfg.out, cfg.downscale = str(args.data), str(out), args.downscale
    cfg.max_steps, cfg.val_views, cfg.val_every_s = args.steps, args.val_views, 0.0
    cfg.preview_every_s, cfg.ckpt_every_s, cfg.threads = 0.0, 0.0, args.threads
    for key, value in overrides.items():
        setattr(cfg, key, value)
    t0 = time.perf_counter()
    res = train(cfg, quiet=True)
    wall = time.perf_counter() - t0
    last = res.log["train"][-1]
    state = read_checkpoint(res.run_dir).get("trainer", {})
    row = {"variant": name, "overrides": overrides, "val_psnr": res.val_psnr, "wall_s": wall,
           "train_s": res.train_time_s, "rays_per_step": last["rays"],
           "samples_per_ray": last["samples_per_ray"],
           "spr_marched": state.get("spr_marched") if cfg.fixed_step else None,
           "spr_trained": state.get("spr") if cfg.fixed_step else None,
           "log": res.log["train"]}
    print(f"  {name}: {res.val_psnr:.2f} dB, {wall:.0f} s, {last['rays']} rays, "
          f"{last['samples_per_ray']:.1f} samples a ray", file=sys.stderr, flush=True)
    return row


def table(rows: list[dict]) -> str:
    """The markdown table of the runs (the PSNR against the waves' beside it)."""
    base = rows[0]["val_psnr"]
    body = [(r["variant"], f"{r['val_psnr']:.2f} ({r['val_psnr'] - base:+.2f})",
             f"{r['wall_s']:.0f}", f"{r['rays_per_step']:,}", f"{r['samples_per_ray']:.1f}")
            for r in rows]
    return markdown_table(["variant", "val PSNR dB (vs waves)", "wall s", "rays/step",
                           "samples/ray"], body)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA,
                    help="the lego scene (default: ../shared/data/nerf_synthetic/lego from the "
                         "repository's root)")
    ap.add_argument("--steps", type=int, default=300, help="training steps of every run")
    ap.add_argument("--candidates", type=int, nargs="+", default=[8],
                    help="fixed_candidates of the early-terminating runs")
    ap.add_argument("--downscale", type=int, default=2, help="lego's downscale (2: 400²)")
    ap.add_argument("--val-views", type=int, default=3, help="test views validated")
    ap.add_argument("--threads", type=int, default=0, help="the trainer's threads (0: all)")
    ap.add_argument("--out", type=Path, default=None,
                    help="scratch folder of the runs (default: a temporary folder, removed)")
    ap.add_argument("--json", type=Path, default=RESULTS / "fixed_vs_waves.json",
                    help="JSON results file (default benchmarks/results/fixed_vs_waves.json)")
    args = ap.parse_args(argv)
    if not (args.data / "transforms_train.json").exists():
        raise SystemExit(f"no lego scene at {args.data}: pass --data DIR")
    load = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="fixed_vs_waves_") as tmp:
        scratch = args.out or Path(tmp)
        rows = [run_variant(name, over, args, scratch)
                for name, over in variants(args.candidates)]
    machine = machine_info(load)
    text = (f"lego {800 // args.downscale}², cpu preset, 2^17 samples a step, {args.steps} "
            f"steps, {args.val_views} test views\n\n{table(rows)}\n\n{machine_line(machine)}")
    print(text)
    out = {"benchmark": "fixed_vs_waves", "machine": machine, "args": vars(args),
           "rows": rows, "table": text}
    print(f"\nwrote {write_json(args.json, out)}")
    return 0


if __name__ == "__main__":
    from plenoctree import runtime

    runtime.configure()
    sys.exit(main())
